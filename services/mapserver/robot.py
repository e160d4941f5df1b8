"""One robot's map as the map server keeps it: grid, trajectory, dirty region."""

from __future__ import annotations

from collections.abc import Callable

from scanflow.frontend import insert_scan
from scanflow.frontend.trajectory import TrajectoryStore
from scanflow.geometry import Pose2D
from scanflow.maps.grid import CellBox
from scanflow.maps.matching_map import MatchingMap
from scanflow.maps.occupancy import OccupancyGrid
from scanflow.wire import MapChangedMessage, MapInsertMessage, PoseEstimateMessage

from services.mapserver.snapshot import Snapshot


class RobotMap:
    """Inserts the tracker's scans at the poses it inserted them, and records its poses.

    Inserts and poses come on two subscribers (no order between them); an insert carries its
    pose, so only the order of the inserts matters, and one subscriber keeps that.
    """

    def __init__(
        self, robot_id: str, new_grid: Callable[[], OccupancyGrid], snap: Snapshot | None = None
    ) -> None:
        """`new_grid`: a robot's starting map (the matchers' prior map, or an empty grid with
        their resolution), also after a reset; a snapshot is resumed as it was saved."""
        self.robot_id = robot_id
        self.new_grid = new_grid
        self.map = MatchingMap(snap.grid if snap else new_grid())
        self.trajectory = TrajectoryStore()
        if snap is not None:
            for stamp_s, row in zip(snap.stamps_s, snap.poses, strict=True):
                self.trajectory.append(float(stamp_s), Pose2D.from_array(row))
        self.last_seq = -1 if snap is None else snap.last_seq
        self.last_insert_seq = -1
        self.streams: set[str] = set()  # the kinds of message this run has had
        self.dirty: CellBox | None = None
        self.saved = self.state

    @property
    def state(self) -> tuple[int, int]:
        """(map revision, last pose seq): what a snapshot must capture."""
        return (self.map.revision, self.last_seq)

    def reset(self) -> None:
        """The robot's stream restarted (a replay): start its map and trajectory afresh."""
        self.map = MatchingMap(self.new_grid())
        self.trajectory = TrajectoryStore()
        self.last_seq = -1
        self.last_insert_seq = -1
        self.streams.clear()
        self.dirty = None

    def apply(self, pose: PoseEstimateMessage) -> None:
        """Record the pose in the trajectory."""
        self.last_seq = pose.seq
        self.trajectory.append(pose.stamp_s, pose.pose)

    def insert(self, scan: MapInsertMessage) -> None:
        """The front end's own insertion of the scan (hits and no-return beams) at its pose;
        remembers the touched cells."""
        self.last_insert_seq = scan.seq
        result = insert_scan(
            self.map, scan.points, scan.pose, scan.no_return_points, scan.mount
        )
        if result.touched is not None:
            self.dirty = result.touched.union(self.dirty)

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
        return Snapshot(
            self.robot_id,
            self.map.grid,
            self.trajectory.stamps_s,
            self.trajectory.poses,
            self.last_seq,
        )
