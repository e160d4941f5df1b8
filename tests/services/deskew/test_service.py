"""The deskew service on real processes: every scan comes out, equal to the library's deskew."""

from __future__ import annotations

import dataclasses
import math
import time

import numpy as np
import pytest
from scanflow import keys
from scanflow.config import DeskewSettings, ZenohSettings
from scanflow.deskew import OdometryBuffer, deskew
from scanflow.geometry import Pose2D
from scanflow.pipeline import DeskewStage
from scanflow.scan import LaserScan, Odometry
from scanflow.wire import DeskewedScanMessage, OdometryMessage, PoseEstimateMessage, ScanMessage

from services.deskew.service import DeskewService, _Robot
from services.ingest.sources import source_events

from ..conftest import stats_failures_while

pytestmark = [pytest.mark.integration]

SIM = {"SCANFLOW_INGEST_SIM_DURATION_S": "3", "SCANFLOW_INGEST_SIM_SEED": "4"}


def reference_points(events) -> list[np.ndarray]:
    """The library's deskew of each scan, in order, with all odometry published before it."""
    buffer = OdometryBuffer()
    out = []
    for event in events:
        if isinstance(event, LaserScan):
            out.append(deskew(event, buffer).points)
        else:
            buffer.add_odometry(event)
    return out


def reference_deskew(events) -> dict[int, np.ndarray]:
    """`reference_points` by scan seq."""
    events = list(events)
    seqs = [event.seq for event in events if isinstance(event, LaserScan)]
    return dict(zip(seqs, reference_points(events), strict=True))


def test_every_scan_is_deskewed_like_the_library_and_junk_is_counted(launcher, bus, start):
    deskewed = bus.record(keys.deskewed_scan())
    # Odometry waited for as long as it takes (a loaded machine delays it): the point here is
    # the deskewing, not the latency budget (the next test's).
    start("deskew", SCANFLOW_DESKEW_MAX_ROBOTS="1", SCANFLOW_DESKEW_ODOM_WAIT_S="10")
    junk = [b"", b"\x00garbage", ScanMessage.__name__.encode()]
    for payload in junk:
        bus.put(keys.raw_scan("robot"), payload)
        bus.put(keys.odom("robot"), payload)
    # Valid messages of another robot on this robot's keys: refused, not deskewed.
    bus.put(keys.raw_scan("robot"), ScanMessage(LaserScan(
        np.ones(8), 0.0, 0.1, robot_id="elsewhere", seq=0)).encode())
    bus.put(keys.odom("robot"), OdometryMessage(Odometry(
        0.0, Pose2D(), robot_id="elsewhere", seq=0)).encode())
    junk.append(b"another robot's message")
    launcher.start(
        "ingest", SCANFLOW_INGEST_WINDOW="0", SCANFLOW_INGEST_DRAIN_TIMEOUT_S="0.5", **SIM
    )
    expected = reference_deskew(source_events(None, "robot", 3.0, 4, None))
    bus.wait_until(lambda: len(deskewed) >= len(expected), 60.0, "all deskewed scans")
    assert [m.seq for m in deskewed] == sorted(expected)
    for message in deskewed:
        assert message.source_used == "odometry"
        np.testing.assert_array_equal(message.points, expected[message.seq], strict=True)
    stats = bus.stats("deskew")
    assert stats.counters["malformed.scan"] == len(junk)
    assert stats.counters["malformed.odom"] == len(junk)
    assert stats.counters["received.scan"] == len(expected)
    assert stats.counters["seq.robot/scan.missed"] == 0
    # A second robot, over SCANFLOW_DESKEW_MAX_ROBOTS=1: dropped, counted, the first unharmed.
    bus.put(keys.raw_scan("second"), ScanMessage(LaserScan(
        np.ones(8), 0.0, 0.1, robot_id="second", seq=0)).encode())
    bus.wait_until(lambda: bus.stats("deskew").counters.get("robots_refused") == 1, 30.0,
                   "the second robot refused")
    assert {m.robot_id for m in deskewed} == {"robot"}
    assert launcher.processes["deskew"].poll() is None


def test_a_scan_without_odometry_leaves_after_the_latency_budget_uncorrected(
    launcher, bus, start
):
    deskewed = bus.record(keys.deskewed_scan("bare"))
    start("deskew", SCANFLOW_DESKEW_ODOM_WAIT_S="0.2")
    scans = [e for e in source_events(None, "bare", 0.5, 1, None) if isinstance(e, LaserScan)]
    for scan in scans:
        bus.put(keys.raw_scan("bare"), ScanMessage(scan).encode())
    bus.wait_until(lambda: len(deskewed) == len(scans), 30.0, "scans without odometry")
    assert [m.seq for m in deskewed] == [s.seq for s in scans]
    assert {m.source_used for m in deskewed} == {"none"}
    for message, scan in zip(deskewed, scans, strict=True):
        np.testing.assert_array_equal(message.points, deskew(scan).points, strict=True)


def test_zero_length_sweeps_are_not_held_for_the_matchers_pose(launcher, bus, start):
    """Keyframe logs: every beam at the scan's stamp, odometry too sparse to cover it. No pose
    can move such a scan, so none waits for the matcher's estimate of the one before (no
    matcher runs here; the budget is far longer than the test waits)."""
    deskewed = bus.record(keys.deskewed_scan("keys"))
    start("deskew", SCANFLOW_DESKEW_ODOM_WAIT_S="300")
    scans = []
    for k in range(5):  # 1 s between odometry samples: beyond the buffer's max gap
        odom = Odometry(float(k), Pose2D(0.5 * k, 0.0, 0.1 * k), robot_id="keys", seq=k)
        scan = LaserScan(
            np.full(90, 3.0, np.float32), -math.pi / 4, math.radians(1.0),
            stamp_s=float(k), robot_id="keys", seq=k,
        )
        bus.put(keys.odom("keys"), OdometryMessage(odom).encode())
        bus.put(keys.raw_scan("keys"), ScanMessage(scan).encode())
        scans.append((scan, odom))
    bus.wait_until(lambda: len(deskewed) == len(scans), 60.0, "every keyframe scan")
    assert [m.seq for m in deskewed] == list(range(len(scans)))
    for message, (scan, odom) in zip(deskewed, scans, strict=True):
        assert message.source_used == "none"
        assert message.odom_pose == odom.pose
        np.testing.assert_array_equal(message.points, deskew(scan).points, strict=True)


def test_a_map_redraws_correction_moves_the_velocity_prior_with_the_frame(launcher, bus, start):
    """Without odometry the prior is the matcher's poses. A pose that carries a redraw's frame
    correction is in the new frame: the prior moves with it (as the in-process pipeline's),
    instead of reading the frame change as motion."""
    deskewed = bus.record(keys.deskewed_scan("cv"))
    start("deskew", SCANFLOW_DESKEW_ODOM_WAIT_S="0.2")
    scans = [e for e in source_events(None, "cv", 0.6, 1, None) if isinstance(e, LaserScan)]
    correction, step = Pose2D(0.4, -0.3, 0.2), Pose2D(0.05, 0.01, 0.08)
    followed, ignored = DeskewStage(), DeskewStage()
    pose, expected, naive = Pose2D(), [], []
    for k, scan in enumerate(scans):
        bus.put(keys.raw_scan("cv"), ScanMessage(scan).encode())
        result = followed.process(scan)
        expected.append(result.points)
        naive.append(ignored.process(scan).points)
        bus.wait_until(lambda n=k + 1: len(deskewed) == n, 30.0, f"deskewed scan {k}")
        fix = correction if k == 2 else None
        if fix is not None:
            pose = fix * pose
            followed.velocity.move_frame(fix)
        followed.observe_pose(result.reference_stamp_s, pose)
        ignored.observe_pose(result.reference_stamp_s, pose)
        bus.put(keys.pose("cv"), PoseEstimateMessage(
            "cv", scan.seq, result.reference_stamp_s, pose, np.eye(3), "tracked", "gn", 1, 1.0,
            "", fix).encode())
        pose = pose * step
    assert len(scans) >= 5 and [m.source_used for m in deskewed][-1] == "constant_velocity"
    for message, points in zip(deskewed, expected, strict=True):
        np.testing.assert_array_equal(message.points, points, strict=True)
    assert not np.allclose(naive[3], expected[3], atol=1e-3)  # the test can tell the two


def test_a_run_started_again_at_once_keeps_each_runs_odometry() -> None:
    """A source starts its next run without waiting: run 2's odometry restarts before run 1's
    last scans are in. Those scans are deskewed with run 1's odometry and leave first; run 2's
    keep run 2's odometry (an audit saw every scan of run 2 deskewed without odometry)."""
    from scanflow.config import DeskewSettings, ZenohSettings

    from services.deskew.service import DeskewService
    from services.ingest.sources import source_events as events_of

    run1 = list(events_of(None, "robot", 2.0, 4, None))
    run2 = list(events_of(None, "robot", 2.0, 5, None))
    tail = [e for e in run1 if isinstance(e, LaserScan)][-2:]
    head = [e for e in run1 if not any(e is t for t in tail)]
    odometry2 = [e for e in run2 if not isinstance(e, LaserScan)]
    service = DeskewService(DeskewSettings(odom_wait_s=0.5), ZenohSettings(mode="peer", connect=[]))
    out: list = []
    service.shell.put = lambda key, payload: out.append(DeskewedScanMessage.decode(payload))
    try:
        feed = [*head, *odometry2[:20], *tail, *odometry2[20:],
                *[e for e in run2 if isinstance(e, LaserScan)]]
        for event in feed:
            scan = isinstance(event, LaserScan)
            message = ScanMessage(event) if scan else OdometryMessage(event)
            service.handle("scan" if scan else "odom", message)
        time.sleep(0.6)  # past the latency budget: the last scans leave as they are
        service.idle()
    finally:
        service.shell.close(flush_s=0.0)
    expected = [*reference_deskew(run1).items(), *reference_deskew(run2).items()]
    assert [m.seq for m in out] == [seq for seq, _ in expected]
    for message, (_, points) in zip(out, expected, strict=True):
        assert message.source_used == "odometry", message.seq
        np.testing.assert_array_equal(message.points, points, strict=True)


def test_stats_gathered_while_robots_are_admitted_do_not_fail() -> None:
    """The stats queryable runs on a Zenoh thread while the worker admits robots: the pending
    count it gathers must not trip over the robots' dict growing (the stats query would go
    unanswered)."""
    service = DeskewService(DeskewSettings(max_robots=100_000),
                            ZenohSettings(mode="peer", connect=[]))
    try:
        failures = stats_failures_while(
            service.shell.stats, lambda i: service.robots.setdefault(f"r{i}", _Robot())
        )
    finally:
        service.shell.close(flush_s=0.0)
    assert failures == []


def deskew_in_process(
    events, odom_wait_s: float
) -> tuple[list[DeskewedScanMessage], dict[str, int]]:
    """Each scan and odometry sample handed to a deskew service (on its own peer session) as
    its inbox would: the scans it put, decoded, and its counters."""
    service = DeskewService(
        DeskewSettings(odom_wait_s=odom_wait_s), ZenohSettings(mode="peer", connect=[])
    )
    out: list[DeskewedScanMessage] = []
    service.shell.put = lambda key, payload: out.append(DeskewedScanMessage.decode(payload))
    try:
        handle_all(service, events)
    finally:
        service.shell.close(flush_s=0.0)
    return out, service.shell.counters.snapshot()


def handle_all(service: DeskewService, events) -> None:
    """Hand each scan and odometry sample to the service's worker as the inbox would."""
    for event in events:
        if isinstance(event, LaserScan):
            service.handle("scan", ScanMessage(event))
        else:
            service.handle("odom", OdometryMessage(event))


def test_a_seq_that_starts_again_on_the_same_clock_keeps_the_odometry() -> None:
    """A lidar driver restarted (its seq from 0, its stamps going on, odometry going on): the
    same run. It began a new run that waited for odometry to restart too, so every later scan
    went out without odometry (an audit saw them all 'none')."""
    events = list(source_events(None, "robot", 2.0, 4, None))
    half = len(events) // 2
    restarted = [
        dataclasses.replace(e, seq=e.seq - 10) if isinstance(e, LaserScan) and i >= half else e
        for i, e in enumerate(events)
    ]
    out, _ = deskew_in_process(restarted, odom_wait_s=10.0)
    expected = reference_points(restarted)
    assert len(out) == len(expected)
    assert {m.source_used for m in out} == {"odometry"}
    for message, points in zip(out, expected, strict=True):
        np.testing.assert_array_equal(message.points, points, strict=True)


def test_a_scan_or_sample_sent_twice_is_dropped_as_a_copy() -> None:
    """A client that puts a scan (or odometry sample) twice, without the Zenoh timestamp that
    shows the network's copies: the copy went out deskewed under the same seq, which the
    matcher and the map server take for a restart and wipe the robot's map. Now it is
    dropped and counted; the run and its odometry go on."""
    events = list(source_events(None, "robot", 2.0, 4, None))
    half = len(events) // 2
    scan = [e for e in events[:half] if isinstance(e, LaserScan)][-1]
    sample = next(e for e in events[half:] if isinstance(e, Odometry))
    at = events.index(sample) + 1
    twice = [*events[:half], scan, *events[half:at], sample, *events[at:]]
    out, counters = deskew_in_process(twice, odom_wait_s=10.0)
    expected = reference_deskew(events)
    assert [m.seq for m in out] == sorted(expected)  # each seq once: no restart downstream
    assert {m.source_used for m in out} == {"odometry"}
    for message in out:
        np.testing.assert_array_equal(message.points, expected[message.seq], strict=True)
    assert counters["duplicates.scan"] == counters["duplicates.odom"] == 1


def test_a_clock_reset_starts_a_new_run_named_in_the_stats() -> None:
    """The robot's clock jumps back a minute, seqs going on: its odometry went into the old
    run's buffer, which dropped every sample as older than its window (uncounted), and every
    later scan went out without odometry. Now a new run, counted and logged."""
    events = list(source_events(None, "robot", 2.0, 4, None))
    half = len(events) // 2
    reset = [dataclasses.replace(e, stamp_s=e.stamp_s - 60.0) if i >= half else e
             for i, e in enumerate(events)]
    out, counters = deskew_in_process(reset, odom_wait_s=10.0)
    expected = {**reference_deskew(reset[:half]), **reference_deskew(reset[half:])}
    assert [m.seq for m in out] == sorted(expected)
    assert {m.source_used for m in out} == {"odometry"}
    for message in out:
        np.testing.assert_array_equal(message.points, expected[message.seq], strict=True)
    assert counters["clock_reset.scan"] == counters["clock_reset.odom"] == 1


def test_odometry_on_a_clock_seconds_off_the_scans_is_named(caplog) -> None:
    """Odometry stamped 3 s behind the scans covers none of them: each went out uncorrected,
    seen only as deskewed.none, the reason never said. Now counted and logged with it."""
    events = [e if isinstance(e, LaserScan) else dataclasses.replace(e, stamp_s=e.stamp_s - 3.0)
              for e in source_events(None, "robot", 1.0, 4, None)]
    out, counters = deskew_in_process(events, odom_wait_s=0.0)
    assert {m.source_used for m in out} == {"none"}
    assert counters["odometry_missed"] == len(out) == 10
    assert "scan 0 deskewed by none, not odometry (#1): no pose source covers the sweep: " \
           "odometry: sweep ends at 0.075000 s, 2.9950 s after the newest odometry" in caplog.text


def test_a_retired_robot_is_dropped_whole_its_place_freed_and_it_comes_back_afresh() -> None:
    """SCANFLOW_DESKEW_MAX_ROBOTS=1: a second robot is refused until the first is retired; the
    retire drops its scans waiting for odometry (not deskewed), its odometry and its clocks,
    and a message of it after the retire starts it as a new robot."""
    events = list(source_events(None, "a", 1.0, 4, None))
    scans = [e for e in events if isinstance(e, LaserScan)]
    service = DeskewService(DeskewSettings(odom_wait_s=60.0, max_robots=1),
                            ZenohSettings(mode="peer", connect=[]))
    out: list[DeskewedScanMessage] = []
    service.shell.put = lambda key, payload: out.append(DeskewedScanMessage.decode(payload))
    try:
        # No odometry reaches into the last scan's sweep: it waits for some.
        handle_all(service, [e for e in events if e.stamp_s < scans[-1].stamp_s or e is scans[-1]])
        other = dataclasses.replace(scans[0], robot_id="b")
        service.handle("scan", ScanMessage(other))
        assert "b" not in service.robots  # refused: one robot at most
        held = service.robots["a"]
        pending, odometry = len(held.pending), len(held.odometry) + len(held.stage.odometry)
        assert pending >= 1 and odometry >= 1
        sent = len(out)
        dropped = service.retire("a")
        assert dropped.known and dropped.counts == {
            "scans_pending": pending, "odometry_samples": odometry}
        assert "a" not in service.robots and not service._last_stamps
        service.idle()
        assert len(out) == sent  # its held scans were dropped, not deskewed
        service.handle("scan", ScanMessage(other))  # the place is free
        assert list(service.robots) == ["b"]
        assert not service.retire("nobody").known
        service.handle("scan", ScanMessage(scans[3]))  # refused again: b holds the place
        assert "a" not in service.robots
        service.retire("b")
        service.handle("scan", ScanMessage(scans[3]))  # a new robot, mid-stream seq and all
        fresh = service.robots["a"]
        assert fresh is not held and fresh.previous is None and len(fresh.pending) == 1
    finally:
        service.shell.close(flush_s=0.0)
