"""Loop closure in the services (SCANFLOW_BACKEND_LOOP_CLOSURE), as real processes through a
real router, against the in-process pipeline with the back end.

A lap of the simulator's ring corridor with poor wheel odometry (seed 1). The front end comes
round within centimetres, below the default redraw thresholds (0.2 m / 2 deg), so here the back
end redraws at any shift (`REDRAW`): every optimisation from the revisit on redraws, seven from
scan 635 of 800 (two from 637 when culled). Poses, each redraw's frame correction, the served
map and the served path must equal the in-process pipeline's. tests/docker loads this module
by path for `ring_in_process` and `REDRAW_ENV`, so it takes no relative imports.
"""

from __future__ import annotations

import functools
import warnings

import numpy as np
import pytest
from scanflow import keys
from scanflow.config import BackendSettings, FrontendSettings
from scanflow.frontend.prior import FrontendStart
from scanflow.geometry import Pose2D
from scanflow.maps.export import save_npz
from scanflow.pipeline import Pipeline
from scanflow.scan import LaserScan
from scanflow.wire import InitialPoseMessage, MapInsertMessage, MapRedrawMessage

from services.ingest.sources import source_events

# Long service runs (about 3 min): `make test` runs them beside the rest (tools/run-tests.sh).
pytestmark = [pytest.mark.integration, pytest.mark.slow, pytest.mark.second_lane]

RING = {
    "SCANFLOW_INGEST_SIM_DURATION_S": "80", "SCANFLOW_INGEST_SIM_SEED": "1",
    "SCANFLOW_INGEST_SIM_WORLD": "loop", "SCANFLOW_INGEST_SIM_ODOM_SCALE_ERROR": "0.03",
}
REDRAW = {"redraw_shift_m": 0.001, "redraw_shift_deg": 0.01}
REDRAW_ENV = {f"SCANFLOW_BACKEND_{k.upper()}": str(v) for k, v in REDRAW.items()}
LOOP_CLOSURE = {"SCANFLOW_BACKEND_LOOP_CLOSURE": "true", **REDRAW_ENV}
ODOM_WAIT = {"SCANFLOW_DESKEW_ODOM_WAIT_S": "3"}  # as in test_pipeline_services


def ring_in_process(
    cull_m: float = 0.0, pipeline: Pipeline | None = None,
) -> tuple[Pipeline, list, list[tuple[int, Pose2D, np.ndarray, list]]]:
    """(pipeline, per-scan estimates, (seq, correction, corrected path, keyframe seqs) of
    every redraw), by default of a new pipeline with loop closure."""
    pipeline = pipeline or Pipeline(
        backend=BackendSettings(loop_closure=True, cull_m=cull_m, **REDRAW)
    )
    outputs, redraws = [], []
    for event in source_events(None, "robot", 80.0, 1, None, sim_world="loop",
                               sim_odom_scale_error=0.03):
        if not isinstance(event, LaserScan):
            pipeline.add_odometry(event)
            continue
        out = pipeline.process(event)
        outputs.append(out.estimate)
        if out.backend.redrawn:
            mapper = pipeline.mapper
            redraws.append((event.seq, out.backend.correction, mapper.trajectory(),
                            list(mapper.keyframe_seqs)))
    return pipeline, outputs, redraws


@functools.cache
def ring_reference(cull_m: float) -> tuple[Pipeline, list, list]:
    """`ring_in_process(cull_m)`, run once per `cull_m` for the tests here, which only read it:
    it is deterministic (the services must equal it bit for bit), and each run took 5-13 s of
    the five tests that need it."""
    return ring_in_process(cull_m)


def assert_served_as_in_process(bus, pipeline: Pipeline, expected: list, redraws: list) -> None:
    """The map server's map and path, once it has handled the last pose and the last insert,
    are the in-process pipeline's, bit for bit."""
    last = (expected[-1].seq, [o.seq for o in expected if o.inserted][-1])

    def handled() -> tuple[float, float]:
        gauges = bus.stats("mapserver").gauges
        return (gauges["seq.robot/pose.last"], gauges["robot.last_insert_seq"])

    bus.wait_until(lambda: handled() == last, 30.0, "map server caught up")
    served, want = bus.map_grid(), pipeline.frontend.map.grid
    assert served.extent == want.extent, str(bus.stats("mapserver").counters)  # all of them
    np.testing.assert_array_equal(served.log_odds, want.log_odds)
    np.testing.assert_array_equal(served.observed, want.observed)
    (path,) = bus.get(keys.trajectory("robot"))
    seq, _, at_redraw, _ = redraws[-1]
    after = [o.pose.to_array() for o in expected[seq + 1:]]
    np.testing.assert_array_equal(path.poses, np.vstack([at_redraw, *after]))


@pytest.mark.parametrize("cull_m", [0.0, 0.3], ids=["every insert a keyframe", "culled"])
def test_a_loop_closing_run_equals_the_in_process_pipeline(launcher, bus, start, cull_m):
    """With culling (SCANFLOW_BACKEND_CULL_M) about half the inserts are no keyframes: they
    go into the served map all the same, and the map server keeps only the keyframes."""
    start("deskew", **ODOM_WAIT, **LOOP_CLOSURE)
    start("matcher", **LOOP_CLOSURE, SCANFLOW_BACKEND_CULL_M=str(cull_m))
    start("mapserver", **LOOP_CLOSURE)
    poses = bus.record(keys.pose())
    redraws = bus.record(keys.map_key("*", "insert"))
    proc = launcher.start("ingest", **RING)
    proc.wait(180)
    assert proc.returncode == 0, launcher.log_text("ingest")
    pipeline, expected, expected_redraws = ring_reference(cull_m)
    assert len(expected_redraws) >= 1  # the run must exercise a redraw
    inserts = [m for m in redraws if isinstance(m, MapInsertMessage)]
    # Every insert the matcher made, in order, save those the bus lost on the way to this
    # recorder (`missed`, checked below: the map server must have had them sent again).
    made = [o.seq for o in expected if o.inserted]
    missed = sorted(set(made) - {m.seq for m in inserts})
    assert len(missed) <= len(made) // 50  # a transport's rare loss, not a matcher's omission
    assert [m.seq for m in inserts] == [seq for seq in made if seq not in missed]
    keyframes = [seq for seq in pipeline.mapper.keyframe_seqs if seq not in missed]
    assert [m.seq for m in inserts if m.keyframe] == keyframes
    assert (len(pipeline.mapper.culled_seqs) > 100) == (cull_m > 0)
    bus.wait_until(lambda: len(poses) >= len(expected), 60.0, "every pose")

    assert [p.seq for p in poses] == [o.seq for o in expected]
    for got, want in zip(poses, expected, strict=True):
        assert got.pose == want.pose, f"seq {got.seq}: {got.pose} != {want.pose}"
        np.testing.assert_array_equal(got.covariance, want.covariance)  # turned at a redraw
    corrected = [(p.seq, p.correction) for p in poses if p.correction is not None]
    assert corrected == [(r[0], r[1]) for r in expected_redraws]

    sent = [m for m in redraws if isinstance(m, MapRedrawMessage)]
    assert [m.seq for m in sent] == [r[0] for r in expected_redraws]
    for message, (_, correction, path, keyframes) in zip(sent, expected_redraws, strict=True):
        assert message.correction == correction
        np.testing.assert_array_equal(message.poses, path)
        np.testing.assert_array_equal(message.keyframe_seqs, keyframes)

    assert_served_as_in_process(bus, pipeline, expected, expected_redraws)

    matcher, mapserver = bus.stats("matcher"), bus.stats("mapserver")
    assert matcher.counters["backend.redraws"] == len(expected_redraws)
    assert matcher.counters["backend.closures"] == len(pipeline.mapper.closures)
    assert matcher.counters.get("backend.culled", 0) == len(pipeline.mapper.culled_seqs)
    assert mapserver.counters["redrawn"] == len(expected_redraws)
    assert mapserver.gauges["robot.keyframes"] == len(pipeline.mapper.keyframe_seqs)
    assert "errors.insert" not in mapserver.counters
    # Zenoh once lost two of the matcher's reliable puts to every subscriber under load (the
    # thirty-ninth session's entry of BENCHMARKS' Test suite). What scanflow promises is that
    # the map server has what it missed sent again: so an insert this recorder missed must
    # have been resent, and the served map above is then whole.
    if missed:
        warnings.warn(f"the bus lost inserts {missed} to the test's recorder", stacklevel=1)
        assert mapserver.counters.get("inserts_resent", 0) >= len(missed), mapserver.counters

    # An operator's pose is taken: the keyframe after it hangs from the one before by a weak
    # link only (tests/scanflow/backend: the closures then move it).
    request = InitialPoseMessage("robot", Pose2D(1.0, 0.0, 0.0)).encode()
    (echo,) = bus.get(keys.initial_pose("robot"), payload=request)
    assert echo.pose == Pose2D(1.0, 0.0, 0.0)
    assert bus.stats("matcher").counters["initial_poses"] == 1


def test_a_loop_closing_run_on_a_prior_map_equals_the_in_process_pipeline(
    launcher, bus, start, tmp_path
):
    """The ring's first 30 s, mapped in process, is the prior map of the matcher and the map
    server; the 80 s lap from the same start closes its loop on it. Poses, the redraw (drawn
    on the prior map) and the served map and path equal the in-process pipeline's on that
    prior map."""
    mapping = Pipeline()
    for event in source_events(None, "robot", 30.0, 1, None, sim_world="loop",
                               sim_odom_scale_error=0.03):
        if isinstance(event, LaserScan):
            mapping.process(event)
        else:
            mapping.add_odometry(event)
    prior = save_npz(mapping.frontend.map.grid, tmp_path / "prior.npz")
    on_prior = {"SCANFLOW_FRONTEND_PRIOR_MAP": str(prior),
                "SCANFLOW_FRONTEND_INITIAL_POSE": "0,0,0"}
    start("deskew", **ODOM_WAIT, **LOOP_CLOSURE)
    start("matcher", **LOOP_CLOSURE, **on_prior)
    start("mapserver", **LOOP_CLOSURE, **on_prior)
    poses = bus.record(keys.pose())
    proc = launcher.start("ingest", **RING)
    proc.wait(180)
    assert proc.returncode == 0, launcher.log_text("ingest")
    settings = FrontendSettings(prior_map=str(prior), initial_pose=[0.0, 0.0, 0.0])
    begin = FrontendStart(settings)
    pipeline, expected, expected_redraws = ring_in_process(pipeline=Pipeline(
        settings, initial_pose=begin.pose, grid=begin.grid(),
        backend=BackendSettings(loop_closure=True, **REDRAW),
    ))
    assert len(expected_redraws) >= 1 and pipeline.mapper.prior is not None
    bus.wait_until(lambda: len(poses) >= len(expected), 60.0, "every pose")
    assert [(p.seq, p.pose) for p in poses] == [(o.seq, o.pose) for o in expected]
    assert_served_as_in_process(bus, pipeline, expected, expected_redraws)
    assert bus.stats("mapserver").counters["redrawn"] == len(expected_redraws)


@pytest.mark.parametrize(
    ("recent", "cull_m"), [("256", 0.0), ("0", 0.0), ("2", 0.3)],
    ids=["recent inserts", "keyframes only", "culled: the whole map"],
)
def test_a_map_server_killed_before_the_redraw_catches_up_and_follows_it(
    launcher, bus, start, tmp_path, recent, cull_m
):
    """The map server killed mid-lap and restarted from its snapshot: the matcher sends the
    inserts it missed again (from its last inserts, or, keeping none, from the back end's
    keyframes; or, when the back end culled some of them, its whole map, path and
    keyframes), so it holds every keyframe when the redraw comes, and its map and path end
    as the in-process pipeline's. Its snapshot keeps the keyframes' scans 8 to a file."""
    snapshots = {
        "SCANFLOW_MAPSERVER_SNAPSHOT_INTERVAL_S": "0.5",
        "SCANFLOW_MAPSERVER_KEYFRAMES_PER_FILE": "8",
    }
    start("deskew", **ODOM_WAIT, **LOOP_CLOSURE)
    start("matcher", **LOOP_CLOSURE, SCANFLOW_MATCHER_RESEND_INSERTS=recent,
          SCANFLOW_BACKEND_CULL_M=str(cull_m))
    start("mapserver", **LOOP_CLOSURE, **snapshots)
    poses = bus.record(keys.pose())
    ingest = launcher.start("ingest", **RING, SCANFLOW_INGEST_RATE="4")  # 20 s
    bus.wait_until(lambda: len(poses) >= 300, 60.0, "300 poses before the crash")
    bus.wait_until(lambda: (tmp_path / "data" / "robot.snapshot.npz").exists(), 10.0,
                   "a snapshot")
    launcher.kill("mapserver")
    assert list((tmp_path / "data" / "robot.keyframes").glob("*-8-000000.npz"))
    start("mapserver", **LOOP_CLOSURE, **snapshots)
    ingest.wait(180.0)
    assert ingest.returncode == 0, launcher.log_text("ingest")
    pipeline, expected, expected_redraws = ring_reference(cull_m)
    assert expected_redraws[0][0] > 300  # the redraw comes after the restart
    bus.wait_until(lambda: poses and poses[-1].seq == 799, 60.0, "the last pose")
    assert_served_as_in_process(bus, pipeline, expected, expected_redraws)
    mapserver = bus.stats("mapserver")
    caught_up = "map_states_taken" if cull_m else "inserts_resent"
    assert mapserver.counters[caught_up] > 0, mapserver.counters
    assert mapserver.counters["redrawn"] == len(expected_redraws)
    assert "inserts_lost" not in mapserver.counters and "errors.insert" not in mapserver.counters


def test_a_restarted_matcher_resumes_loop_closure_from_the_map_servers_keyframes(
    launcher, bus, start
):
    """The matcher killed before the ring's revisit, restarted: it gets the keyframes back
    from the map server, closes the loop with keyframes from before the crash, and the map
    server follows that redraw."""
    start("deskew", **ODOM_WAIT, **LOOP_CLOSURE)
    start("matcher", **LOOP_CLOSURE)
    start("mapserver", **LOOP_CLOSURE)
    poses = bus.record(keys.pose())
    ingest = launcher.start("ingest", **RING, SCANFLOW_INGEST_WINDOW="4",
                            SCANFLOW_INGEST_STALL_TIMEOUT_S="2")
    bus.wait_until(lambda: len(poses) >= 300, 60.0, "300 poses before the crash")
    launcher.kill("matcher")
    start("matcher", **LOOP_CLOSURE)
    ingest.wait(180.0)
    assert ingest.returncode == 0, launcher.log_text("ingest")
    bus.wait_until(lambda: poses and poses[-1].seq == 799, 60.0, "the last pose")
    matcher = bus.stats("matcher")
    assert matcher.counters["resumed_robots"] == 1
    assert matcher.counters["backend.resumed"] == 1
    assert matcher.counters["backend.redraws"] >= 1, matcher.counters
    bus.wait_until(
        lambda: bus.stats("mapserver").counters.get("redrawn", 0)
        == matcher.counters["backend.redraws"], 30.0, "the map server to follow every redraw",
    )
    mapserver = bus.stats("mapserver")
    assert "errors.insert" not in mapserver.counters, launcher.log_text("mapserver")
    (path,) = bus.get(keys.trajectory("robot"))
    assert len(path.poses) == len({p.seq for p in poses})
    assert np.max(np.hypot(*np.diff(path.poses[:, :2], axis=0).T)) < 1.0  # no jump
