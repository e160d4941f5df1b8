"""ROS 1 and ROS 2 bag reader (no ROS installation, via the pure-Python `rosbags` package).

Streams, in bag time order:
- `sensor_msgs/msg/LaserScan` -> `LaserScan`: `header.stamp` -> `stamp_s` (first beam, as in
  ROS), `scan_time` -> `scan_duration_s`, `time_increment` > 0 -> measured per-beam offsets
  `i * time_increment` (otherwise offsets are left to be assumed uniform), intensities kept
  when there is one per beam;
- `nav_msgs/msg/Odometry` -> `Odometry` (pose yaw from the quaternion, twist as velocity);
- `tf2_msgs/msg/TFMessage` (or ROS 1 `tf/tfMessage`) transforms `odom_frame -> base_frame`
  -> `Odometry` without velocity.
By default (`topics=None`) all LaserScan and Odometry topics are read, and the tf topics only
when the bag has no Odometry topic (so odometry is never counted twice).

Frame names match with a leading "/" and a namespace ignored ("/robot1/odom" is "odom").

Sensor mount (`LaserScan.mount`): the transform base_frame -> the scan's frame_id, composed
through intermediate frames (base_link -> base_laser_link -> laser) and projected to the plane
(x, y, yaw). Before streaming, a pre-pass reads every message on the `tf_static` topic(s) (few,
latched, and may be recorded after the first scans; a later transform of a child frame replaces
an earlier one), then, only when a scan topic's frame (that of its first message) is not yet
placed, the `tf` topic(s) until it is: ROS 1 static_transform_publisher sends fixed transforms
there. A child frame's first transform on `tf` is taken as fixed, and never overrides
`tf_static`. Mounts do not depend on `topics` or on odometry; one tree serves the whole bag.
The chain is walked up by tf2 names (leading "/" ignored) to the first frame whose bare name is
`base_frame`. No chain to the base frame (or the scan frame is the base frame) -> identity.
A scan is placed when its plane is level (within `MAX_TILT_RAD` of the base's plane; the small
tilt is dropped) or upside down (rolled or pitched by pi), which is handled exactly by mirroring
the scan: its angles are negated (`angle_increment_rad` < 0), so beams keep their order and
times. Any other tilt has no 2D mount: such scans are skipped and recorded as errors naming the
frame.

The robot id is `robot_id` when given, else the first segment of a namespaced topic
("/robot1/scan" -> "robot1"), else "robot". Odometry on a global topic ("/odom", "/tf") goes
to the scans' robot when every scan read is of one robot, so a robot recorded under its
namespace with a global tf still gets its odometry; with several robots' scans, an odom -> base
transform on a global tf topic goes to the robot its child frame's namespace names
("robot2/base_link" -> "robot2"), if that robot has scans, so each robot of a shared tf gets its
own odometry (an Odometry message likewise, by its child_frame_id).

Messages that make an invalid scan (e.g. range_max below range_min) are skipped, recorded in
`BagReader.errors` and passed to `on_error` if given (or raise `BagFormatError` with
`strict=True`). A bag that cannot be opened, or read on past some point (damaged, cut short),
raises `BagFormatError` naming it; the records before stand.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable, Iterable, Iterator, Sequence
from contextlib import suppress
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray
from rosbags.highlevel import AnyReader, AnyReaderError
from rosbags.interfaces import Connection
from rosbags.typesys import Stores, get_typestore

from scanflow.geometry import IDENTITY, Pose2D
from scanflow.scan import LaserScan, Odometry, ScanError

SCAN_TYPE = "sensor_msgs/msg/LaserScan"
ODOM_TYPE = "nav_msgs/msg/Odometry"
TF_TYPES = ("tf2_msgs/msg/TFMessage", "tf/msg/tfMessage")
MAX_RECORDED_ERRORS = 1000
STATIC_TF_TOPIC, TF_TOPIC = "tf_static", "tf"  # last segment of the tf topics' names
DEFAULT_FRAME_ID = "laser"  # for scans with an empty header.frame_id
DEFAULT_ROBOT_ID = "robot"  # for messages no topic or frame tells the robot of
MAX_TILT_RAD = math.radians(2.0)  # a projection error below 1 - cos(2 deg) = 0.06 %


class BagFormatError(ValueError):
    """A bag message that cannot be turned into a scan or odometry sample (strict mode)."""


@dataclass(frozen=True)
class BagScan:
    """A laser scan read from a bag, with its topic and bag (receive) time."""

    scan: LaserScan
    topic: str
    bag_time_s: float


@dataclass(frozen=True)
class BagOdom:
    """An odometry sample read from a bag (nav_msgs/Odometry or a tf transform)."""

    odom: Odometry
    topic: str
    bag_time_s: float


def stamp_to_s(stamp: Any) -> float:
    """A ROS time (sec, nanosec) in seconds."""
    return float(stamp.sec) + 1e-9 * float(stamp.nanosec)


def yaw_from_quaternion(q: Any) -> float:
    """Heading (rotation about z) of a quaternion with fields x, y, z, w, of any norm (as tf2
    normalises them); ValueError when it is zero."""
    w, x, y, z = q.w, q.x, q.y, q.z
    if not w * w + x * x + y * y + z * z > 0.0:
        raise ValueError(f"quaternion is zero or not finite: {q}")
    return math.atan2(2.0 * (w * z + x * y), w * w + x * x - y * y - z * z)


def _bare_frame(frame_id: str) -> str:
    return frame_id.rsplit("/", 1)[-1]


def _tf_frame(frame_id: str) -> str:
    """A frame name as tf2 compares them: without a leading "/"."""
    return frame_id.lstrip("/")


def transform_matrix(tf: Any) -> NDArray[np.float64]:
    """geometry_msgs/Transform -> 4x4 homogeneous matrix (quaternion normalised)."""
    q = np.array([tf.rotation.w, tf.rotation.x, tf.rotation.y, tf.rotation.z], dtype=np.float64)
    t = np.array([tf.translation.x, tf.translation.y, tf.translation.z], dtype=np.float64)
    norm = float(np.linalg.norm(q))
    if not (np.all(np.isfinite(t)) and math.isfinite(norm) and norm > 0.0):
        raise ValueError(f"transform is not finite or its quaternion is zero: {tf}")
    w, x, y, z = q / norm
    m = np.eye(4)
    m[:3, :3] = (
        (1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)),
        (2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)),
        (2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)),
    )
    m[:3, 3] = t
    return m


@dataclass(frozen=True)
class Mount:
    """A scan frame's place on the robot in 2D: its planar pose, and whether it is upside down."""

    pose: Pose2D = IDENTITY
    mirrored: bool = False


def planar_mount(matrix: NDArray[np.float64], frame: str) -> Mount:
    """The 2D mount of a 4x4 T_base_frame; ValueError naming `frame` if its plane is tilted.

    Upside down, R = Rz(yaw) * diag(1, -1, -1): the scan is the mirrored one, turned by yaw.
    Either way yaw is the heading of the sensor's x axis.
    """
    r = matrix[:3, :3]
    level = math.cos(MAX_TILT_RAD)
    if abs(r[2, 2]) < level:
        tilt = math.degrees(math.acos(min(1.0, abs(r[2, 2]))))
        raise ValueError(
            f"scan frame {frame!r} is tilted {tilt:.1f} deg from the base frame's plane "
            f"(more than {math.degrees(MAX_TILT_RAD):.1f} deg): no 2D mount represents it"
        )
    yaw = math.atan2(r[1, 0], r[0, 0])
    return Mount(Pose2D(matrix[0, 3], matrix[1, 3], yaw), mirrored=bool(r[2, 2] < 0))


class TransformTree:
    """Fixed transforms parent -> child from tf messages, and the mounts they give scan frames."""

    def __init__(self, base_frame: str) -> None:
        self.base_frame = base_frame
        self._links: dict[str, tuple[str, NDArray[np.float64]]] = {}

    def add(self, msg: Any, *, override: bool) -> None:
        """Take a TFMessage's transforms (all or, on a ValueError, none); `override` lets them
        replace known child frames."""
        links = {
            _tf_frame(tf.child_frame_id): (
                _tf_frame(tf.header.frame_id),
                transform_matrix(tf.transform),
            )
            for tf in msg.transforms
        }
        for child, link in links.items():
            if override or child not in self._links:
                self._links[child] = link

    def chain(self, frame_id: str) -> NDArray[np.float64] | None:
        """T_base_frame (4x4) composed up the tree, or None when no chain reaches the base."""
        frame, matrix, seen = _tf_frame(frame_id), np.eye(4), set()
        while _bare_frame(frame) != self.base_frame:
            if frame in seen or frame not in self._links:
                return None
            seen.add(frame)
            frame, link = self._links[frame]
            matrix = link @ matrix
        return matrix

    def mount(self, frame_id: str) -> Mount:
        """The scan frame's 2D mount: identity without a chain; ValueError when it is tilted."""
        matrix = self.chain(frame_id)
        return Mount() if matrix is None else planar_mount(matrix, frame_id)


def _namespace(name: str) -> str | None:
    """The first segment of a namespaced topic or frame ("/robot1/scan" -> "robot1")."""
    segments = [s for s in name.split("/") if s]
    return segments[0] if len(segments) > 1 else None


@dataclass(frozen=True)
class RobotIds:
    """Whose a message is, when the reader was given no robot id (module docstring)."""

    scans: frozenset[str]  # the robots of the scan topics read

    @classmethod
    def of_connections(cls, connections: Iterable[Connection]) -> RobotIds:
        scan_topics = (c.topic for c in connections if c.msgtype == SCAN_TYPE)
        return cls(frozenset(_namespace(t) or DEFAULT_ROBOT_ID for t in scan_topics))

    def of_topic(self, topic: str) -> str:
        """A namespaced topic's robot, else the scans' one robot, else DEFAULT_ROBOT_ID."""
        ns = _namespace(topic)
        if ns is not None:
            return ns
        return next(iter(self.scans)) if len(self.scans) == 1 else DEFAULT_ROBOT_ID

    def of_transform(self, topic: str, child_frame: str) -> str:
        """A transform's robot: on a global topic, the one its child frame's namespace names
        when that robot has scans; else the topic's."""
        ns = _namespace(child_frame)
        if _namespace(topic) is None and ns in self.scans:
            return ns
        return self.of_topic(topic)


def scan_from_msg(msg: Any, robot_id: str, seq: int, mount: Mount = Mount()) -> LaserScan:
    """sensor_msgs/LaserScan -> LaserScan (see the module docstring for the field mapping)."""
    ranges = np.asarray(msg.ranges, dtype=np.float32)
    intensities = np.asarray(msg.intensities, dtype=np.float32)
    offsets = np.arange(ranges.size) * msg.time_increment if msg.time_increment > 0 else None
    sign = -1.0 if mount.mirrored else 1.0
    return LaserScan(
        ranges_m=ranges,
        angle_min_rad=sign * msg.angle_min,
        angle_increment_rad=sign * msg.angle_increment,
        range_min_m=max(0.0, float(msg.range_min)),
        range_max_m=msg.range_max,
        stamp_s=stamp_to_s(msg.header.stamp),
        scan_duration_s=max(0.0, float(msg.scan_time)),
        beam_time_offsets_s=offsets,
        robot_id=robot_id,
        frame_id=msg.header.frame_id or DEFAULT_FRAME_ID,
        intensities=intensities if intensities.size == ranges.size else None,
        seq=seq,
        mount=mount.pose,
    )


def odom_from_msg(msg: Any, robot_id: str, seq: int) -> Odometry:
    """nav_msgs/Odometry -> Odometry (planar part: x, y, yaw; v_x, v_y, omega)."""
    p = msg.pose.pose
    t = msg.twist.twist
    pose = Pose2D(p.position.x, p.position.y, yaw_from_quaternion(p.orientation))
    velocity = (t.linear.x, t.linear.y, t.angular.z)
    return Odometry(stamp_to_s(msg.header.stamp), pose, velocity, robot_id, seq)


class BagReader:
    """Iterates the scans and odometry of one ROS 1 (.bag) or ROS 2 (directory) bag."""

    def __init__(
        self,
        path: str | Path,
        *,
        topics: Sequence[str] | None = None,
        robot_id: str | None = None,
        odom_frame: str = "odom",
        base_frame: str = "base_link",
        strict: bool = False,
        on_error: Callable[[str], None] | None = None,
    ) -> None:
        self.path = Path(path)
        self.on_error = on_error
        self.topics = None if topics is None else list(topics)
        self.robot_id = robot_id
        self.odom_frame = odom_frame
        self.base_frame = base_frame
        self.strict = strict
        self.errors: list[str] = []
        self.error_count = 0

    def _selected(self, connections: Sequence[Connection]) -> list[Connection]:
        if self.topics is not None:
            missing = set(self.topics) - {c.topic for c in connections}
            if missing:
                raise BagFormatError(f"{self.path}: topics not in the bag: {sorted(missing)}")
            return [c for c in connections if c.topic in self.topics]
        wanted = {SCAN_TYPE, ODOM_TYPE}
        if not any(c.msgtype == ODOM_TYPE for c in connections):
            wanted.update(TF_TYPES)
        return [c for c in connections if c.msgtype in wanted]

    def __iter__(self) -> Iterator[BagScan | BagOdom]:
        reader = AnyReader([self.path], default_typestore=get_typestore(Stores.ROS2_HUMBLE))
        try:
            reader.open()
        except AnyReaderError as exc:
            raise BagFormatError(f"cannot open bag {self.path}: {exc}") from exc
        except Exception as exc:  # a damaged bag: whatever rosbags' parsers hit
            raise BagFormatError(
                f"cannot open bag {self.path}: {type(exc).__name__}: {exc}"
            ) from exc
        try:
            connections = self._selected(reader.connections)
            if not connections:  # rosbags reads every connection when given none
                return
            tree = self._transform_tree(reader, connections)
            mounts: dict[str, Mount] = {}
            counts = {SCAN_TYPE: 0, ODOM_TYPE: 0}
            robots = RobotIds.of_connections(connections)
            for conn, time_ns, raw in _messages(reader, connections, self.path):
                robot = self.robot_id or robots.of_topic(conn.topic)
                bag_time_s = time_ns * 1e-9
                try:
                    msg = _deserialize(reader, raw, conn.msgtype)
                    if conn.msgtype == SCAN_TYPE:
                        frame = msg.header.frame_id or DEFAULT_FRAME_ID
                        if frame not in mounts:  # a tilted frame raises, uncached, every time
                            mounts[frame] = tree.mount(frame)
                        scan = scan_from_msg(msg, robot, counts[SCAN_TYPE], mounts[frame])
                        yield BagScan(scan, conn.topic, bag_time_s)
                        counts[SCAN_TYPE] += 1
                    elif conn.msgtype == ODOM_TYPE:
                        owner = self._owner(robots, conn.topic)(_tf_frame(msg.child_frame_id))
                        odom = odom_from_msg(msg, owner, counts[ODOM_TYPE])
                        yield BagOdom(odom, conn.topic, bag_time_s)
                        counts[ODOM_TYPE] += 1
                    elif conn.msgtype in TF_TYPES:
                        owner_of = self._owner(robots, conn.topic)
                        for odom in self._tf_odometry(msg, owner_of, counts[ODOM_TYPE]):
                            yield BagOdom(odom, conn.topic, bag_time_s)
                            counts[ODOM_TYPE] += 1
                except (ScanError, ValueError) as exc:
                    self._report(f"{conn.topic} @ {bag_time_s:.9f} s: {exc}")
        finally:
            reader.close()

    def _transform_tree(
        self, reader: AnyReader, connections: Sequence[Connection]
    ) -> TransformTree:
        """The mounts' pre-pass (module docstring): tf_static, then tf until scans are placed."""
        tree = TransformTree(self.base_frame)
        tf_conns = [c for c in reader.connections if c.msgtype in TF_TYPES]
        static = [c for c in tf_conns if c.topic.rsplit("/", 1)[-1] == STATIC_TF_TOPIC]
        dynamic = [c for c in tf_conns if c.topic.rsplit("/", 1)[-1] == TF_TOPIC]
        if static:  # an empty selection would read every message
            for conn, time_ns, raw in _messages(reader, static, self.path):
                self._add_transforms(reader, tree, conn, time_ns, raw, override=True)
        frames = _first_scan_frames(reader, connections, self.path)

        def placed() -> bool:
            return all(tree.chain(frame) is not None for frame in frames)

        if dynamic and not placed():
            for conn, time_ns, raw in _messages(reader, dynamic, self.path):
                self._add_transforms(reader, tree, conn, time_ns, raw, override=False)
                if placed():
                    break
        return tree

    def _add_transforms(
        self,
        reader: AnyReader,
        tree: TransformTree,
        conn: Connection,
        time_ns: int,
        raw: bytes,
        *,
        override: bool,
    ) -> None:
        try:
            tree.add(_deserialize(reader, raw, conn.msgtype), override=override)
        except ValueError as exc:
            self._report(f"{conn.topic} @ {time_ns * 1e-9:.9f} s: {exc}")

    def _owner(self, robots: RobotIds, topic: str) -> Callable[[str], str]:
        """The robot of a transform on `topic`, from its child frame."""
        if self.robot_id is not None:
            given = self.robot_id
            return lambda _child: given
        return functools.partial(robots.of_transform, topic)

    def _tf_odometry(
        self, msg: Any, owner: Callable[[str], str], seq: int
    ) -> Iterator[Odometry]:
        for tf in msg.transforms:
            parent, child = _bare_frame(tf.header.frame_id), _bare_frame(tf.child_frame_id)
            if parent != self.odom_frame or child != self.base_frame:
                continue
            tr, q = tf.transform.translation, tf.transform.rotation
            pose = Pose2D(tr.x, tr.y, yaw_from_quaternion(q))
            robot_id = owner(_tf_frame(tf.child_frame_id))
            yield Odometry(stamp_to_s(tf.header.stamp), pose, None, robot_id, seq)
            seq += 1

    def _report(self, reason: str) -> None:
        if self.strict:
            raise BagFormatError(f"{self.path}: {reason}")
        self.error_count += 1
        if len(self.errors) < MAX_RECORDED_ERRORS:
            self.errors.append(reason)
        if self.on_error is not None:
            self.on_error(f"{self.path}: {reason}")


def _deserialize(reader: AnyReader, raw: bytes, msgtype: str) -> Any:
    """The message in `raw`; ValueError (reported like any bad message) when it is damaged."""
    try:
        return reader.deserialize(raw, msgtype)
    except AnyReaderError as exc:
        raise ValueError(f"cannot deserialize {msgtype}: {exc}") from None


def _messages(
    reader: AnyReader, connections: Sequence[Connection], path: Path
) -> Iterator[tuple[Connection, int, bytes]]:
    """`reader.messages(connections)`, with a damaged or cut bag's failure (whatever rosbags'
    parsers or sqlite raise) turned into BagFormatError naming the bag and where it broke."""
    messages, last_s = reader.messages(connections=connections), None
    while True:
        try:
            conn, time_ns, raw = next(messages)
            if not (isinstance(time_ns, int) and isinstance(raw, bytes)):
                raise TypeError(f"time {time_ns!r} is no integer or data is no bytes")
        except StopIteration:
            return
        except Exception as exc:
            after = "" if last_s is None else f" after {last_s:.9f} s"
            raise BagFormatError(
                f"{path}: the bag cannot be read{after}: {type(exc).__name__}: {exc}"
            ) from exc
        last_s = time_ns * 1e-9
        yield conn, time_ns, raw


def _first_scan_frames(
    reader: AnyReader, connections: Sequence[Connection], path: Path
) -> set[str]:
    """The frame of each scan topic's first message: the frames the pre-pass must place."""
    frames = set()
    for conn in connections:
        if conn.msgtype != SCAN_TYPE:
            continue
        for _, _, raw in _messages(reader, [conn], path):
            with suppress(ValueError):  # the main pass reports a broken message
                frames.add(_deserialize(reader, raw, SCAN_TYPE).header.frame_id or DEFAULT_FRAME_ID)
            break
    return frames


def read_bag(path: str | Path, **options: Any) -> Iterator[BagScan | BagOdom]:
    """Stream scans and odometry of a ROS 1 or ROS 2 bag in time order; options as `BagReader`."""
    return iter(BagReader(path, **options))
