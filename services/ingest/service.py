"""Ingest service: publish a source's odometry and scans with per-robot seqs, then drain.

Pacing: `rate` times real time, or (rate 0) as fast as the pipeline takes them: then a
credit window on the matcher's published pose seqs holds ingest back (backpressure, no drops).
At the end it waits for the pose of its last scan before closing, so the tail is not lost.
A log's unreadable records are skipped, counted and logged (the first 10, then every 100th:
`worth_logging`); a log that breaks off (a damaged bag) ends the replays where it broke, and
what was published before is drained as usual: the process exits cleanly, not in a restart
loop.
"""

from __future__ import annotations

from collections.abc import Iterable

from scanflow import keys
from scanflow.config import IngestSettings, ZenohSettings
from scanflow.io.carmen import CarmenFormatError
from scanflow.io.rosbag import BagFormatError
from scanflow.scan import LaserScan
from scanflow.wire import MessageError, PoseEstimateMessage

from services.common.counters import worth_logging
from services.common.process import init_process, require_settings
from services.common.shell import ServiceShell
from services.ingest.flow import CreditWindow, Pacer
from services.ingest.sources import Event, bus_message, source_events


class Ingest:
    """Publishes one or more replays of the configured source."""

    def __init__(self, settings: IngestSettings, zenoh_settings: ZenohSettings) -> None:
        self.settings = settings
        keys.check_robot_id(settings.robot_id)
        self.shell = ServiceShell("ingest", settings, zenoh_settings)
        stop = self.shell.stop_event
        window = settings.window if settings.rate == 0 else 0
        self.credit = CreditWindow(window, settings.stall_timeout_s, stop)
        self._last_scan: dict[str, int] = {}
        self._scans = 0  # scans published in this replay
        self.broken = False  # the source broke off: no further replays
        self.shell.subscribe(
            keys.pose("*", self.shell.prefix), "pose", PoseEstimateMessage.decode, self._on_pose
        )
        self.shell.add_stats(lambda: {"credit_stalls": self.credit.stalls})

    def _on_pose(self, _kind: str, message: PoseEstimateMessage) -> None:
        self.credit.on_pose(message.robot_id, message.seq)

    def _on_skipped(self, message: str) -> None:
        n = self.shell.counters.add("source.skipped")
        if worth_logging(n):
            self.shell.log.warning("skipped an unreadable record: %s", message)

    def replay_once(self) -> int:
        """Publish one pass over the source; returns the number of scans published."""
        s = self.settings
        self._scans = 0
        events = source_events(
            s.log, s.robot_id, s.sim_duration_s, s.sim_seed, s.limit, s.mount_pose(),
            sim_world=s.sim_world, sim_odom_scale_error=s.sim_odom_scale_error,
            sim_odom_yaw_noise=s.sim_odom_yaw_noise,
            on_error=self._on_skipped,
        )
        try:
            self._publish(events)
        except (CarmenFormatError, BagFormatError) as exc:
            self.broken = True
            self.shell.counters.add("source.broken")
            self.shell.log.error("the log cannot be read on, replays end here (%d scans of "
                                 "it published): %s", self._scans, exc)
        self.shell.counters.add("published.scan", self._scans)
        return self._scans

    def _publish(self, events: Iterable[Event]) -> None:
        """Publish `events` paced and within the credit window, counting the scans; a record
        no message can carry (odometry beyond MAX_POSITION_M) is skipped as unreadable."""
        pacer = Pacer(self.settings.rate, self.shell.stop_event)
        prefix = self.shell.prefix
        for event in events:
            if self.shell.stop_event.is_set():
                break
            robot = event.robot_id
            try:
                message = bus_message(event, prefix)
            except MessageError as exc:
                self._on_skipped(f"{type(event).__name__} {robot} seq {event.seq}: {exc}")
                continue
            pacer.wait(event.stamp_s)
            if isinstance(event, LaserScan):
                if event.seq == 0:
                    self.credit.reset(robot)
                    self._wait_for_pipeline(keys.raw_scan(robot, prefix))
                if not self.credit.acquire(robot, event.seq):
                    break
                self.shell.put(*message)
                self._last_scan[robot] = event.seq
                self.shell.seqs.observe(f"{robot}/scan", event.seq)
                self._scans += 1
            else:
                self.shell.put(*message)
                self.shell.seqs.observe(f"{robot}/odom", event.seq)

    def _wait_for_pipeline(self, key: str) -> None:
        """Scans published before anyone subscribes are lost: wait for a subscriber first."""
        if not self.shell.wait_for_subscribers(key, self.settings.wait_subscribers_s):
            self.shell.log.warning(
                "nothing subscribes to %s after %.0f s: publishing anyway",
                key, self.settings.wait_subscribers_s,
            )

    def drain(self) -> bool:
        """Wait for the pose of every robot's last scan (bounded by `drain_timeout_s`)."""
        drained = True
        for robot, seq in self._last_scan.items():
            if not self.credit.drain(robot, seq, self.settings.drain_timeout_s):
                self.shell.log.warning(
                    "robot %s: no pose for last scan %d within %.1f s (last pose seq %d)",
                    robot, seq, self.settings.drain_timeout_s, self.credit.acked(robot),
                )
                drained = False
        return drained

    def run(self) -> None:
        """Publish the source `replays` times, each time waiting for its last scan's pose; close."""
        with self.shell:
            self.shell.start()
            total = 0
            for replay in range(self.settings.replays):
                if self.shell.stop_event.is_set() or self.broken:
                    break
                total += self.replay_once()
                self.drain()
                self.shell.log.info(
                    "replay %d done: %d scans published, %d credit stalls",
                    replay + 1, total, self.credit.stalls,
                )


def main() -> None:
    """Run ingest with settings from SCANFLOW_INGEST_* and SCANFLOW_ZENOH_*."""
    require_settings("ingest", IngestSettings, ZenohSettings)
    settings = IngestSettings()
    init_process(settings)
    Ingest(settings, ZenohSettings()).run()
