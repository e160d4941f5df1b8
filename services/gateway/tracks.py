"""Bounded per-robot caches of the pose estimates seen on the bus, pose lookup by time, and the
seqs of each robot's input streams (so that what the gateway publishes moves them forward)."""

from __future__ import annotations

import threading
import time
from collections import deque
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray
from scanflow.geometry import Pose2D
from scanflow.wire import ENDED_RUNS_KEPT, PoseEstimateMessage

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


class StaleSeqError(ValueError):
    """A client's seq (not 0) at or below its stream's last: the services would read it as a
    replay and start the robot's map afresh, so it is refused instead."""


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
    run: int = 0  # the tracker's run of the last estimate that named one (0: none yet)
    ended_runs: deque[int] = field(default_factory=lambda: deque(maxlen=ENDED_RUNS_KEPT))
    seqs: dict[str, int] = field(default_factory=dict)  # input stream -> its last seq

    def __post_init__(self) -> None:
        self.estimates = deque(maxlen=self.maxlen)

    @property
    def latest(self) -> PoseEstimateMessage | None:
        """The newest cached estimate; None when the cache is empty."""
        return self.estimates[-1] if self.estimates else None

    def add(self, estimate: PoseEstimateMessage, received_s: float) -> None:
        """Append; a seq that does not move forward (a replay) or another run of the tracker
        (its token: one whose first poses this gateway missed) starts the cache afresh, and
        so does a map redraw (the earlier poses are in the old frame: the map server's
        corrected path answers for them). A late one of a run it replaced is dropped."""
        if estimate.run and estimate.run in self.ended_runs:  # late, of a run replaced
            return
        latest = self.latest
        another_run = bool(estimate.run and self.run and estimate.run != self.run)
        if another_run:
            self.ended_runs.append(self.run)
        self.run = estimate.run or self.run
        if latest is not None and (estimate.seq <= latest.seq or another_run):
            self.estimates.clear()
            self.restarts += 1
        elif estimate.correction is not None:
            self.estimates.clear()
        self.estimates.append(estimate)
        self.last_pose_received_s = received_s

    def saw_seq(self, stream: str, seq: int) -> None:
        """`seq` went out on `stream` (from here or another source): seq 0 starts a new run,
        any other keeps the highest so far (a late copy of an earlier one does not lower it)."""
        self.seqs[stream] = seq if seq == 0 else max(seq, self.seqs.get(stream, -1))

    def last_seq(self, stream: str) -> int:
        """The stream's last seq, -1 for none. Until a scan is seen (the gateway started
        mid-run) the scans' is the last pose's: the tracker sends one per scan, with its seq."""
        if stream in self.seqs:
            return self.seqs[stream]
        latest = self.latest
        return latest.seq if stream == "scan" and latest is not None else -1


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

    def saw_scan(self, robot_id: str, seq: int) -> None:
        """Note a scan of the robot seen now: arrival time, count and seq (not if refused)."""
        with self._lock:
            track = self._track(robot_id)
            if track is not None:
                track.last_scan_received_s = time.time()
                track.scans_seen += 1
                track.saw_seq("scan", seq)

    def saw_odometry(self, robot_id: str, seq: int) -> None:
        """Note the seq of an odometry sample of the robot (nothing when the robot is refused)."""
        with self._lock:
            track = self._track(robot_id)
            if track is not None:
                track.saw_seq("odom", seq)

    def knows_seq(self, robot_id: str, stream: str) -> bool:
        """Whether a seq of the robot's `stream` was seen or learnt since the gateway started."""
        with self._lock:
            track = self._tracks.get(robot_id)
            return track is not None and stream in track.seqs

    def learn_seq(self, robot_id: str, stream: str, last: int) -> None:
        """The stream's last seq as the services saw it before this gateway started (-1: none),
        unless one was seen since (it is newer); the scans' takes the last pose's when higher."""
        with self._lock:
            track = self._track(robot_id)
            if track is not None and stream not in track.seqs:
                track.seqs[stream] = max(last, track.last_seq(stream))

    def next_seq(self, robot_id: str, stream: str, given: int | None) -> int | None:
        """The seq to publish on the robot's input `stream` ("scan", "odom"): `given`, or one
        past the stream's last when it is None; None when the robot is refused (over the
        limit). A `given` seq other than 0 at or below the last raises StaleSeqError: a retried or
        reordered request would otherwise restart the robot's map in every service. Seq 0
        starts a new run (a replay) on purpose. Nothing is recorded: once the message went
        out, `saw_scan` / `saw_odometry` note its seq (a put that failed uses none up)."""
        with self._lock:
            track = self._track(robot_id)
            if track is None:
                return None
            last = track.last_seq(stream)
            if given is None:
                given = last + 1
            elif 0 < given <= last:
                raise StaleSeqError(
                    f"seq {given} does not move the {stream} stream of robot {robot_id!r} "
                    f"forward (its last is {last}): the services would take it for a replay "
                    f"and start the robot's map afresh; leave seq out to have it numbered, or "
                    f"send seq 0 to start a new run"
                )
            return given

    def saw_map(self, robot_id: str, revision: int) -> None:
        """Note the revision of the robot's map (nothing when the robot is refused)."""
        with self._lock:
            track = self._track(robot_id)
            if track is not None:
                track.map_revision = revision

    def latest(self, robot_id: str) -> PoseEstimateMessage | None:
        """The robot's newest cached estimate; None for an unknown robot or an empty cache."""
        with self._lock:
            track = self._tracks.get(robot_id)
            return None if track is None else track.latest

    def known(self, robot_id: str) -> bool:
        """Whether the robot has a track: seen on the bus or posted, and admitted."""
        with self._lock:
            return robot_id in self._tracks

    def forget(self, robot_id: str) -> dict[str, int] | None:
        """Drop the robot's track (it was retired): what it held, None when it had none. A
        refusal of it later is reported again; its next message starts a new track."""
        with self._lock:
            track = self._tracks.pop(robot_id, None)
            if self._limit is not None:
                self._limit.forget(robot_id)
        if track is None:
            return None
        return {"poses_cached": len(track.estimates), "scans_seen": track.scans_seen}

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
