"""One robot's map as the map server keeps it: grid, trajectory, dirty region, and (with loop
closure on) the keyframes to redraw it from."""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Callable

import numpy as np
from numpy.typing import NDArray
from scanflow.backend.loops import draw_keyframes
from scanflow.frontend import insert_scan
from scanflow.frontend.trajectory import TrajectoryStore
from scanflow.geometry import Pose2D
from scanflow.maps.grid import CellBox
from scanflow.maps.matching_map import MatchingMap
from scanflow.maps.occupancy import OccupancyGrid, OccupancyParams
from scanflow.wire import (
    ENDED_RUNS_KEPT,
    MapChangedMessage,
    MapInsertMessage,
    MapRedrawMessage,
    MapStateMessage,
    PoseEstimateMessage,
)

from services.mapserver.keyframes import Keyframes
from services.mapserver.snapshot import Snapshot

MAX_HELD_POSES = 64  # poses of a run the map is not of yet, held until its first insert


class RobotMap:
    """Inserts the tracker's scans at the poses it inserted them, and records its poses.

    Inserts and poses come on two subscribers (no order between them); an insert carries its
    pose, so only the order of the inserts matters, and one subscriber keeps that. A redraw
    comes on the inserts' subscriber, between the inserts the tracker made around it; it also
    carries the whole corrected path up to its scan: a pose of a scan it covers is not added
    again, and poses of later scans that came before it are kept. A tracker's whole map (its
    answer for inserts it no longer keeps) replaces the map and the path it covers in the same
    way, and the inserts it holds that come after it are skipped (`holds`).
    """

    def __init__(
        self, robot_id: str, new_grid: Callable[[], OccupancyGrid], snap: Snapshot | None = None,
        keep_keyframes: bool = False,
    ) -> None:
        """`new_grid`: a robot's starting map (the matchers' prior map, or an empty grid with
        their resolution), also after a reset; a snapshot is resumed as it was saved.
        `keep_keyframes`: keep the scan of every insert flagged a keyframe, so that redraws
        can be followed."""
        self.robot_id = robot_id
        self.new_grid = new_grid
        self.keep_keyframes = keep_keyframes
        self.map = MatchingMap(snap.grid if snap else new_grid())
        self.trajectory = (
            TrajectoryStore() if snap is None else TrajectoryStore.of(snap.stamps_s, snap.poses)
        )
        self.keyframes: Keyframes | None = None
        if keep_keyframes:
            saved = snap.keyframes if snap is not None else None
            # A resumed map without its keyframes (unreadable, or loop closure was off) holds
            # scans no kept keyframe would: none are kept, so a resumed matcher's redraw of the
            # later ones alone cannot wipe the rest; a new run (`reset`) keeps them again.
            if saved is not None:
                self.keyframes = saved
            elif snap is None or snap.last_insert_seq < 0:
                self.keyframes = Keyframes()
        # The tracker's run this map is of (its token; 0: not known yet, or a snapshot older
        # than tokens), the runs it replaced, whose late messages are dropped, and the poses
        # of another run that came before any insert of it (see `start_run`).
        self.run = 0 if snap is None else snap.run
        self.ended_runs: list[int] = [] if snap is None else list(snap.ended_runs)
        self.held_poses: deque[PoseEstimateMessage] = deque()
        self.redrawn_seq = -1 if snap is None else snap.redrawn_seq
        self.last_seq = -1 if snap is None else snap.last_seq
        self.last_insert_seq = -1 if snap is None else snap.last_insert_seq
        # (stamp, odometry pose) of the last estimate that had one: a restarted matcher
        # predicts the next scan from the path's end with it (`odom_at_path_end`).
        self.last_odom: tuple[float, Pose2D] | None = None if snap is None else snap.last_odom
        # The kinds of message this run has had: a run resumed from a snapshot had both, so a
        # replay (seqs back) replaces it rather than adding to its map and path.
        self.streams: set[str] = set() if snap is None else {"insert", "pose"}
        self.dirty: CellBox | None = None
        self.held: tuple[int, int] | None = None  # inserts (after, through] in a taken state
        # The state its snapshot holds; None: none of this run (its file replaced or moved).
        self.saved: tuple[int, int] | None = self.state

    @property
    def state(self) -> tuple[int, int]:
        """(map revision, last pose seq): what a snapshot must capture."""
        return (self.map.revision, self.last_seq)

    def start_run(self, run: int) -> list[PoseEstimateMessage]:
        """Start afresh as the map of the tracker's run `run`, which an insert or redraw of it
        showed (their stream is in order, so a run's first one follows every one of the run
        before), or a pose of it where the map's run inserted nothing (localising on a prior
        map); the run replaced is ended. Returns the poses of `run` held so far, to apply."""
        if self.run:
            self.ended_runs = [*self.ended_runs, self.run][-ENDED_RUNS_KEPT:]
        self.reset()
        self.run = run
        mine = [pose for pose in self.held_poses if pose.run == run]
        self.held_poses = deque(
            pose for pose in self.held_poses if pose.run != run and pose.run not in self.ended_runs
        )
        return mine

    def hold(self, pose: PoseEstimateMessage) -> bool:
        """Keep a pose of a run other than the map's (not one it replaced): poses travel apart
        from the inserts, so it may come before its run's first insert, or be a late one of a
        run this map never was. False when the oldest held pose made room for it."""
        full = len(self.held_poses) >= MAX_HELD_POSES
        if full:
            self.held_poses.popleft()
        self.held_poses.append(pose)
        return not full

    def reset(self) -> None:
        """The robot's stream restarted (a replay, or a new run: `start_run`): start its map
        and trajectory afresh."""
        self.map = MatchingMap(self.new_grid())
        self.trajectory = TrajectoryStore()
        self.keyframes = Keyframes() if self.keep_keyframes else None
        self.redrawn_seq = -1
        self.last_seq = -1
        self.last_insert_seq = -1
        self.last_odom = None
        self.streams.clear()
        self.saved = None  # a new run reaching the old one's (revision, seq) is saved still
        self.dirty = None
        self.held = None

    def apply(self, pose: PoseEstimateMessage) -> None:
        """Record the pose in the trajectory (unless a redraw's path already holds it)."""
        self.last_seq = pose.seq
        self.last_odom = None if pose.odom_pose is None else (pose.stamp_s, pose.odom_pose)
        if pose.seq > self.redrawn_seq:
            self.trajectory.append(pose.stamp_s, pose.pose)

    def odom_at_path_end(self) -> Pose2D | None:
        """The odometry pose of the path's last pose, None unless the last estimate had one
        and the path ends at its stamp (a taken map state may end elsewhere)."""
        stamps = self.trajectory.stamps_s
        if self.last_odom is None or len(stamps) == 0 or stamps[-1] != self.last_odom[0]:
            return None
        return self.last_odom[1]

    def insert(self, scan: MapInsertMessage) -> None:
        """The front end's own insertion of the scan (hits and no-return beams) at its pose;
        remembers the touched cells."""
        self.last_insert_seq = scan.seq
        if self.keyframes is not None and scan.keyframe:
            self.keyframes.add(scan)
        result = insert_scan(
            self.map, scan.points, scan.pose, scan.no_return_points, scan.mount
        )
        if result.touched is not None:
            self.dirty = result.touched.union(self.dirty)

    def redraw(self, redraw: MapRedrawMessage, params: OccupancyParams) -> None:
        """The tracker's redraw: the map of every keyframe at its optimised pose on the map
        the robot started on (the prior map, or nothing; a new revision), and the corrected
        path. Raises, changing nothing, when this server does not hold exactly the keyframes
        the redraw names."""
        if self.keyframes is None:
            raise ValueError(
                f"robot {self.robot_id}: a map redraw came, but this map server keeps no "
                "keyframes (SCANFLOW_BACKEND_LOOP_CLOSURE is off here, on in the matcher; or "
                "this run's map was resumed without them)"
            )
        self.keyframes.check(redraw.keyframe_seqs)
        drawn = draw_keyframes(self.keyframes.nodes, redraw.keyframe_poses, params, self.new_grid())
        self._replace_map(drawn.grid)
        self.keyframes.moved(redraw.keyframe_poses)
        self._replace_path(redraw.stamps_s, redraw.poses, redraw.seq)

    def take_state(self, state: MapStateMessage, grid: OccupancyGrid, after: int) -> None:
        """The tracker's whole map `grid`, path and keyframes (`state`), sent for the inserts
        after seq `after` that it no longer keeps: they replace this map, the path they cover
        and the kept keyframes, and the inserts and redraws through `state.insert_seq` that
        come after it are held in them."""
        self._replace_map(grid)
        self._replace_path(state.stamps_s, state.poses, state.seq)
        if self.keep_keyframes and state.keyframes is not None:  # all of the map's keyframes
            self.keyframes = Keyframes.from_message(state.keyframes)
        self.last_insert_seq = state.insert_seq
        self.held = (after, state.insert_seq)

    def holds(self, message: MapInsertMessage | MapRedrawMessage | PoseEstimateMessage) -> bool:
        """Whether an insert or a redraw is in the map already: a taken state holds it."""
        return (
            not isinstance(message, PoseEstimateMessage) and self.held is not None
            and self.held[0] < message.seq <= self.held[1]
        )

    def _replace_map(self, grid: OccupancyGrid) -> None:
        """A new map (the next revision); the regions of the old and the new are dirty."""
        grid.revision = self.map.revision + 1
        for box in (self.map.grid.extent, grid.extent):
            if box is not None:
                self.dirty = box.union(self.dirty)
        self.map = MatchingMap(grid)

    def _replace_path(
        self, stamps_s: NDArray[np.float64], poses: NDArray[np.float64], seq: int
    ) -> None:
        """The path over the stamps it covers becomes `poses` (the tracker's, through scan
        `seq`). Poses of later scans that came before it are in its frame already, and earlier
        ones (before a restarted tracker's first) stay."""
        own_s, own = self.trajectory.stamps_s, self.trajectory.poses
        first_s, last_s = (stamps_s[0], stamps_s[-1]) if len(stamps_s) else (math.inf, math.inf)
        earlier, later = own_s < first_s, own_s > last_s
        self.trajectory = TrajectoryStore.of(
            np.concatenate((own_s[earlier], stamps_s, own_s[later])),
            np.concatenate((own[earlier], poses, own[later])),
        )
        self.redrawn_seq = seq

    def take_change(self, stamp_s: float) -> MapChangedMessage | None:
        """The change notice for everything touched since the last one (None if nothing)."""
        if self.dirty is None:
            return None
        spec = self.map.grid.spec_of(self.dirty)
        self.dirty = None
        return MapChangedMessage(
            robot_id=self.robot_id,
            revision=self.map.revision,
            stamp_s=stamp_s,
            min_x_m=spec.origin_x_m,
            min_y_m=spec.origin_y_m,
            max_x_m=spec.origin_x_m + spec.cols * spec.resolution_m,
            max_y_m=spec.origin_y_m + spec.rows * spec.resolution_m,
        )

    def snapshot(self) -> Snapshot:
        """The robot's state for save_snapshot: map, trajectory, seqs, keyframes, last odometry."""
        return Snapshot(
            self.robot_id,
            self.map.grid,
            self.trajectory.stamps_s,
            self.trajectory.poses,
            self.last_seq,
            self.keyframes,
            self.redrawn_seq,
            self.last_insert_seq,
            self.last_odom,
            self.run,
            tuple(self.ended_runs),
        )
