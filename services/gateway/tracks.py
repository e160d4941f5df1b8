"""Bounded per-robot caches of the pose estimates seen on the bus, and pose lookup by time."""

from __future__ import annotations

import threading
import time
from collections import deque
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray
from scanflow.geometry import Pose2D
from scanflow.wire import PoseEstimateMessage

from services.common.robots import RobotLimit


def pose_at(
    stamps_s: NDArray[np.float64], poses: NDArray[np.float64], stamp_s: float
) -> tuple[Pose2D, int] | None:
    """SE(2) interpolation of an (N, 3) trajectory at `stamp_s`, with the index of the estimate
    before it; None outside [stamps_s[0], stamps_s[-1]]."""
    if len(stamps_s) == 0 or not stamps_s[0] <= stamp_s <= stamps_s[-1]:
        return None
    i = int(np.searchsorted(stamps_s, stamp_s, side="right")) - 1
    if i >= len(stamps_s) - 1:
        return Pose2D.from_array(poses[-1]), len(stamps_s) - 1
    span_s = stamps_s[i + 1] - stamps_s[i]
    fraction = 0.0 if span_s <= 0 else (stamp_s - stamps_s[i]) / span_s
    a, b = Pose2D.from_array(poses[i]), Pose2D.from_array(poses[i + 1])
    return a.interpolate(b, fraction), i


@dataclass
class RobotTrack:
    """What the gateway knows of one robot: recent estimates and when data last arrived."""

    robot_id: str
    maxlen: int
    estimates: deque[PoseEstimateMessage] = field(init=False)
    last_pose_received_s: float | None = None
    last_scan_received_s: float | None = None
    scans_seen: int = 0
    map_revision: int | None = None
    restarts: int = 0

    def __post_init__(self) -> None:
        self.estimates = deque(maxlen=self.maxlen)

    @property
    def latest(self) -> PoseEstimateMessage | None:
        return self.estimates[-1] if self.estimates else None

    def add(self, estimate: PoseEstimateMessage, received_s: float) -> None:
        """Append; a seq that does not move forward (a replay) starts the cache afresh, and
        so does a map redraw (the earlier poses are in the old frame: the map server's
        corrected path answers for them)."""
        latest = self.latest
        if latest is not None and estimate.seq <= latest.seq:
            self.estimates.clear()
            self.restarts += 1
        elif estimate.correction is not None:
            self.estimates.clear()
        self.estimates.append(estimate)
        self.last_pose_received_s = received_s


class TrackStore:
    """Thread-safe map robot id -> RobotTrack, fed from Zenoh callback threads."""

    def __init__(self, maxlen: int, limit: RobotLimit | None = None) -> None:
        self.maxlen = maxlen
        self._lock = threading.Lock()
        self._tracks: dict[str, RobotTrack] = {}
        self._limit = limit  # None: any number of robots

    def _track(self, robot_id: str) -> RobotTrack | None:
        """The robot's track, made on first sight; None when the limit refuses a new one."""
        track = self._tracks.get(robot_id)
        if track is None:
            if self._limit is not None and not self._limit.admits(robot_id, self._tracks):
                return None
            track = self._tracks[robot_id] = RobotTrack(robot_id, self.maxlen)
        return track

    def add_pose(self, estimate: PoseEstimateMessage) -> bool:
        """Cache `estimate`; False when its robot is refused (over the limit)."""
        with self._lock:
            track = self._track(estimate.robot_id)
            if track is not None:
                track.add(estimate, time.time())
            return track is not None

    def saw_scan(self, robot_id: str) -> None:
        with self._lock:
            track = self._track(robot_id)
            if track is not None:
                track.last_scan_received_s = time.time()
                track.scans_seen += 1

    def saw_map(self, robot_id: str, revision: int) -> None:
        with self._lock:
            track = self._track(robot_id)
            if track is not None:
                track.map_revision = revision

    def latest(self, robot_id: str) -> PoseEstimateMessage | None:
        with self._lock:
            track = self._tracks.get(robot_id)
            return None if track is None else track.latest

    def known(self, robot_id: str) -> bool:
        with self._lock:
            return robot_id in self._tracks

    def robots(self) -> list[RobotSummary]:
        """What is known of every robot, sorted by id (copied under the lock)."""
        with self._lock:
            return [
                RobotSummary(
                    robot_id=t.robot_id,
                    latest=t.latest,
                    poses_cached=len(t.estimates),
                    last_pose_received_s=t.last_pose_received_s,
                    last_scan_received_s=t.last_scan_received_s,
                    scans_seen=t.scans_seen,
                    map_revision=t.map_revision,
                    restarts=t.restarts,
                )
                for _, t in sorted(self._tracks.items())
            ]

    def estimates(self, robot_id: str) -> list[PoseEstimateMessage] | None:
        """A copy of the robot's cached estimates, oldest first; None for an unknown robot."""
        with self._lock:
            track = self._tracks.get(robot_id)
            return None if track is None else list(track.estimates)


@dataclass(frozen=True)
class RobotSummary:
    """A point-in-time view of one RobotTrack for the robots listing."""

    robot_id: str
    latest: PoseEstimateMessage | None
    poses_cached: int
    last_pose_received_s: float | None
    last_scan_received_s: float | None
    scans_seen: int
    map_revision: int | None
    restarts: int


def estimate_arrays(
    estimates: list[PoseEstimateMessage],
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """(stamps_s (N,), poses (N, 3)) of a list of estimates."""
    stamps = np.fromiter((e.stamp_s for e in estimates), np.float64, len(estimates))
    poses = np.array([e.pose.to_array() for e in estimates], dtype=np.float64)
    return stamps, poses.reshape(-1, 3)
