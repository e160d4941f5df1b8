"""Deskew service: per robot the in-process pipeline's `DeskewStage`; each scan is held until
odometry covers its sweep (or the latency budget runs out), then deskewed and published.

Scans leave in arrival order per robot. Without covering odometry the stage falls back to the
constant-velocity prior fed by the matcher's accepted poses, else to no correction;
`source_used` in each message says which. A scan that odometry will never cover first waits
(within the same budget) for the matcher's pose of the scan before it, so the prior holds every
earlier estimate, as in the in-process pipeline; a zero-length sweep (keyframe logs) has nothing
to correct and does not wait. A pose that carries a map frame `correction` (loop closure
redrew the map) moves the prior's frame with it. Poses come in on the shell's feedback lane:
the matcher blocks on publishing them, so they must not queue behind scans that wait on it.
A robot retired (`<prefix>/<robot>/retire/deskew`) loses its scans still waiting for odometry
and the odometry held: they are dropped, not deskewed.
"""

from __future__ import annotations

import math
import time
from collections import deque
from dataclasses import dataclass, field

from scanflow import keys
from scanflow.config import DeskewSettings, ZenohSettings
from scanflow.deskew import motion_free_reason
from scanflow.frontend import ACCEPTED
from scanflow.pipeline import DeskewStage
from scanflow.scan import LaserScan, Odometry
from scanflow.warmup import warm_up
from scanflow.wire import DeskewedScanMessage, OdometryMessage, PoseEstimateMessage, ScanMessage

from services.common.counters import worth_logging
from services.common.process import init_process, require_settings
from services.common.retire import Dropped
from services.common.shell import ServiceShell

_MIN_POLL_S = 0.002
MAX_PENDING_ODOMETRY = 4096  # samples held ahead of the scans


def _stamp_s(message: ScanMessage | OdometryMessage) -> float:
    """A scan's or odometry sample's stamp (s)."""
    return message.scan.stamp_s if isinstance(message, ScanMessage) else message.odom.stamp_s


@dataclass
class _Robot:
    """One robot's deskew stage, its scans waiting for odometry and the odometry waiting for
    its scan: scans and odometry come on separate subscribers, whose callbacks do not keep
    their relative order, so odometry enters the stage only up to the scan being deskewed (and
    the first sample past its sweep, to bracket it), as the in-process pipeline holds it."""

    stage: DeskewStage = field(default_factory=DeskewStage)
    pending: deque[tuple[float, LaserScan]] = field(default_factory=deque)
    odometry: deque[Odometry] = field(default_factory=deque)
    streams: set[str] = field(default_factory=set)  # the kinds of message this run has had
    # When a new run began on one stream, the old run's robot: the other streams' messages
    # still on their way (not restarted yet, in `awaiting`) are the old run's tail.
    previous: _Robot | None = None
    awaiting: set[str] = field(default_factory=set)
    published_seq: int | None = None  # the last scan sent to the matcher
    pose_seq: int | None = None  # the last scan the matcher's pose came back for

    def add_odometry(self, sample: Odometry) -> None:
        """Hold `sample` for its scan; beyond MAX_PENDING_ODOMETRY, the oldest go to the stage."""
        self.odometry.append(sample)
        while len(self.odometry) > MAX_PENDING_ODOMETRY:
            self.stage.add_odometry(self.odometry.popleft())

    def feed_odometry_through(self, stamp_s: float) -> None:
        """Move waiting samples into the stage up to the first one later than `stamp_s`."""
        while self.odometry:
            sample = self.odometry.popleft()
            self.stage.add_odometry(sample)
            if sample.stamp_s > stamp_s:
                return

    def has_prior(self) -> bool:
        """True when the matcher's estimate of the last scan sent is in (or none was sent)."""
        return self.published_seq is None or self.pose_seq == self.published_seq


class DeskewService:
    """Holds per-robot odometry buffers and the scans waiting for odometry."""

    def __init__(self, settings: DeskewSettings, zenoh_settings: ZenohSettings) -> None:
        self.settings = settings
        self.shell = ServiceShell("deskew", settings, zenoh_settings)
        prefix = self.shell.prefix
        self.robots: dict[str, _Robot] = {}
        self._last_stamps: dict[str, float] = {}  # per robot stream: where its clock is
        # Exactly its inputs: a robot-tree wildcard would also carry the matcher's output, and
        # a full inbox would then hold up the matcher's puts too. Scans wait for covering
        # odometry anyway, so the two subscribers' callbacks need not keep their relative order.
        self.shell.subscribe(keys.raw_scan("*", prefix), "scan", ScanMessage.decode)
        self.shell.subscribe(keys.odom("*", prefix), "odom", OdometryMessage.decode)
        self.shell.subscribe_feedback(  # a map frame's correction is no hint: never dropped
            keys.pose("*", prefix), "pose", PoseEstimateMessage.decode,
            keep=lambda pose: pose.correction is not None,
        )
        self.shell.add_stats(lambda: {"robots": len(self.robots), "pending": self._pending()})
        self.shell.serve_retire(self.retire)

    def handle(
        self, kind: str, message: ScanMessage | OdometryMessage | PoseEstimateMessage
    ) -> None:
        """A pose updates the robot's prior (its frame too, after a redraw) and releases its scans;
        a scan or odometry sample of an admitted robot joins its run (its clock going back: a new
        run, see `_starts_run`)."""
        robot_id = message.robot_id
        if isinstance(message, PoseEstimateMessage):
            robot = self.robots.get(robot_id)
            if robot is not None:
                robot.pose_seq = message.seq
                if message.correction is not None:  # the map was redrawn: follow its frame
                    robot.stage.velocity.move_frame(message.correction)
                if message.status in ACCEPTED:
                    robot.stage.observe_pose(message.stamp_s, message.pose)
                self._flush_in_order(robot_id, robot)
            return
        if not self.shell.admits(robot_id, self.robots):
            return
        stream = f"{robot_id}/{kind}"
        if self._is_copy(stream, message):
            n = self.shell.counters.add(f"duplicates.{kind}")
            if worth_logging(n):
                self.shell.log.warning("%s: seq %d came again with the same stamp (#%d): the "
                                       "copy is dropped", stream, message.seq, n)
            return
        robot = self.robots.setdefault(robot_id, _Robot())
        restarted = self._starts_run(kind, message, robot.stage.odometry.max_age_s)
        self.shell.seqs.observe(stream, message.seq)
        if restarted and kind in robot.streams:
            robot = self._new_run(robot_id, robot, kind)
        elif kind in robot.awaiting:
            if restarted:  # this stream's new run begins too: the old run is complete
                robot.awaiting.discard(kind)
                if not robot.awaiting:
                    self._finish_previous(robot_id, robot)
            elif robot.previous is not None:  # still the old run's tail: deskewed with it
                robot = robot.previous
        robot.streams.add(kind)
        if isinstance(message, OdometryMessage):
            robot.add_odometry(message.odom)
        else:
            robot.pending.append((time.monotonic() + self.settings.odom_wait_s, message.scan))
        self.idle()

    def _is_copy(self, stream: str, message: ScanMessage | OdometryMessage) -> bool:
        """Whether `message` is its stream's last one again (same seq, same stamp): a client
        that sent it twice, without the Zenoh timestamp that shows the network's copies. Passed
        on, it would go out again under a seq that does not advance, a restart to the matcher
        and the map server, which would wipe the robot's map."""
        return (
            self.shell.seqs.last_seq(stream) == message.seq
            and self._last_stamps.get(stream) == _stamp_s(message)
        )

    def _starts_run(
        self, kind: str, message: ScanMessage | OdometryMessage, window_s: float
    ) -> bool:
        """Whether the robot's stream `kind` starts a new run: its stamps go back with a seq that
        does not advance (a replay, a restarted source), or further than the odometry window
        `window_s` with one that does (a clock reset, counted as clock_reset.<kind>: the odometry
        held would drop the new samples as too old). A seq that starts again on the same clock
        (a driver restarted, a message sent twice) continues the run: its odometry still covers
        the scans (a new run would wait for the other stream to restart, maybe for ever)."""
        stream = f"{message.robot_id}/{kind}"
        stamp_s = _stamp_s(message)
        last_s = self._last_stamps.get(stream, -math.inf)
        self._last_stamps[stream] = stamp_s
        if stamp_s >= last_s:
            return False
        if self.shell.seqs.is_restart(stream, message.seq):
            return True
        if last_s - stamp_s <= window_s:
            return False
        n = self.shell.counters.add(f"clock_reset.{kind}")
        if worth_logging(n):
            self.shell.log.warning(
                "%s: stamps went back %.3f s (from %.6f to %.6f s) at seq %d: a clock reset, "
                "a new run (#%d)", stream, last_s - stamp_s, last_s, stamp_s, message.seq, n,
            )
        return True

    def _new_run(self, robot_id: str, old: _Robot, kind: str) -> _Robot:
        """The source restarted (a replay) on stream `kind`: a fresh robot for the new run.
        The old one stays for the tail of its other streams, which the two subscribers may
        still deliver after this (a source that starts again without waiting), until each of
        them restarts too."""
        self._finish_previous(robot_id, old)
        new = _Robot(previous=old, awaiting=old.streams - {kind})
        self.robots[robot_id] = new
        if not new.awaiting:
            self._finish_previous(robot_id, new)
        return new

    def _finish_previous(self, robot_id: str, robot: _Robot) -> None:
        """Deskew what the old run still holds, whatever covers it, and let it go."""
        if robot.previous is not None:
            self._flush(robot_id, robot.previous, force=True)
            robot.previous = None

    def idle(self) -> None:
        """Deskew and publish, in order, the scans odometry now covers or that are out of time."""
        for robot_id, robot in self.robots.items():
            self._flush_in_order(robot_id, robot)

    def _flush_in_order(self, robot_id: str, robot: _Robot) -> None:
        """The old run's scans leave first (they came first), then the robot's own."""
        if robot.previous is not None:
            self._flush(robot_id, robot.previous, force=False)
            if robot.previous.pending:
                return
        self._flush(robot_id, robot, force=False)

    def _flush(self, robot_id: str, robot: _Robot, force: bool) -> None:
        """Deskew the scans at the head of the queue that are covered or out of time."""
        now = time.monotonic()
        while robot.pending:
            deadline, scan = robot.pending[0]
            robot.feed_odometry_through(scan.end_stamp_s if not force else math.inf)
            if not (force or now >= deadline or self._ready(robot, scan)):
                return
            robot.pending.popleft()
            self._publish(robot_id, scan, robot.stage)
            robot.published_seq = scan.seq

    @staticmethod
    def _ready(robot: _Robot, scan: LaserScan) -> bool:
        """Odometry reaches the end of the sweep (waiting longer cannot change it; a log with
        one odometry pose per zero-length scan has it at the scan's stamp), and when it does
        not cover the sweep the fallback prior holds the matcher's estimate of the scan before,
        unless no pose can move the scan's beams (a zero-length sweep): waiting for the matcher
        there would only hold every scan behind the one before it (stop and wait)."""
        stamps = robot.stage.odometry.stamps_s
        if not (stamps.size > 0 and stamps[-1] >= scan.end_stamp_s):
            return False
        covered = robot.stage.odometry.coverage_gap(scan.stamp_s, scan.end_stamp_s) is None
        return covered or motion_free_reason(scan) is not None or robot.has_prior()

    def _publish(self, robot_id: str, scan: LaserScan, stage: DeskewStage) -> None:
        """Deskew `scan` and publish it; a scan with motion to correct that the robot's odometry
        did not cover is counted as odometry_missed and logged with the reason (a clock offset
        between the two streams, odometry later than the budget, a gap in it)."""
        result = stage.process(scan)
        self.shell.counters.add(f"deskewed.{result.source_used}")
        if (result.source_used != "odometry" and len(stage.odometry)
                and motion_free_reason(scan) is None):
            n = self.shell.counters.add("odometry_missed")
            if worth_logging(n):
                self.shell.log.warning(
                    "robot %s: scan %d deskewed by %s, not odometry (#%d): %s", robot_id,
                    scan.seq, result.source_used, n, result.message,
                )
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
            odom_pose=stage.odometry_pose_at(result.reference_stamp_s),
            mount=result.mount,
        )
        self.shell.put(keys.deskewed_scan(robot_id, self.shell.prefix), message.encode())

    def retire(self, robot_id: str) -> Dropped:
        """Let go of the robot (on the worker, between two messages): its run, the old run's
        tail, the scans waiting for odometry (dropped, not deskewed), the odometry held, where
        its streams' clocks were. Its next message starts it afresh."""
        clocks = [self._last_stamps.pop(f"{robot_id}/{kind}", None) for kind in ("scan", "odom")]
        robot = self.robots.pop(robot_id, None)
        if robot is None:
            return Dropped(any(c is not None for c in clocks))
        runs = [robot] if robot.previous is None else [robot, robot.previous]
        return Dropped(True, {
            "scans_pending": sum(len(r.pending) for r in runs),
            "odometry_samples": sum(len(r.odometry) + len(r.stage.odometry) for r in runs),
        })

    def _pending(self) -> int:
        return sum(
            len(r.pending) + (0 if r.previous is None else len(r.previous.pending))
            for r in list(self.robots.values())  # a copy: the worker may admit a robot now
        )

    def run(self) -> None:
        """Warm up (if set), serve until stopped, then deskew every scan still held, and close."""
        with self.shell:
            if self.settings.warm_up:  # before the health token: the first scan at full speed
                warm_up()
            self.shell.start()
            poll_s = min(max(self.settings.odom_wait_s / 5, _MIN_POLL_S), 0.1)
            self.shell.run(self.handle, self.idle, poll_s)
            for robot_id, robot in self.robots.items():
                self._finish_previous(robot_id, robot)
                self._flush(robot_id, robot, force=True)


def main() -> None:
    """Run the deskew service with settings from SCANFLOW_DESKEW_* and SCANFLOW_ZENOH_*."""
    require_settings("deskew", DeskewSettings, ZenohSettings)
    settings = DeskewSettings()
    init_process(settings)
    DeskewService(settings, ZenohSettings()).run()
