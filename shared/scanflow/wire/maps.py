"""Map messages: insertions, grid metadata, occupancy windows, exported images, change notices.

Occupancy values follow ROS nav_msgs/OccupancyGrid: -1 unknown, 0 free .. 100 occupied.
Grid geometry is scanflow.maps.grid.GridSpec (row index grows with y, column with x).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar, Literal, Self, TypeGuard

import numpy as np
from numpy.typing import NDArray

from scanflow.geometry import IDENTITY, Pose2D
from scanflow.maps.grid import GridSpec
from scanflow.wire.base import (
    Message,
    check_array,
    check_bytes,
    check_count,
    check_finite,
    check_path,
    check_pose,
    check_robot_id,
    check_seqs,
)
from scanflow.wire.errors import MessageError
from scanflow.wire.schema import (
    BLOB,
    FLAG,
    INT,
    NUMBER,
    PATH,
    POSE,
    TEXT,
    FieldCodec,
    Schema,
    array,
    optional,
)

MAP_IMAGE_FORMATS = ("png", "pgm", "yaml", "zip", "npz")
MapImageFormat = Literal["png", "pgm", "yaml", "zip", "npz"]


def is_map_image_format(fmt: str) -> TypeGuard[MapImageFormat]:
    """True for a format a MapImageMessage carries (one of MAP_IMAGE_FORMATS)."""
    return fmt in MAP_IMAGE_FORMATS


@dataclass(frozen=True, eq=False)
class MapInsertMessage(Message):
    """A scan a tracker put into its map, and the pose it put it at: a map server that inserts
    exactly these points at exactly this pose, in the order they come, builds the same map,
    whatever the order of the pose stream beside it.

    `points` (hits) and `no_return_points` (beams that saw nothing: they clear free space) are
    in the robot's frame at `stamp_s`, float64, bit for bit what the tracker inserted; `pose` is
    the robot's and `mount` the sensor's pose on it, where the rays start. `previous_seq` is the
    seq of the tracker's insert before this one in the same run (None for its first, or when
    the tracker does not know it: a restarted matcher): a map server that holds another last
    insert missed some, and asks the matcher to send them again (`keys.map_key(r, "resend")`).
    `keyframe` is false when the tracker's back end (loop closure, `cull_m`) did not make the
    scan a keyframe: map redraws leave it out, so a map server need not keep it. `run` is the
    tracker's run token (`new_run`; 0: unknown), on its redraws, map states and estimates too:
    a map server holding another run's map starts the robot afresh.
    """

    TYPE = "map_insert"
    WIRE: ClassVar[Schema] = {
        "robot_id": TEXT,
        "seq": INT,
        "stamp_s": NUMBER,
        "pose": POSE,
        "points": array("<f8"),
        "no_return_points": array("<f8"),
        "mount": POSE,
        "previous_seq": optional(INT),
        "keyframe": FLAG,
        "run": INT,
    }
    robot_id: str
    seq: int
    stamp_s: float
    pose: Pose2D
    points: NDArray[np.float64]
    no_return_points: NDArray[np.float64]
    mount: Pose2D = IDENTITY
    previous_seq: int | None = None
    keyframe: bool = True
    run: int = 0

    def __post_init__(self) -> None:
        check_robot_id(self.robot_id)
        object.__setattr__(self, "seq", check_count("seq", self.seq))
        object.__setattr__(self, "run", check_count("run", self.run))
        object.__setattr__(self, "keyframe", bool(self.keyframe))
        if self.previous_seq is not None:
            previous = check_count("previous_seq", self.previous_seq)
            if previous >= self.seq:
                raise MessageError(f"previous_seq must be below seq {self.seq}, got {previous}")
            object.__setattr__(self, "previous_seq", previous)
        object.__setattr__(self, "stamp_s", check_finite("stamp_s", self.stamp_s))
        check_pose("pose", self.pose)
        check_pose("mount", self.mount)
        for name in ("points", "no_return_points"):
            object.__setattr__(
                self, name, check_array(name, getattr(self, name), np.float64, (None, 2))
            )


@dataclass(frozen=True, eq=False)
class MapRedrawMessage(Message):
    """The back end optimised its pose graph and redrew the tracker's map: the map is now every
    keyframe (the scans of the inserts with `keyframe_seqs`, in that order) at
    `keyframe_poses`, and the robot's path is `poses` at `stamps_s` (every scan so far, the
    one of `seq` last). Sent on the inserts' key, so a map server takes it between the same
    inserts the tracker did; `correction` is T_new_old, the change of the map frame.
    """

    TYPE = "map_redraw"
    BULK = True
    WIRE: ClassVar[Schema] = {
        "robot_id": TEXT,
        "seq": INT,
        "correction": POSE,
        "keyframe_seqs": array("<i8"),
        "keyframe_poses": array("<f8"),
        **PATH,
        "run": INT,
    }
    robot_id: str
    seq: int
    correction: Pose2D
    keyframe_seqs: NDArray[np.int64]
    keyframe_poses: NDArray[np.float64]
    stamps_s: NDArray[np.float64]
    poses: NDArray[np.float64]
    run: int = 0  # the tracker's run (MapInsertMessage.run)

    def __post_init__(self) -> None:
        check_robot_id(self.robot_id)
        object.__setattr__(self, "seq", check_count("seq", self.seq))
        object.__setattr__(self, "run", check_count("run", self.run))
        check_pose("correction", self.correction)
        seqs = check_seqs("keyframe_seqs", self.keyframe_seqs)
        object.__setattr__(self, "keyframe_seqs", seqs)
        object.__setattr__(
            self, "keyframe_poses",
            check_array("keyframe_poses", self.keyframe_poses, np.float64, (len(seqs), 3)),
        )
        check_path(self)


@dataclass(frozen=True, eq=False)
class KeyframesMessage(Message):
    """The keyframes a map server keeps for loop closure (in a ResumeMessage: a matcher resuming
    a robot rebuilds its back end from them; and in its snapshots): keyframe i is the scan of
    seq `seqs[i]` at `stamps_s[i]`, drawn at `poses[i]` with its lidar at `mounts[i]`; its hits
    are the next `hit_counts[i]` rows of `hits`, its no-return points the next
    `miss_counts[i]` rows of `misses`.
    """

    TYPE = "keyframes"
    WIRE: ClassVar[Schema] = {
        "robot_id": TEXT,
        "seqs": array("<i8"),
        "stamps_s": array("<f8"),
        "poses": array("<f8"),
        "mounts": array("<f8"),
        "hit_counts": array("<i8"),
        "hits": array("<f8"),
        "miss_counts": array("<i8"),
        "misses": array("<f8"),
    }
    robot_id: str
    seqs: NDArray[np.int64]
    stamps_s: NDArray[np.float64]
    poses: NDArray[np.float64]
    mounts: NDArray[np.float64]
    hit_counts: NDArray[np.int64]
    hits: NDArray[np.float64]
    miss_counts: NDArray[np.int64]
    misses: NDArray[np.float64]

    def __post_init__(self) -> None:
        check_robot_id(self.robot_id)
        seqs = check_seqs("seqs", self.seqs)
        n = len(seqs)
        checked = {
            "seqs": seqs,
            "stamps_s": check_array("stamps_s", self.stamps_s, np.float64, (n,)),
            "poses": check_array("poses", self.poses, np.float64, (n, 3)),
            "mounts": check_array("mounts", self.mounts, np.float64, (n, 3)),
        }
        for counts, rows in (("hit_counts", "hits"), ("miss_counts", "misses")):
            c = check_array(counts, getattr(self, counts), np.int64, (n,))
            r = check_array(rows, getattr(self, rows), np.float64, (None, 2))
            # Each count within the rows first: a sum of huge ones wraps around int64.
            if np.any(c < 0) or np.any(c > len(r)) or int(c.sum()) != len(r):
                raise MessageError(f"{counts} must be >= 0 and add up to the rows of {rows}")
            checked.update({counts: c, rows: r})
        for name, value in checked.items():
            object.__setattr__(self, name, value)

    def scans(self) -> list[tuple[NDArray[np.float64], NDArray[np.float64]]]:
        """Per keyframe: (hits, no-return points), each (k, 2)."""
        if not len(self.seqs):
            return []
        hits = np.split(self.hits, np.cumsum(self.hit_counts)[:-1])
        misses = np.split(self.misses, np.cumsum(self.miss_counts)[:-1])
        return list(zip(hits, misses, strict=True))


# A message's optional `keyframes` (a KeyframesMessage of the same robot), nested.
KEPT_KEYFRAMES = optional(
    FieldCodec(
        KeyframesMessage.to_fields,
        lambda fields, name: KeyframesMessage.from_fields(fields.nested(name)),
    )
)


def _check_map_path_kept(message: ResumeMessage | MapStateMessage) -> None:
    """Check and set a robot's whole state: `map_npz`, the path and the optional keyframes
    (of the same robot)."""
    object.__setattr__(message, "map_npz", check_bytes("map_npz", message.map_npz))
    check_path(message)
    kept = message.keyframes
    if kept is not None and kept.robot_id != message.robot_id:
        raise MessageError(
            f"keyframes.robot_id must be {message.robot_id!r}, got {kept.robot_id!r}"
        )


@dataclass(frozen=True, eq=False)
class ResumeMessage(Message):
    """What a matcher that meets a robot mid-stream (it restarted) carries on from, taken by
    the map server at one instant: its map (`map_npz`, the native .npz file) at `revision`, the
    path so far (`poses` at `stamps_s`) and, when it keeps them (loop closure), the
    `keyframes`. One answer rather than three queries: a redraw cannot fall between the map and
    the keyframes and leave them in two frames. `odom_pose` (schema version 8) is the odometry
    pose of the path's last pose (None: unknown): the next scan is predicted from there.
    `run` is the run the map holds (MapInsertMessage.run; 0: unknown, the tracker then draws
    a new one): the resumed tracker carries it on.
    """

    TYPE = "resume"
    BULK = True
    WIRE: ClassVar[Schema] = {
        "robot_id": TEXT,
        "revision": INT,
        "map_npz": BLOB,
        **PATH,
        "keyframes": KEPT_KEYFRAMES,
        "odom_pose": optional(POSE),
        "run": INT,
    }
    robot_id: str
    revision: int
    map_npz: bytes
    stamps_s: NDArray[np.float64]
    poses: NDArray[np.float64]
    keyframes: KeyframesMessage | None = None
    odom_pose: Pose2D | None = None
    run: int = 0

    def __post_init__(self) -> None:
        check_robot_id(self.robot_id)
        object.__setattr__(self, "revision", check_count("revision", self.revision))
        object.__setattr__(self, "run", check_count("run", self.run))
        _check_map_path_kept(self)
        if self.odom_pose is not None:
            check_pose("odom_pose", self.odom_pose)


@dataclass(frozen=True, eq=False)
class MapStateMessage(Message):
    """A matcher's whole map of a robot, sent instead of inserts it no longer keeps (a map
    server asked for more than its last few, and the back end's keyframes cannot stand in for
    them: there is no back end, or it culled some of them as keyframes).

    `map_npz` is the tracker's map (the native .npz file), holding every insert up to and
    including seq `insert_seq`. The path (`poses` at `stamps_s`, the one of scan `seq` last)
    is as the map server would have it: the tracker's since it started, corrected at its last
    redraw. With loop closure the message carries the back end's `keyframes` too, at the poses
    they are drawn at, so that the map server follows the next redraw. The map server takes
    it in place of the missing inserts, and skips the inserts, redraws and poses of the scans
    it holds that come after it.
    """

    TYPE = "map_state"
    BULK = True
    WIRE: ClassVar[Schema] = {
        "robot_id": TEXT,
        "seq": INT,
        "insert_seq": INT,
        "map_npz": BLOB,
        **PATH,
        "keyframes": KEPT_KEYFRAMES,
        "run": INT,
    }
    robot_id: str
    seq: int
    insert_seq: int
    map_npz: bytes
    stamps_s: NDArray[np.float64]
    poses: NDArray[np.float64]
    keyframes: KeyframesMessage | None = None
    run: int = 0  # the tracker's run (MapInsertMessage.run)

    def __post_init__(self) -> None:
        check_robot_id(self.robot_id)
        object.__setattr__(self, "seq", check_count("seq", self.seq))
        object.__setattr__(self, "run", check_count("run", self.run))
        insert_seq = check_count("insert_seq", self.insert_seq)
        if insert_seq > self.seq:
            raise MessageError(f"insert_seq must be at most seq {self.seq}, got {insert_seq}")
        object.__setattr__(self, "insert_seq", insert_seq)
        _check_map_path_kept(self)


@dataclass(frozen=True, eq=False)
class MapMetaMessage(Message):
    """Where a robot's map sits and which revision it is (bumped on every map update)."""

    TYPE = "map_meta"
    WIRE: ClassVar[Schema] = {
        "robot_id": TEXT,
        "resolution_m": NUMBER,
        "origin_x_m": NUMBER,
        "origin_y_m": NUMBER,
        "rows": INT,
        "cols": INT,
        "revision": INT,
        "stamp_s": NUMBER,
    }
    robot_id: str
    resolution_m: float
    origin_x_m: float
    origin_y_m: float
    rows: int
    cols: int
    revision: int
    stamp_s: float

    def __post_init__(self) -> None:
        check_robot_id(self.robot_id)
        object.__setattr__(self, "rows", check_count("rows", self.rows))
        object.__setattr__(self, "cols", check_count("cols", self.cols))
        object.__setattr__(self, "revision", check_count("revision", self.revision))
        object.__setattr__(self, "stamp_s", check_finite("stamp_s", self.stamp_s))
        for name in ("resolution_m", "origin_x_m", "origin_y_m"):
            object.__setattr__(self, name, check_finite(name, getattr(self, name)))
        if self.resolution_m <= 0:
            raise MessageError(f"resolution_m must be > 0, got {self.resolution_m}")

    @property
    def spec(self) -> GridSpec:
        """The map's layout as a GridSpec (origin, resolution, rows, cols)."""
        return GridSpec(self.origin_x_m, self.origin_y_m, self.resolution_m, self.rows, self.cols)

    @classmethod
    def from_spec(cls, robot_id: str, spec: GridSpec, revision: int, stamp_s: float) -> Self:
        """The meta of a map laid out as `spec`, at `revision` and `stamp_s`."""
        return cls(
            robot_id=robot_id,
            resolution_m=spec.resolution_m,
            origin_x_m=spec.origin_x_m,
            origin_y_m=spec.origin_y_m,
            rows=spec.rows,
            cols=spec.cols,
            revision=revision,
            stamp_s=stamp_s,
        )


@dataclass(frozen=True, eq=False)
class MapRegionMessage(Message):
    """A window of a map: `occupancy[i, j]` is cell (row0 + i, col0 + j) of the grid in `meta`."""

    TYPE = "map_region"
    BULK = True
    WIRE: ClassVar[Schema] = {
        "meta": FieldCodec(
            MapMetaMessage.to_fields,
            lambda fields, name: MapMetaMessage.from_fields(fields.nested(name)),
        ),
        "row0": INT,
        "col0": INT,
        "occupancy": array("|i1"),
    }
    meta: MapMetaMessage
    row0: int
    col0: int
    occupancy: NDArray[np.int8]

    def __post_init__(self) -> None:
        if not isinstance(self.meta, MapMetaMessage):
            raise MessageError(f"meta must be a MapMetaMessage, got {type(self.meta).__name__}")
        row0 = check_count("row0", self.row0)
        col0 = check_count("col0", self.col0)
        occ = check_array("occupancy", self.occupancy, np.int8, (None, None))
        if row0 + occ.shape[0] > self.meta.rows or col0 + occ.shape[1] > self.meta.cols:
            raise MessageError(
                f"occupancy window rows {row0}..{row0 + occ.shape[0]}, cols {col0}.."
                f"{col0 + occ.shape[1]} exceeds the {self.meta.rows}x{self.meta.cols} grid"
            )
        if occ.size and (occ.min() < -1 or occ.max() > 100):
            raise MessageError(
                f"occupancy values must be -1 or 0..100, got range {occ.min()}..{occ.max()}"
            )
        object.__setattr__(self, "row0", row0)
        object.__setattr__(self, "col0", col0)
        object.__setattr__(self, "occupancy", occ)

    @property
    def window_spec(self) -> GridSpec:
        """The geometry of the window itself (its own origin and size)."""
        meta = self.meta
        return GridSpec(
            meta.origin_x_m + self.col0 * meta.resolution_m,
            meta.origin_y_m + self.row0 * meta.resolution_m,
            meta.resolution_m,
            int(self.occupancy.shape[0]),
            int(self.occupancy.shape[1]),
        )


@dataclass(frozen=True, eq=False)
class MapImageMessage(Message):
    """An exported map file (`format` tells which exporter wrote `data`)."""

    TYPE = "map_image"
    BULK = True
    WIRE: ClassVar[Schema] = {"robot_id": TEXT, "revision": INT, "format": TEXT, "data": BLOB}
    robot_id: str
    revision: int
    format: MapImageFormat
    data: bytes

    def __post_init__(self) -> None:
        check_robot_id(self.robot_id)
        object.__setattr__(self, "revision", check_count("revision", self.revision))
        if self.format not in MAP_IMAGE_FORMATS:
            raise MessageError(f"format must be one of {MAP_IMAGE_FORMATS}, got {self.format!r}")
        object.__setattr__(self, "data", check_bytes("data", self.data))


@dataclass(frozen=True, eq=False)
class MapChangedMessage(Message):
    """A map reached `revision`; cells inside the world box [min, max] (metres) changed."""

    TYPE = "map_changed"
    WIRE: ClassVar[Schema] = {
        "robot_id": TEXT,
        "revision": INT,
        "stamp_s": NUMBER,
        "min_x_m": NUMBER,
        "min_y_m": NUMBER,
        "max_x_m": NUMBER,
        "max_y_m": NUMBER,
    }
    robot_id: str
    revision: int
    stamp_s: float
    min_x_m: float
    min_y_m: float
    max_x_m: float
    max_y_m: float

    def __post_init__(self) -> None:
        check_robot_id(self.robot_id)
        object.__setattr__(self, "revision", check_count("revision", self.revision))
        for name in ("stamp_s", "min_x_m", "min_y_m", "max_x_m", "max_y_m"):
            object.__setattr__(self, name, check_finite(name, getattr(self, name)))
        if self.min_x_m > self.max_x_m or self.min_y_m > self.max_y_m:
            raise MessageError(
                f"dirty box min ({self.min_x_m}, {self.min_y_m}) exceeds max "
                f"({self.max_x_m}, {self.max_y_m})"
            )
