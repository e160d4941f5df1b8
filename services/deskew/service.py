"""Deskew service: per robot the in-process pipeline's `DeskewStage`; each scan is held until
odometry covers its sweep (or the latency budget runs out), then deskewed and published.

Scans leave in arrival order per robot. Without covering odometry the stage falls back to the
constant-velocity prior fed by the matcher's accepted poses, else to no correction;
`source_used` in each message says which.
"""

from __future__ import annotations

import time
from collections import deque
from dataclasses import dataclass, field

from scanflow import keys
from scanflow.config import DeskewSettings, ZenohSettings
from scanflow.frontend import ACCEPTED
from scanflow.pipeline import DeskewStage
from scanflow.scan import LaserScan
from scanflow.wire import DeskewedScanMessage, OdometryMessage, PoseEstimateMessage, ScanMessage

from services.common.logs import configure_logging
from services.common.shell import ServiceShell

_MIN_POLL_S = 0.002


@dataclass
class _Robot:
    stage: DeskewStage = field(default_factory=DeskewStage)
    pending: deque[tuple[float, LaserScan]] = field(default_factory=deque)


class DeskewService:
    """Holds per-robot odometry buffers and the scans waiting for odometry."""

    def __init__(self, settings: DeskewSettings, zenoh_settings: ZenohSettings) -> None:
        self.settings = settings
        self.shell = ServiceShell("deskew", settings.instance, zenoh_settings, settings.queue_size)
        prefix = self.shell.prefix
        self.robots: dict[str, _Robot] = {}
        routes = [
            (keys.raw_scan("*", prefix), "scan", ScanMessage.decode),
            (keys.odom("*", prefix), "odom", OdometryMessage.decode),
            (keys.pose("*", prefix), "pose", PoseEstimateMessage.decode),
        ]
        self.shell.subscribe_routes(keys.robot_streams("*", prefix), routes)
        self.shell.add_stats(lambda: {"robots": len(self.robots), "pending": self._pending()})

    def handle(
        self, kind: str, message: ScanMessage | OdometryMessage | PoseEstimateMessage
    ) -> None:
        robot_id = message.robot_id
        if isinstance(message, PoseEstimateMessage):
            robot = self.robots.get(robot_id)
            if robot is not None and message.status in ACCEPTED:
                robot.stage.observe_pose(message.stamp_s, message.pose)
            return
        stream = f"{robot_id}/{kind}"
        restarted = self.shell.seqs.is_restart(stream, message.seq)
        self.shell.seqs.observe(stream, message.seq)
        robot = self.robots.setdefault(robot_id, _Robot())
        if isinstance(message, OdometryMessage):
            if restarted:
                self._flush(robot_id, robot, force=True)
                robot.stage = DeskewStage()
            robot.stage.add_odometry(message.odom)
        else:
            robot.pending.append((time.monotonic() + self.settings.odom_wait_s, message.scan))
        self.idle()

    def idle(self) -> None:
        for robot_id, robot in self.robots.items():
            self._flush(robot_id, robot, force=False)

    def _flush(self, robot_id: str, robot: _Robot, force: bool) -> None:
        """Deskew the scans at the head of the queue that are covered or out of time."""
        now = time.monotonic()
        while robot.pending:
            deadline, scan = robot.pending[0]
            covered = robot.stage.odometry.coverage_gap(scan.stamp_s, scan.end_stamp_s) is None
            if not (covered or force or now >= deadline or self._never_covered(robot, scan)):
                return
            robot.pending.popleft()
            self._publish(robot_id, scan, robot.stage)

    @staticmethod
    def _never_covered(robot: _Robot, scan: LaserScan) -> bool:
        """Odometry already runs past the sweep, so waiting longer cannot help."""
        stamps = robot.stage.odometry.stamps_s
        return stamps.size > 0 and stamps[-1] > scan.end_stamp_s

    def _publish(self, robot_id: str, scan: LaserScan, stage: DeskewStage) -> None:
        result = stage.process(scan)
        self.shell.counters.add(f"deskewed.{result.source_used}")
        message = DeskewedScanMessage(
            robot_id=robot_id,
            seq=scan.seq,
            stamp_s=result.reference_stamp_s,
            points=result.points,
            source_used=result.source_used,
            times_assumed=result.times_assumed,
            beam_count=result.beam_count,
            dropped_count=result.beam_count - result.valid_count,
            no_return_points=result.no_return_points,
        )
        self.shell.put(keys.deskewed_scan(robot_id, self.shell.prefix), message.encode())

    def _pending(self) -> int:
        return sum(len(r.pending) for r in self.robots.values())

    def run(self) -> None:
        self.shell.start()
        poll_s = min(max(self.settings.odom_wait_s / 5, _MIN_POLL_S), 0.1)
        self.shell.run(self.handle, self.idle, poll_s)
        for robot_id, robot in self.robots.items():
            self._flush(robot_id, robot, force=True)
        self.shell.close()


def main() -> None:
    """Run the deskew service with settings from SCANFLOW_DESKEW_* and SCANFLOW_ZENOH_*."""
    settings = DeskewSettings()
    configure_logging(settings.log_level)
    DeskewService(settings, ZenohSettings()).run()
