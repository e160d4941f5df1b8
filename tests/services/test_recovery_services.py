"""Crash and restart the matcher or the map server mid-run; junk on every subscribed key;
match requests. Real processes, a real router."""

from __future__ import annotations

import numpy as np
import pytest
from scanflow import keys
from scanflow.frontend import ACCEPTED
from scanflow.scan import LaserScan
from scanflow.wire import MapRef, MatchRequest, MatchResponse

from services.ingest.sources import source_events

from .test_pipeline_services import assert_same_grid, in_process

# Crashes and restarts of real services (about 65 s): `make test` runs them beside the rest
# (tools/run-tests.sh), after the container tests.
pytestmark = [pytest.mark.integration, pytest.mark.slow, pytest.mark.second_lane]

SCANS = 80
SIM = {
    "SCANFLOW_INGEST_SIM_DURATION_S": str(SCANS / 10),
    "SCANFLOW_INGEST_SIM_SEED": "3",
    "SCANFLOW_INGEST_WINDOW": "4",
    "SCANFLOW_INGEST_STALL_TIMEOUT_S": "2",
}


@pytest.fixture
def pipeline(launcher, bus, start):
    for name in ("deskew", "matcher", "mapserver"):  # deskew waits for odometry: as in-process
        start(name, SCANFLOW_MAPSERVER_SNAPSHOT_INTERVAL_S="0.5", SCANFLOW_DESKEW_ODOM_WAIT_S="3")
    return launcher, bus, start


def max_step_m(poses: np.ndarray) -> float:
    return float(np.max(np.hypot(*np.diff(poses[:, :2], axis=0).T)))


def test_matcher_crash_resumes_from_the_map_server_and_gaps_are_reported(pipeline):
    launcher, bus, start = pipeline
    poses = bus.record(keys.pose())
    ingest = launcher.start("ingest", **SIM)
    bus.wait_until(lambda: len(poses) >= 20, 60.0, "20 poses before the crash")
    launcher.kill("matcher")
    start("matcher")
    ingest.wait(120.0)
    assert ingest.returncode == 0
    log = launcher.log_text("ingest")
    assert f"{SCANS} scans published" in log
    seqs = [p.seq for p in poses]
    assert seqs[-1] == SCANS - 1  # the pipeline carried on to the end
    missed = SCANS - len(set(seqs))
    assert missed > 0  # scans in flight when the matcher died are gone...
    mapserver = bus.stats("mapserver")
    assert mapserver.counters["seq.robot/pose.missed"] == missed  # ...and reported
    matcher = bus.stats("matcher")
    assert matcher.counters["resumed_robots"] == 1
    after = [p for p in poses if p.seq > 20]
    accepted = sum(p.status in ACCEPTED for p in after)
    assert accepted >= 0.7 * len(after), [p.status for p in after]
    (path,) = bus.get(keys.trajectory("robot"))
    assert max_step_m(path.poses) < 1.0  # resumed where it was, no jump back to the origin


def test_map_server_crash_resumes_from_its_snapshot(pipeline, tmp_path):
    launcher, bus, start = pipeline
    poses = bus.record(keys.pose())
    ingest = launcher.start("ingest", **{**SIM, "SCANFLOW_INGEST_RATE": "1"})  # 8 s
    bus.wait_until(lambda: len(poses) >= 20, 60.0, "20 poses before the crash")
    data = tmp_path / "data"
    bus.wait_until(
        lambda: (data / "robot.snapshot.npz").exists(),
        10.0,
        "a complete snapshot",
    )
    launcher.kill("mapserver")
    start("mapserver", SCANFLOW_MAPSERVER_SNAPSHOT_INTERVAL_S="0.5")
    log = bus.wait_until(
        lambda: "resumed at seq " in (text := launcher.log_text("mapserver")) and text,
        10.0,
        "the restarted map server to log where it resumed",
    )
    resumed_at = int(log.split("resumed at seq ")[1].split()[0])
    assert resumed_at >= 0
    ingest.wait(120.0)
    assert ingest.returncode == 0
    bus.wait_until(
        lambda: bus.stats("mapserver").gauges["seq.robot/pose.last"] == SCANS - 1, 30.0, "last pose"
    )
    stats = bus.stats("mapserver")
    missed = stats.counters["seq.robot/pose.missed"]
    received = stats.counters["seq.robot/pose.received"]
    assert missed > 0
    assert resumed_at + 1 + missed + received == SCANS
    (path,) = bus.get(keys.trajectory("robot"))
    assert len(path.poses) == resumed_at + 1 + received
    # The inserts made while it was down came again from the matcher: the map is whole.
    outputs, grid = in_process(source_events(None, "robot", SCANS / 10, 3, None))
    last_insert = max(o.seq for o in outputs if o.inserted)
    bus.wait_until(
        lambda: bus.stats("mapserver").gauges["robot.last_insert_seq"] == last_insert,
        30.0, "the last insert",
    )
    stats = bus.stats("mapserver")
    assert stats.counters["inserts_resent"] > 0, stats.counters
    assert "inserts_lost" not in stats.counters
    assert_same_grid(bus.map_grid(), grid)


def test_a_map_server_down_past_the_matchers_recent_inserts_takes_its_whole_map(
    launcher, bus, start, tmp_path
):
    """The matcher keeps its last 2 inserts only and tracks without loop closure, so the
    inserts made while the map server was down cannot come again: the map server takes the
    matcher's whole map and path instead. Both end as the in-process pipeline's, every scan's
    pose included, though the map server missed some of them."""
    for name in ("deskew", "matcher", "mapserver"):
        start(name, SCANFLOW_MAPSERVER_SNAPSHOT_INTERVAL_S="0.5", SCANFLOW_DESKEW_ODOM_WAIT_S="3",
              SCANFLOW_MATCHER_RESEND_INSERTS="2")
    poses = bus.record(keys.pose())
    ingest = launcher.start("ingest", **{**SIM, "SCANFLOW_INGEST_RATE": "1"})  # 8 s
    bus.wait_until(lambda: len(poses) >= 15, 60.0, "15 poses before the crash")
    data = tmp_path / "data"
    bus.wait_until(lambda: (data / "robot.snapshot.npz").exists(), 10.0, "a snapshot")
    launcher.kill("mapserver")
    down_at = len(poses)
    bus.wait_until(lambda: len(poses) >= down_at + 25, 30.0, "25 poses while it is down")
    start("mapserver", SCANFLOW_MAPSERVER_SNAPSHOT_INTERVAL_S="0.5")
    ingest.wait(120.0)
    assert ingest.returncode == 0
    outputs, grid = in_process(source_events(None, "robot", SCANS / 10, 3, None))
    last_insert = max(o.seq for o in outputs if o.inserted)
    bus.wait_until(
        lambda: (bus.stats("mapserver").gauges["robot.last_insert_seq"],
                 bus.stats("mapserver").gauges["seq.robot/pose.last"]) == (last_insert, SCANS - 1),
        30.0, "the last insert and the last pose",
    )
    stats = bus.stats("mapserver")
    assert stats.counters["map_states_taken"] == 1, stats.counters
    assert stats.counters["seq.robot/pose.missed"] > 0  # it did miss poses...
    assert "inserts_lost" not in stats.counters
    assert bus.stats("matcher").counters["map_states_sent"] == 1
    assert_same_grid(bus.map_grid(), grid)
    (path,) = bus.get(keys.trajectory("robot"))  # ...and serves them all the same
    np.testing.assert_array_equal(path.poses, [o.pose.to_array() for o in outputs])
    assert "took its whole map" in launcher.log_text("mapserver")


def test_junk_on_every_key_is_counted_and_match_requests_are_answered(pipeline):
    launcher, bus, start = pipeline
    start("ingest", SCANFLOW_INGEST_RATE="0.5", SCANFLOW_INGEST_SIM_DURATION_S="4")
    junk = b"\x93not a message"
    for key in (
        keys.raw_scan("robot"),
        keys.odom("robot"),
        keys.deskewed_scan("robot"),
        keys.pose("robot"),
        keys.map_key("robot", "insert"),
    ):
        bus.put(key, junk)
    poses = bus.record(keys.pose())
    bus.wait_until(lambda: len(poses) >= 5, 60.0, "poses despite the junk")
    expected = {
        "deskew": ("scan", "odom", "pose"),
        "matcher": ("scan",),  # deskewed scans only: they carry the odometry pose
        "mapserver": ("insert", "pose"),
        "ingest": ("pose",),
    }
    for service, kinds in expected.items():
        stats = bus.stats(service)
        for kind in kinds:
            assert stats.counters.get(f"malformed.{kind}") == 1, (service, kind, stats.counters)
    with pytest.raises(AssertionError, match=r"msgpack|payload"):
        bus.get(keys.scan_match(), payload=junk)
    scans = [e for e in source_events(None, "robot", 1.0, 0, 3) if isinstance(e, LaserScan)]
    request = MatchRequest(method="icp", source=scans[1], target=scans[0])
    # Started without its warm-up (conftest's NO_WARM_UP), the matcher loads each method's
    # kernels at its first request: time enough for that on a loaded machine.
    (answer,) = bus.get(keys.scan_match(), timeout_s=60.0, payload=request.encode())
    assert isinstance(answer, MatchResponse) and answer.ok, answer
    assert np.hypot(answer.pose.x, answer.pose.y) < 0.5
    to_map = MatchRequest(method="gn", source=scans[0], target=MapRef("robot"))
    (answer,) = bus.get(keys.robot_match("robot"), timeout_s=60.0, payload=to_map.encode())
    assert answer.error == "", answer
    # Where on the robot's map is this scan, with no guess: the whole-map search by name.
    anywhere = MatchRequest(method="global", source=scans[0], target=MapRef("robot"))
    (answer,) = bus.get(keys.robot_match("robot"), timeout_s=60.0, payload=anywhere.encode())
    assert answer.error == "" and answer.status in ("ok", "ambiguous"), answer
    not_a_map = MatchRequest(method="global", source=scans[1], target=scans[0])
    (answer,) = bus.get(keys.scan_match(), payload=not_a_map.encode())
    assert "must be a MatchingMap" in answer.error
    assert launcher.exited() == {} or set(launcher.exited()) == {"ingest"}
