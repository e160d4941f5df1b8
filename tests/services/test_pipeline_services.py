"""The whole pipeline as real processes through a real router, against the in-process pipeline.

Reference: the plain `scanflow.pipeline.Pipeline` fed the same source events in the same order
(`services.ingest.sources.source_events`); poses and the served map must equal it bit for bit.
"""

from __future__ import annotations

import math
import os
from pathlib import Path

import httpx
import numpy as np
import pytest
from scanflow import keys
from scanflow.config import FrontendSettings, ServiceSettings
from scanflow.frontend import FrontendOutput, FrontendStatus
from scanflow.frontend.prior import FrontendStart
from scanflow.geometry import Pose2D
from scanflow.maps.export import save_map
from scanflow.maps.occupancy import OccupancyGrid
from scanflow.pipeline import Pipeline
from scanflow.scan import LaserScan
from scanflow.wire import InitialPoseMessage, OdometryMessage, PoseEstimateMessage, ScanMessage

from services.common.launch import free_port, wait_for_port
from services.common.process import available_cpus
from services.ingest.sources import source_events

pytestmark = [pytest.mark.integration, pytest.mark.slow]

SIM_S = 6.0
SIM = {"SCANFLOW_INGEST_SIM_DURATION_S": str(SIM_S), "SCANFLOW_INGEST_SIM_SEED": "7"}
LOG_SCANS = 40


def in_process(
    events, pipeline: Pipeline | None = None
) -> tuple[list[FrontendOutput], OccupancyGrid]:
    """(per-scan front end outputs, final grid) of the in-process pipeline (default: a new
    `Pipeline()`) on `events`."""
    pipeline = pipeline or Pipeline()
    outputs = []
    for event in events:
        if isinstance(event, LaserScan):
            outputs.append(pipeline.process(event).estimate)
        else:
            pipeline.add_odometry(event)
    return outputs, pipeline.frontend.map.grid


def assert_same_grid(served: OccupancyGrid, expected: OccupancyGrid) -> None:
    assert served.extent == expected.extent
    np.testing.assert_array_equal(served.log_odds, expected.log_odds)
    np.testing.assert_array_equal(served.observed, expected.observed)


def assert_same_poses(poses: list[PoseEstimateMessage], expected: list) -> None:
    assert [p.seq for p in poses] == [o.seq for o in expected]
    for got, want in zip(poses, expected, strict=True):
        assert got.status == str(want.status), f"seq {got.seq}"
        assert got.pose == want.pose, f"seq {got.seq}: {got.pose} != {want.pose}"
        np.testing.assert_array_equal(got.covariance, want.covariance)


# The deskew latency budget is wall-clock: on a loaded machine the odometry callback thread can
# run more than the default 50 ms after the scan's, and the scan then falls back (uncorrected),
# by design. Equality is checked with a budget these runs never reach.
ODOM_WAIT = {"SCANFLOW_DESKEW_ODOM_WAIT_S": "3"}


@pytest.fixture
def pipeline(launcher, bus, start):
    """Router, deskew, matcher and map server running; yields (launcher, bus)."""
    start("deskew", **ODOM_WAIT)
    for name in ("matcher", "mapserver"):
        start(name)
    return launcher, bus


def run_ingest(launcher, bus, timeout_s: float = 120.0, **settings: str) -> None:
    proc = launcher.start("ingest", **settings)
    proc.wait(timeout_s)
    assert proc.returncode == 0, launcher.log_text("ingest")


def assert_every_scan_processed(bus, scans: int) -> None:
    """Deskew and matcher each took every scan, no stream reports a missed seq, and the
    credit window alone held ingest back (no inbox filled), the workers report their load."""
    deskew, matcher = bus.stats("deskew"), bus.stats("matcher")
    assert deskew.counters["received.scan"] == scans
    assert matcher.counters["received.scan"] == scans
    queue_size = ServiceSettings.model_fields["queue_size"].default
    for stats in (deskew, matcher):
        assert all(v == 0 for k, v in stats.counters.items() if k.endswith(".missed")), stats
        assert stats.gauges["inbox_high_water"] < queue_size, stats.gauges
        assert stats.gauges["worker_busy_s"] > 0.0
        assert 0.0 < stats.gauges["put_s"] <= stats.gauges["worker_busy_s"]


def assert_served_map(bus, grid: OccupancyGrid, scans: int) -> None:
    bus.wait_until(
        lambda: bus.stats("mapserver").counters.get("received.pose", 0) >= scans,
        30.0, "map server caught up",
    )
    assert_same_grid(bus.map_grid(), grid)


def test_simulated_run_equals_the_in_process_pipeline(pipeline):
    launcher, bus = pipeline
    poses = bus.record(keys.pose())
    notices = bus.record(keys.map_key("*", "changed"))
    run_ingest(launcher, bus, **SIM)
    expected, grid = in_process(source_events(None, "robot", SIM_S, 7, None))
    bus.wait_until(lambda: len(poses) >= len(expected), 30.0, "every pose")
    assert_same_poses(poses, expected)
    assert_served_map(bus, grid, len(expected))
    assert_every_scan_processed(bus, len(expected))
    (path,) = bus.get(keys.trajectory("robot"))
    np.testing.assert_array_equal(path.poses, [o.pose.to_array() for o in expected])
    assert_map_queries(bus, grid, notices)


def test_a_mounted_lidar_run_equals_the_in_process_pipeline(pipeline):
    """The simulator's lidar off the robot's centre (SCANFLOW_INGEST_MOUNT): the mount travels
    with raw scans, deskewed scans and map inserts, so poses and map equal in-process."""
    launcher, bus = pipeline
    poses = bus.record(keys.pose())
    run_ingest(launcher, bus, SCANFLOW_INGEST_MOUNT="0.35,-0.1,25", **SIM)
    mount = Pose2D(0.35, -0.1, math.radians(25.0))
    expected, grid = in_process(source_events(None, "robot", SIM_S, 7, None, mount))
    bus.wait_until(lambda: len(poses) >= len(expected), 30.0, "every pose")
    assert_same_poses(poses, expected)
    assert_served_map(bus, grid, len(expected))
    unmounted, _ = in_process(source_events(None, "robot", SIM_S, 7, None))
    assert [o.pose for o in expected] != [o.pose for o in unmounted]


@pytest.fixture
def on_prior_map(launcher, bus, start, tmp_path):
    """Deskew, and matcher and map server localising (UPDATE_MAP=false) on a prior map: the
    simulator's own run mapped in-process. Yields (launcher, bus, prior map file, its grid)."""
    _, prior = in_process(source_events(None, "robot", SIM_S, 7, None))
    path = save_map(prior, tmp_path / "prior.npz")
    env = {"SCANFLOW_FRONTEND_PRIOR_MAP": str(path), "SCANFLOW_FRONTEND_UPDATE_MAP": "false"}
    start("deskew", **ODOM_WAIT)
    for name in ("matcher", "mapserver"):
        start(name, **env)
    return launcher, bus, path, prior


def localising(path: Path, initial_pose: Pose2D | None) -> Pipeline:
    settings = FrontendSettings.model_construct(prior_map=str(path), update_map=False)
    start = FrontendStart(settings)
    return Pipeline(settings, initial_pose=initial_pose or start.pose, grid=start.grid())


def test_localising_on_a_prior_map_equals_the_in_process_pipeline(on_prior_map):
    """SCANFLOW_FRONTEND_PRIOR_MAP and UPDATE_MAP=false on matcher and map server: the robot is
    found on the map by the whole-map search, tracked on it as in-process, and the map served
    is the prior map, unchanged."""
    launcher, bus, path, prior = on_prior_map
    poses = bus.record(keys.pose())
    run_ingest(launcher, bus, **SIM)
    expected, _ = in_process(source_events(None, "robot", SIM_S, 7, None), localising(path, None))
    assert expected[0].status is FrontendStatus.LOCALISED
    assert all(o.accepted and not o.inserted for o in expected)
    bus.wait_until(lambda: len(poses) >= len(expected), 30.0, "every pose")
    assert_same_poses(poses, expected)
    assert_served_map(bus, prior, len(expected))


def test_an_operators_pose_on_the_bus_starts_the_robot_there(on_prior_map):
    """An InitialPoseMessage for a robot not seen yet: the matcher echoes it, and the robot's
    first scan is matched from it (no whole-map search), exactly as in-process."""
    launcher, bus, path, _ = on_prior_map
    told = Pose2D(0.12, -0.08, 0.04)  # roughly where the simulated robot starts
    request = InitialPoseMessage("robot", told).encode()
    (echo,) = bus.get(keys.initial_pose("robot"), payload=request)
    assert isinstance(echo, InitialPoseMessage) and echo.pose == told
    assert bus.stats("matcher").counters["initial_poses"] == 1
    with pytest.raises(AssertionError, match="must be sent on scanflow/robot/initial_pose"):
        bus.get(keys.initial_pose("other"), payload=request)  # another robot's key: refused
    poses = bus.record(keys.pose())
    run_ingest(launcher, bus, **SIM)
    expected, _ = in_process(source_events(None, "robot", SIM_S, 7, None), localising(path, told))
    assert expected[0].status is FrontendStatus.TRACKED
    assert expected[0].pose.translation_norm() < 0.05
    bus.wait_until(lambda: len(poses) >= len(expected), 30.0, "every pose")
    assert_same_poses(poses, expected)


def test_full_inboxes_hold_the_pipeline_back_without_deadlock(launcher, bus, start):
    """Inboxes far smaller than the credit window fill up and block their Zenoh links: deskew
    waits on the matcher (scans) while the matcher waits to publish the poses deskew takes
    back; those come in on deskew's feedback session, so the run still completes, exactly."""
    tiny = {"SCANFLOW_DESKEW_QUEUE_SIZE": "2", "SCANFLOW_MATCHER_QUEUE_SIZE": "2", **ODOM_WAIT}
    for name in ("deskew", "matcher", "mapserver"):
        start(name, **{k: v for k, v in tiny.items() if name.upper() in k})
    poses = bus.record(keys.pose())
    run_ingest(launcher, bus, SCANFLOW_INGEST_WINDOW="64", **SIM)
    expected, grid = in_process(source_events(None, "robot", SIM_S, 7, None))
    bus.wait_until(lambda: len(poses) >= len(expected), 30.0, "every pose")
    assert_same_poses(poses, expected)
    assert_served_map(bus, grid, len(expected))
    for service in ("deskew", "matcher"):
        assert bus.stats(service).gauges["inbox_high_water"] == 2


def test_a_replay_restarts_every_service_and_comes_out_the_same(pipeline):
    """The source restarts its seqs (a replay): deskew, matcher and map server each start the
    robot afresh, whichever of its streams shows the restart first."""
    launcher, bus = pipeline
    poses = bus.record(keys.pose())
    run_ingest(launcher, bus, SCANFLOW_INGEST_REPLAYS="2", **SIM)
    expected, grid = in_process(source_events(None, "robot", SIM_S, 7, None))
    bus.wait_until(lambda: len(poses) >= 2 * len(expected), 30.0, "every pose of both runs")
    assert_same_poses(poses[: len(expected)], expected)
    assert_same_poses(poses[len(expected) :], expected)
    assert_served_map(bus, grid, 2 * len(expected))


def test_a_robot_fed_over_http_is_tracked_and_mapped_as_in_process(pipeline):
    """A client without Zenoh posts a simulated run's odometry and scans to the gateway (msgpack,
    as the wire has them): poses and the served map are the in-process pipeline's, bit for bit.
    A retried scan (its seq taken) is a 409, and no service starts the robot afresh for it."""
    launcher, bus = pipeline
    port = free_port()
    launcher.start("gateway", SCANFLOW_GATEWAY_PORT=str(port))
    wait_for_port(port, 30.0)
    poses = bus.record(keys.pose())
    events = list(source_events(None, "robot", SIM_S, 7, None))
    msgpack = {"Content-Type": "application/x-msgpack"}
    with httpx.Client(base_url=f"http://127.0.0.1:{port}/api/v1", timeout=30.0) as http:
        bus.wait_until(lambda: http.get("/health").json()["missing"] == [], 30.0,
                       "the gateway to see every service")
        for event in events:
            scan = isinstance(event, LaserScan)
            message = ScanMessage(event) if scan else OdometryMessage(event)
            r = http.post(f"/robots/robot/{'scans' if scan else 'odometry'}",
                          content=message.encode(), headers=msgpack)
            assert r.status_code == 202 and r.json()["seq"] == event.seq, r.text
        expected, grid = in_process(events)
        bus.wait_until(lambda: len(poses) >= len(expected), 60.0, "every pose")
        retried = http.post("/robots/robot/scans", content=message.encode(), headers=msgpack)
        assert retried.status_code == 409, retried.text
        latest = http.get("/robots/robot/pose").json()
    assert_same_poses(poses, expected)
    assert (latest["seq"], latest["x_m"], latest["y_m"], latest["theta_rad"]) == (
        expected[-1].seq, *expected[-1].pose.to_array().tolist())
    assert_served_map(bus, grid, len(expected))
    for service in ("deskew", "matcher", "mapserver"):
        seqs = bus.stats(service).counters
        assert not any(v for k, v in seqs.items() if k.endswith(".restarts")), (service, seqs)


def assert_map_queries(bus, grid: OccupancyGrid, notices: list) -> None:
    """Region, images and change notices agree with the in-process map."""
    (meta,) = bus.get(keys.map_key("robot", "meta"))
    assert meta.spec == grid.spec
    (whole,) = bus.get(keys.map_key("robot", "region"))
    np.testing.assert_array_equal(whole.occupancy, grid.to_int8())
    x0, y0 = grid.spec.origin_x_m + 0.525, grid.spec.origin_y_m + 0.275  # mid-cell corners
    selector = f"{keys.map_key('robot', 'region')}?x0={x0};y0={y0};x1={x0 + 1.0};y1={y0 + 2.0}"
    (window,) = bus.get(selector)
    rows, cols = window.occupancy.shape
    assert (rows, cols) == (41, 21)  # 2 m x 1 m at 5 cm, both corner cells included
    r0, c0 = window.row0, window.col0
    np.testing.assert_array_equal(window.occupancy, grid.to_int8()[r0 : r0 + rows, c0 : c0 + cols])
    (png,) = bus.get(f"{keys.map_key('robot', 'image')}?format=png")
    assert png.data.startswith(b"\x89PNG")
    (yaml,) = bus.get(f"{keys.map_key('robot', 'image')}?format=yaml")
    assert f"resolution: {grid.resolution_m!r}" in yaml.data.decode()
    (pgm,) = bus.get(f"{keys.map_key('robot', 'image')}?format=pgm")
    assert pgm.data.startswith(b"P5")
    bus.wait_until(lambda: notices and notices[-1].revision == meta.revision, 10.0, "last notice")
    revisions = [n.revision for n in notices]
    assert revisions == sorted(set(revisions))


def test_real_log_slice_equals_the_in_process_pipeline(pipeline, data_file):
    launcher, bus = pipeline
    log = data_file("aces-corrected.log.gz")
    poses = bus.record(keys.pose())
    limit = {"SCANFLOW_INGEST_LOG": str(log), "SCANFLOW_INGEST_LIMIT": str(LOG_SCANS)}
    run_ingest(launcher, bus, **limit)
    expected, grid = in_process(source_events(str(log), "robot", 1.0, 0, LOG_SCANS))
    assert len(expected) == LOG_SCANS
    assert sum(o.inserted for o in expected) > 1  # the map grew beyond the first scan
    bus.wait_until(lambda: len(poses) >= LOG_SCANS, 30.0, "every pose")
    assert_same_poses(poses, expected)
    assert_served_map(bus, grid, LOG_SCANS)
    assert_every_scan_processed(bus, LOG_SCANS)


def test_two_matchers_split_the_robots_by_shard(launcher, bus, start):
    start("deskew")
    for index in ("0", "1"):
        shard = {"SCANFLOW_MATCHER_INSTANCE": index, "SCANFLOW_MATCHER_SHARD": f"{index}/2"}
        start("matcher", f"matcher-{index}", **shard)
    poses = bus.record(keys.pose())
    sim = {"SCANFLOW_INGEST_SIM_DURATION_S": "2"}
    for robot in ("alpha", "beta"):  # CRC-32 puts alpha on shard 0, beta on shard 1
        run_ingest(launcher, bus, SCANFLOW_INGEST_ROBOT_ID=robot, **sim)
    for robot in ("alpha", "beta"):
        assert [p.seq for p in poses if p.robot_id == robot] == list(range(20))
    first, second = bus.stats("matcher", "0"), bus.stats("matcher", "1")
    assert first.gauges["robots"] == 1 and second.gauges["robots"] == 1
    assert first.counters["other_shard.scan"] == 20 == second.counters["other_shard.scan"]
    assert_cpu_plan(launcher, ["deskew", "matcher-0", "matcher-1"])


def assert_cpu_plan(launcher, labels: list[str]) -> None:
    """With 2+ CPUs the first matcher runs on a CPU of its own, every other process on the
    rest (SCANFLOW_LAUNCH_MATCHER_CPUS=1 by default); with one CPU nothing is pinned."""
    cpus = {label: os.sched_getaffinity(launcher.processes[label].pid) for label in labels}
    available = set(available_cpus())
    if len(available) < 2:
        assert all(c == available for c in cpus.values())
        return
    (own,) = cpus.pop("matcher-0")
    assert all(c == available - {own} for c in cpus.values()), cpus
