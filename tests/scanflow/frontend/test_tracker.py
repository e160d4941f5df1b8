"""Frontend: tracking with and without odometry, and bad input that must not touch the map."""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable
from dataclasses import replace

import numpy as np
import pytest
from numpy.typing import NDArray
from scanflow.config import FrontendSettings
from scanflow.deskew import NO_RETURN_RANGE_M
from scanflow.frontend import (
    Frontend,
    FrontendOutput,
    FrontendStatus,
    PredictionSource,
    insert_scan,
    occupancy_params,
)
from scanflow.geometry import Pose2D
from scanflow.maps.grid import CellBox
from scanflow.maps.matching_map import MatchingMap
from scanflow.maps.occupancy import OccupancyGrid, OccupancyParams
from scanflow.matching import MatchResult, MatchStatus
from scanflow.matching import api as matching_api
from scanflow.matching.field_cost import assess_field_match, field_pyramid
from scanflow.sim import get_world
from scanflow.sim.raycast import static_scan

START = Pose2D(2.5, 2.0, 0.0)
# The map frame is turned against the world so walls do not lie on grid cell boundaries.
MAP_FROM_WORLD = Pose2D(0.013, -0.021, 0.3)
START_IN_MAP = MAP_FROM_WORLD * START
Scanner = Callable[[Pose2D], NDArray[np.float64]]


def straight_path(start: Pose2D, step_m: float, count: int) -> list[Pose2D]:
    """Poses `step_m` apart along the start heading."""
    return [start * Pose2D(i * step_m, 0.0, 0.0) for i in range(count)]


def odometry_with_drift(poses: list[Pose2D], scale: float = 1.03) -> list[Pose2D]:
    """Odometry that over-reads distance by `scale` and starts in its own frame."""
    odom = [Pose2D(-7.0, 4.0, 1.0)]
    for a, b in itertools.pairwise(poses):
        step = b.relative_to(a)
        odom.append(odom[-1] * Pose2D(step.x * scale, step.y * scale, step.theta))
    return odom


def error(estimate: Pose2D, world_pose: Pose2D) -> tuple[float, float]:
    """Translation and |rotation| error of a map-frame estimate against a world pose."""
    e = estimate.relative_to(MAP_FROM_WORLD * world_pose)
    return e.translation_norm(), abs(e.theta)


def run(
    frontend: Frontend,
    scan_points: Scanner,
    poses: list[Pose2D],
    odom: list[Pose2D] | None,
    t0: int = 0,
) -> list[FrontendOutput]:
    """Feed the scans taken at world `poses` (10 Hz stamps) with optional odometry poses."""
    outs = []
    for i, pose in enumerate(poses):
        odom_pose = None if odom is None else odom[i]
        outs.append(frontend.process(scan_points(pose), 0.1 * (t0 + i), odom_pose, t0 + i))
    return outs


def test_tracks_drifting_odometry(
    settings: FrontendSettings, scan_at: Scanner
) -> None:
    truth = straight_path(START, 0.1, 40)
    frontend = Frontend(settings, initial_pose=START_IN_MAP)
    outs = run(frontend, scan_at, truth, odometry_with_drift(truth))
    assert outs[0].status is FrontendStatus.INITIALISED and outs[0].inserted
    assert all(o.status is FrontendStatus.TRACKED for o in outs[1:])
    assert all(o.prediction_source == PredictionSource.ODOMETRY for o in outs[1:])
    # Odometry over-reads 3 %: 12 cm after 3.9 m. The map holds the estimate to a few cm
    # (what is left is the matcher's own drift on a grid map, not the front end's).
    trans, rot = error(outs[-1].pose, truth[-1])
    assert trans < 0.06 and rot < math.radians(1.0)
    assert np.all(np.isfinite(outs[-1].covariance))
    # Motion filter at 0.2 m: every second scan of a 0.1 m step path is inserted.
    inserted = [o.inserted for o in outs]
    assert 15 <= sum(inserted) <= 25
    assert len(frontend.trajectory) == 40


def test_tracks_without_odometry_by_constant_velocity(
    settings: FrontendSettings, scan_at: Scanner
) -> None:
    truth = [START * Pose2D(0.08 * i, 0.0, math.radians(1.0) * i) for i in range(25)]
    frontend = Frontend(settings, initial_pose=START_IN_MAP)
    outs = run(frontend, scan_at, truth, None)
    assert outs[1].prediction_source == PredictionSource.HOLD
    assert outs[5].prediction_source == PredictionSource.CONSTANT_VELOCITY
    assert all(o.accepted for o in outs)
    trans, rot = error(outs[-1].pose, truth[-1])
    assert trans < 0.06 and rot < math.radians(1.0)


def test_too_few_points_keeps_map_and_reports(
    settings: FrontendSettings, scan_at: Scanner
) -> None:
    truth = straight_path(START, 0.1, 6)
    odom = odometry_with_drift(truth, 1.0)
    frontend = Frontend(settings, initial_pose=START_IN_MAP)
    run(frontend, scan_at, truth[:3], odom[:3])
    revision = frontend.map.revision
    before = frontend.process(scan_at(truth[3])[:5], 0.3, odom[3], 3)
    assert before.status is FrontendStatus.TOO_FEW_POINTS
    assert "min_points" in before.message and not before.inserted
    assert frontend.map.revision == revision
    assert error(before.pose, truth[3])[0] < 0.02  # the odometry prediction
    # Carries on: the next scan tracks again.
    after = frontend.process(scan_at(truth[4]), 0.4, odom[4], 4)
    assert after.status is FrontendStatus.TRACKED


def _cleared_along_x(frontend: Frontend, origin: Pose2D, distances_m: NDArray) -> NDArray:
    """Whether the map holds free cells at `distances_m` from `origin` along the map's x axis."""
    grid = frontend.map.grid
    box = grid.extent
    assert box is not None
    world = np.column_stack((origin.x + distances_m, np.full(len(distances_m), origin.y)))
    cells = grid.world_to_cells(world) - (box.row0, box.col0)
    rows, cols = cells[:, 0], cells[:, 1]
    inside = (rows >= 0) & (rows < box.shape[0]) & (cols >= 0) & (cols < box.shape[1])
    out = np.zeros(len(distances_m), dtype=bool)
    out[inside] = grid.free_mask(0.5)[rows[inside], cols[inside]]
    return out


def test_no_return_beams_clear_up_to_the_clear_distance_only(settings: FrontendSettings) -> None:
    """A wall behind the sensor, a beam ahead that saw nothing: its cells are free up to the
    map's no_return_clear_m (5 m) and unknown beyond."""
    behind = np.linspace(math.pi / 2, 3 * math.pi / 2, 181)
    wall = 3.0 * np.column_stack((np.cos(behind), np.sin(behind)))
    pose = MAP_FROM_WORLD * START
    # The beam runs along the map's x axis, so its cells are one row of the grid.
    beam = Pose2D(0.0, 0.0, -pose.theta).transform_points(np.array([[NO_RETURN_RANGE_M, 0.0]]))
    frontend = Frontend(settings, initial_pose=pose)
    out = frontend.process(wall, 0.0, None, 0, beam)
    assert out.inserted
    clear_m = frontend.map.grid.params.no_return_clear_m
    assert clear_m == 5.0
    assert _cleared_along_x(frontend, pose, np.arange(0.0, clear_m, 0.05)).all()
    assert not _cleared_along_x(frontend, pose, np.arange(clear_m + 0.1, 9.0, 0.05)).any()
    plain = Frontend(settings, initial_pose=pose)
    plain.process(wall, 0.0, None, 0)
    assert not _cleared_along_x(plain, pose, np.arange(0.5, 9.0, 0.05)).any()


def test_rays_start_at_the_mounted_sensor(settings: FrontendSettings) -> None:
    """Points arrive in the robot's frame; the map traces every ray from the sensor's mount
    (1.1 m off the robot's origin, turned), and clears no-return beams from there."""
    mount = Pose2D(1.0, 0.5, 0.4)
    pose = MAP_FROM_WORLD * START
    sensor = pose * mount
    behind = np.linspace(math.pi / 2, 3 * math.pi / 2, 181)
    wall = mount.transform_points(3.0 * np.column_stack((np.cos(behind), np.sin(behind))))
    beam_in_sensor = Pose2D(0.0, 0.0, -sensor.theta).transform_points([[NO_RETURN_RANGE_M, 0.0]])
    frontend = Frontend(settings, initial_pose=pose)
    out = frontend.process(wall, 0.0, None, 0, mount.transform_points(beam_in_sensor), mount)
    assert out.inserted and out.pose == pose
    assert _cleared_along_x(frontend, sensor, np.arange(0.0, 5.0, 0.05)).all()
    assert not _cleared_along_x(frontend, sensor, np.arange(5.1, 9.0, 0.05)).any()


def test_no_return_beams_are_not_matched(settings: FrontendSettings, scan_at: Scanner) -> None:
    truth = straight_path(START, 0.25, 4)  # each step beyond the motion filter's 0.2 m
    odom = odometry_with_drift(truth)
    with_misses, without = (Frontend(settings, initial_pose=START_IN_MAP) for _ in range(2))
    run(with_misses, scan_at, truth[:3], odom[:3])
    run(without, scan_at, truth[:3], odom[:3])
    misses = 30.0 * np.column_stack((np.cos(np.arange(0, 6, 0.1)), np.sin(np.arange(0, 6, 0.1))))
    a = with_misses.process(scan_at(truth[3]), 0.3, odom[3], 3, misses)
    b = without.process(scan_at(truth[3]), 0.3, odom[3], 3)
    assert a.accepted and a.pose == b.pose and a.iterations == b.iterations
    assert a.inserted and b.inserted
    assert not np.array_equal(with_misses.map.grid.log_odds, without.map.grid.log_odds)


def test_rejected_prediction_covariance_grows(
    settings: FrontendSettings, scan_at: Scanner
) -> None:
    truth = straight_path(START, 0.1, 6)
    odom = odometry_with_drift(truth, 1.0)
    frontend = Frontend(settings, initial_pose=START_IN_MAP)
    good = run(frontend, scan_at, truth[:2], odom[:2])[-1]
    bad = [frontend.process(np.zeros((0, 2)), 0.1 * i, odom[i], i) for i in (2, 3, 4)]
    variances = [float(o.covariance[0, 0]) for o in [good, *bad]]
    assert variances == sorted(variances) and variances[-1] > variances[0]


def test_garbage_scan_is_rejected_and_map_untouched(
    settings: FrontendSettings, scan_at: Scanner
) -> None:
    truth = straight_path(START, 0.1, 5)
    odom = odometry_with_drift(truth, 1.0)
    frontend = Frontend(settings, initial_pose=START_IN_MAP)
    run(frontend, scan_at, truth[:4], odom[:4])
    revision = frontend.map.revision
    rng = np.random.default_rng(3)
    noise = rng.uniform(-8.0, 8.0, size=(300, 2))
    out = frontend.process(noise, 0.4, odom[4], 4)
    assert out.status is FrontendStatus.REJECTED, out.message
    assert not out.inserted and out.message
    assert frontend.map.revision == revision
    assert error(out.pose, truth[4])[0] < 0.02


@pytest.mark.parametrize("stamp_s", [math.nan, math.inf, -math.inf])
def test_a_non_finite_stamp_is_refused_before_it_touches_the_state(
    settings: FrontendSettings, scan_at: Scanner, stamp_s: float
) -> None:
    """A scan at a NaN or infinite stamp cannot be tracked (nor put on the trajectory): it is
    refused by name before the match, so the next scans go on exactly as if it never came."""
    truth = straight_path(START, 0.1, 8)
    odom = odometry_with_drift(truth, 1.0)
    clean, refused = (Frontend(settings, initial_pose=START_IN_MAP) for _ in range(2))
    for frontend in (clean, refused):
        run(frontend, scan_at, truth[:6], odom[:6])
    revision = refused.map.revision
    with pytest.raises(ValueError, match="stamp_s"):
        refused.process(scan_at(truth[6]), stamp_s, odom[6], 6)
    assert len(refused.trajectory) == 6 and refused.map.revision == revision
    # A rejected scan next: its covariance grows from the last accepted match's, not from the
    # refused scan's.
    outs = [frontend.process(np.zeros((0, 2)), 0.7, odom[7], 7) for frontend in (clean, refused)]
    assert all(o.status is FrontendStatus.TOO_FEW_POINTS for o in outs)
    np.testing.assert_array_equal(outs[1].covariance, outs[0].covariance)
    assert outs[1].pose == outs[0].pose


def test_odometry_jump_is_ignored(
    settings: FrontendSettings, scan_at: Scanner
) -> None:
    truth = straight_path(START, 0.1, 12)
    odom = odometry_with_drift(truth, 1.0)
    jump = Pose2D(40.0, -25.0, 2.0)
    odom = odom[:6] + [jump * p for p in odom[6:]]
    frontend = Frontend(settings, initial_pose=START_IN_MAP)
    outs = run(frontend, scan_at, truth, odom)
    assert "odometry jumped" in outs[6].message
    assert outs[6].prediction_source != PredictionSource.ODOMETRY
    assert all(o.accepted for o in outs)
    assert outs[7].prediction_source == PredictionSource.ODOMETRY  # re-anchored after the jump
    assert error(outs[-1].pose, truth[-1])[0] < 0.03


def test_an_odometry_pose_far_beyond_any_map_is_unused_not_an_exception(
    settings: FrontendSettings, scan_at: Scanner
) -> None:
    """Poses at 1.5e308 m overflowed the odometry increment to inf, and process raised
    ValueError (a fuzzing audit); the front end never raises for bad content."""
    truth = straight_path(START, 0.1, 4)
    huge = [Pose2D(1.5e308, -1.5e308, 0.1 * i) for i in range(4)]
    outs = run(Frontend(settings, initial_pose=START_IN_MAP), scan_at, truth, huge)
    assert all(o.accepted for o in outs)
    assert all("beyond +-1e+09 m: unused" in o.message for o in outs)
    assert outs[-1].prediction_source != PredictionSource.ODOMETRY
    assert error(outs[-1].pose, truth[-1])[0] < 0.03


def test_fallback_recovers_from_a_bad_prediction(scan_at: Scanner, stays_put: str) -> None:
    truth = straight_path(START, 0.1, 6)[-1]
    # One odometry step 0.6 m / 12 deg off, within the jump limits: a wrong prior.
    off = Pose2D(0.4, -0.45, math.radians(12.0))
    # gn's pyramid reaches that far by itself.
    out = track_with_a_bad_prediction(FrontendSettings.model_construct(), scan_at, 5, off)
    assert out.accepted, out.message
    assert error(out.pose, truth)[0] < 0.03
    # A matcher that stays at its guess does not: its match fails min_score, and the fallback
    # search finds the pose.
    with_fallback = FrontendSettings.model_construct(method=stays_put)
    out = track_with_a_bad_prediction(with_fallback, scan_at, 5, off)
    assert out.status is FrontendStatus.RECOVERED, out.message
    assert out.message.startswith("recovered by csm: score")
    assert error(out.pose, truth)[0] < 0.05
    no_fallback = with_fallback.model_copy(update={"fallback_method": ""})
    without = track_with_a_bad_prediction(no_fallback, scan_at, 5, off)
    assert without.status is FrontendStatus.REJECTED
    assert "below min_score" in without.message


def test_relocalise_finds_the_pose_from_a_far_guess_and_leaves_the_state_alone(
    scan_at: Scanner,
) -> None:
    truth = straight_path(START, 0.1, 6)
    frontend = Frontend(FrontendSettings.model_construct(), initial_pose=START_IN_MAP)
    run(frontend, scan_at, truth, odometry_with_drift(truth, 1.0))
    pose, trajectory = frontend.pose, len(frontend.trajectory)
    far = MAP_FROM_WORLD * truth[-1] * Pose2D(0.6, -0.5, math.radians(20.0))
    found, status, note = frontend.relocalise(scan_at(truth[-1]), far)
    assert status is FrontendStatus.RECOVERED, note
    assert note.startswith("recovered by csm")
    position_m, heading_rad = error(found.pose, truth[-1])
    assert position_m < 0.03 and heading_rad < math.radians(1.0)
    assert frontend.pose == pose and len(frontend.trajectory) == trajectory


def test_a_search_in_a_corridor_keeps_the_guess_s_position_along_it() -> None:
    """Along a corridor the search's best peak lies anywhere in its +-1 m window (0.2-1.0 m
    from the guess here), and its refinement, degenerate too, kept that: the robot jumped. A
    degenerate search now starts from the guess's position along the corridor's axis, its
    position across and its heading kept (`corridor_start`)."""
    rng = np.random.default_rng(0)
    angles = np.radians(np.arange(-135.0, 135.0, 0.75))

    def scan(pose: Pose2D) -> NDArray[np.float64]:
        return static_scan(get_world("corridor").segments, pose, angles, 12.0, 0.01, rng)

    settings = FrontendSettings.model_construct()
    world = MatchingMap(OccupancyGrid(occupancy_params(settings)))
    for x in np.arange(15.0, 25.0, 0.25):
        insert_scan(world, scan(Pose2D(x, 1.0, 0.0)), Pose2D(x, 1.0, 0.0))
    frontend = Frontend(settings, initial_pose=Pose2D(20.0, 1.0, 0.0), grid=world.grid)
    for k in range(8):
        truth = Pose2D(18.0 + 0.5 * k, 1.0 + rng.uniform(-0.3, 0.3), rng.uniform(-0.1, 0.1))
        guess = truth * Pose2D(0.3, 0.05, 0.02)
        found, status, note = frontend.relocalise(scan(truth), guess)
        assert status is FrontendStatus.RECOVERED, note
        assert found.status is MatchStatus.DEGENERATE
        assert abs(found.pose.x - guess.x) < 1e-3
        assert abs(found.pose.y - truth.y) < 0.05
        assert abs(found.pose.theta - truth.theta) < math.radians(1.0)


def test_relocalise_on_an_empty_map_says_why_and_needs_a_fallback(scan_at: Scanner) -> None:
    frontend = Frontend(FrontendSettings.model_construct(), initial_pose=START_IN_MAP)
    found, status, note = frontend.relocalise(scan_at(START), START_IN_MAP)
    assert status is FrontendStatus.REJECTED and not found.ok
    assert note.startswith("fallback: ") and len(note) > len("fallback: ")
    plain = Frontend(FrontendSettings.model_construct(fallback_method=""))
    with pytest.raises(ValueError, match="fallback_method"):
        plain.relocalise(scan_at(START), START_IN_MAP)


@pytest.mark.parametrize("method", ["gn", "lm"])
def test_method_is_configurable(method: str, scan_at: Scanner) -> None:
    truth = straight_path(START, 0.1, 4)
    frontend = Frontend(FrontendSettings.model_construct(method=method), initial_pose=START_IN_MAP)
    outs = run(frontend, scan_at, truth, odometry_with_drift(truth))
    assert outs[-1].method == method and outs[-1].accepted


def test_memory_does_not_grow_when_revisiting(
    settings: FrontendSettings, scan_at: Scanner
) -> None:
    forth = straight_path(START, 0.2, 15)
    back = list(reversed(forth))
    frontend = Frontend(settings, initial_pose=START_IN_MAP)
    run(frontend, scan_at, forth + back, odometry_with_drift(forth + back, 1.0))
    mapped_bytes = frontend.map.nbytes
    run(frontend, scan_at, forth + back, None, t0=30)
    assert frontend.map.nbytes == mapped_bytes
    assert len(frontend.trajectory) == 60


def test_no_return_clear_distance_comes_from_the_settings():
    settings = FrontendSettings(no_return_clear_m=1.5, map_resolution_m=0.1)
    assert Frontend(settings).map.grid.params.no_return_clear_m == 1.5
    assert occupancy_params(settings).resolution_m == 0.1


def test_a_redrawn_map_in_another_frame_is_tracked_on(scan_at: Scanner) -> None:
    """`redraw` hands the front end the same world drawn in another frame (as the back end does
    after optimising): the next scan is predicted and matched there, odometry carrying on."""
    settings = FrontendSettings.model_construct()
    poses = [START * Pose2D(0.1 * i, 0.0, 0.03 * i) for i in range(7)]
    frontend = Frontend(settings, initial_pose=START_IN_MAP)
    run(frontend, scan_at, poses[:5], poses[:5])
    correction = Pose2D(3.0, -1.0, 0.4)  # T_new_old
    new_from_world = correction * MAP_FROM_WORLD
    redrawn = MatchingMap(OccupancyGrid(occupancy_params(settings)))
    for pose in poses[:5]:
        insert_scan(redrawn, scan_at(pose), new_from_world * pose)
    frontend.redraw(redrawn, correction)
    assert frontend.map is redrawn
    moved = frontend.pose.relative_to(new_from_world * poses[4])
    assert moved.translation_norm() < 0.03
    out = frontend.process(scan_at(poses[5]), 0.5, odom_pose=poses[5])
    assert out.status is FrontendStatus.TRACKED
    assert out.prediction_source == PredictionSource.ODOMETRY
    assert out.pose.relative_to(new_from_world * poses[5]).translation_norm() < 0.03


def test_an_estimate_moved_into_a_redrawn_frame_turns_its_covariance() -> None:
    """T_new_old turned by 90 deg: the pose moves, the position uncertainty turns with it (x's
    variance becomes y's), and "no information" stays infinite rather than NaN."""
    out = FrontendOutput(
        seq=3, stamp_s=0.3, pose=Pose2D(1.0, 0.0, 0.0), covariance=np.diag([4.0, 1.0, 0.1]),
        status=FrontendStatus.TRACKED, method="gn", iterations=2, score=0.9, message="",
        inserted=True, prediction_source="odometry",
    )
    correction = Pose2D(0.5, 0.0, math.pi / 2)
    moved = out.in_frame(correction)
    assert moved.pose == correction * out.pose and moved.seq == 3
    np.testing.assert_allclose(moved.covariance, np.diag([1.0, 4.0, 0.1]), atol=1e-12)
    lost = replace(out, covariance=np.diag([math.inf] * 3)).in_frame(correction)
    assert np.isinf(np.diag(lost.covariance)).all() and not np.isnan(lost.covariance).any()


def test_a_redraw_turns_the_uncertainty_the_next_rejected_scans_grow_from(
    scan_at: Scanner,
) -> None:
    """A rejected scan's covariance is the last match's grown by the motion: after a redraw
    that turned the frame it is the last match's turned with it, as `in_frame` turns an
    estimate. Before, the last match's stayed in the old frame's axes (a corridor's long axis
    pointing the old way)."""
    settings = FrontendSettings.model_construct()
    poses = straight_path(START, 0.1, 5)
    clean, redrawn = (Frontend(settings, initial_pose=START_IN_MAP) for _ in range(2))
    for frontend in (clean, redrawn):
        run(frontend, scan_at, poses[:4], poses[:4])
    correction = Pose2D(3.0, -1.0, math.pi / 2)  # T_new_old
    redrawn.redraw(redrawn.map, correction)
    outs = [f.process(np.zeros((0, 2)), 0.4, poses[4], 4) for f in (clean, redrawn)]
    assert all(o.status is FrontendStatus.TOO_FEW_POINTS for o in outs)
    expected = outs[0].in_frame(correction)
    assert outs[1].pose.relative_to(expected.pose).translation_norm() < 1e-9
    np.testing.assert_allclose(outs[1].covariance, expected.covariance, rtol=1e-9, atol=1e-15)


@pytest.fixture
def stays_put(monkeypatch: pytest.MonkeyPatch) -> str:
    """A local matcher with no basin at all, registered for one test: it scores its guess on
    the map's field and stays there, as `gn` does when it lands in a wrong basin."""

    def match_stays_put(
        source: NDArray[np.float64], target: object, guess: Pose2D, **_: object
    ) -> MatchResult:
        field = field_pyramid(target, 1, 0.05, 0.1)[-1]
        return assess_field_match("stays-put", field, source, guess.to_array(), 0, guess)

    monkeypatch.setitem(matching_api._METHODS, "stays-put", match_stays_put)
    return "stays-put"


# 0.32 m / 8 deg: a prediction the correction limits (1 m, 30 deg) still allow.
BAD_PREDICTION = Pose2D(0.25, -0.2, math.radians(8.0))


def track_with_a_bad_prediction(
    settings: FrontendSettings, scan_at: Scanner, at: int = 7, off: Pose2D = BAD_PREDICTION
) -> FrontendOutput:
    """Scans along a straight path with exact odometry, except at scan `at`, the last: the
    odometry is `off` there."""
    truth = straight_path(START, 0.1, at + 1)
    odom = odometry_with_drift(truth, 1.0)
    odom[at] = odom[at] * off
    return run(Frontend(settings, initial_pose=START_IN_MAP), scan_at, truth, odom)[-1]


def test_a_passing_match_far_below_the_recent_scores_is_searched_again(
    scan_at: Scanner, stays_put: str
) -> None:
    truth = straight_path(START, 0.1, 8)[-1]
    without = track_with_a_bad_prediction(
        FrontendSettings.model_construct(method=stays_put, recheck_ratio=0.0), scan_at
    )
    # The failure the recheck is for: a wrong pose that passes every check of `acceptance`.
    assert without.status is FrontendStatus.TRACKED, without.message
    assert error(without.pose, truth)[0] > 0.2 and not without.rechecked
    out = track_with_a_bad_prediction(
        FrontendSettings.model_construct(method=stays_put), scan_at
    )
    assert out.status is FrontendStatus.RECOVERED and out.rechecked, out.message
    assert out.message.startswith("rechecked, recovered by csm")
    assert "below 0.8 x the recent median" in out.message
    assert out.score >= without.score + 0.1
    position_m, heading_rad = error(out.pose, truth)
    assert position_m < 0.05 and heading_rad < math.radians(1.0)


def test_a_searched_pose_that_scores_no_better_by_the_margin_leaves_the_match(
    scan_at: Scanner, stays_put: str
) -> None:
    settings = FrontendSettings.model_construct(method=stays_put, recheck_margin=1.0)
    out = track_with_a_bad_prediction(settings, scan_at)
    assert out.status is FrontendStatus.TRACKED and out.rechecked
    assert "rechecked and kept: score" in out.message
    assert "the search: recovered by csm (0.9" in out.message
    assert error(out.pose, straight_path(START, 0.1, 8)[-1])[0] > 0.2


def test_no_recheck_before_the_recent_scores_are_known_or_without_a_fallback(
    scan_at: Scanner, stays_put: str
) -> None:
    # Scan 3 has 2 matches before it, fewer than recheck.MIN_SCORES.
    early = track_with_a_bad_prediction(
        FrontendSettings.model_construct(method=stays_put), scan_at, at=3
    )
    assert early.status is FrontendStatus.TRACKED and not early.rechecked
    no_fallback = FrontendSettings.model_construct(method=stays_put, fallback_method="")
    out = track_with_a_bad_prediction(no_fallback, scan_at)
    assert out.status is FrontendStatus.TRACKED and not out.rechecked


def test_insert_scan_keeps_points_within_max_range_seen_from_the_pose() -> None:
    pose = Pose2D(1.0, -2.0, math.pi / 2)
    near, far = np.array([[3.0, 0.0]]), np.array([[30.0, 0.0]])
    with_far = MatchingMap(OccupancyGrid(OccupancyParams(max_range_m=10.0)))
    result = insert_scan(with_far, np.vstack([near, far]), pose)
    alone = MatchingMap(OccupancyGrid(OccupancyParams(max_range_m=10.0)))
    insert_scan(alone, near, pose)
    np.testing.assert_array_equal(with_far.grid.log_odds, alone.grid.log_odds)  # far: no ray
    sensor, hit = with_far.grid.world_to_cells(np.array([[1.0, -2.0], [1.0, 1.0]]))
    assert result.touched == CellBox.around(np.array([sensor, hit]))  # the ray, in the map frame


# The front end on a prior map: the start found over the whole map, localise-only, a kidnapped
# robot, an operator's pose.
PRIOR_MAP_FROM_WORLD = Pose2D(0.41, -0.17, 0.35)  # walls off the cell lattice
# A pillar-flanked stretch of the middle rooms: unambiguous, unlike most of the alike rooms.
PRIOR_START = Pose2D(7.0, 2.6, 0.4)
KIDNAPPED_TO = Pose2D(11.6, 5.3, -2.0)
PriorGrid = Callable[[Scanner, Pose2D], OccupancyGrid]


def path_from(start: Pose2D, count: int) -> list[Pose2D]:
    return [start * Pose2D(0.05 * i, 0.0, math.radians(1.0) * i) for i in range(count)]


def near(estimate: Pose2D, world_pose: Pose2D, metres: float = 0.05) -> bool:
    error = estimate.relative_to(PRIOR_MAP_FROM_WORLD * world_pose)
    return error.translation_norm() < metres and abs(error.theta) < math.radians(1.0)


def test_without_a_start_the_first_scan_is_found_on_the_prior_map(
    settings: FrontendSettings, scan_at: Scanner, prior_grid: PriorGrid
) -> None:
    frontend = Frontend(settings, grid=prior_grid(scan_at, PRIOR_MAP_FROM_WORLD))
    truth = path_from(PRIOR_START, 6)
    outs = [frontend.process(scan_at(p), 0.1 * i, None, i) for i, p in enumerate(truth)]
    assert outs[0].status is FrontendStatus.LOCALISED, outs[0].message
    assert "whole-map search" in outs[0].message and outs[0].method == "global+gn"
    assert all(o.status is FrontendStatus.TRACKED for o in outs[1:])
    assert all(near(o.pose, p) for o, p in zip(outs, truth, strict=True))


def test_a_given_start_skips_the_search(
    settings: FrontendSettings, scan_at: Scanner, prior_grid: PriorGrid
) -> None:
    frontend = Frontend(
        settings,
        initial_pose=PRIOR_MAP_FROM_WORLD * PRIOR_START,
        grid=prior_grid(scan_at, PRIOR_MAP_FROM_WORLD),
    )
    out = frontend.process(scan_at(PRIOR_START), 0.0)
    assert out.status is FrontendStatus.TRACKED and near(out.pose, PRIOR_START)


def test_localise_only_leaves_the_prior_map_as_it_was(
    settings: FrontendSettings, scan_at: Scanner, prior_grid: PriorGrid
) -> None:
    grid = prior_grid(scan_at, PRIOR_MAP_FROM_WORLD)
    revision = grid.revision
    frontend = Frontend(settings.model_copy(update={"update_map": False}), grid=grid)
    path = path_from(PRIOR_START, 8)
    outs = [frontend.process(scan_at(p), 1.0 * i, None, i) for i, p in enumerate(path)]
    assert all(o.accepted and not o.inserted for o in outs)
    assert frontend.map.revision == revision
    mapping = Frontend(settings, grid=prior_grid(scan_at, PRIOR_MAP_FROM_WORLD))
    assert any(mapping.process(scan_at(p), 1.0 * i).inserted for i, p in enumerate(path[:3]))
    with pytest.raises(ValueError, match="update_map"):
        Frontend(settings.model_copy(update={"update_map": False}))


def test_a_kidnapped_robot_is_found_again_after_n_rejections(
    settings: FrontendSettings, scan_at: Scanner, prior_grid: PriorGrid
) -> None:
    grid = prior_grid(scan_at, PRIOR_MAP_FROM_WORLD)
    # No local fallback search: it could latch on to a look-alike pose near the old one.
    kidnap = settings.model_copy(update={"global_after_rejections": 2, "fallback_method": ""})
    frontend = Frontend(kidnap, initial_pose=PRIOR_MAP_FROM_WORLD * PRIOR_START, grid=grid)
    for i, p in enumerate(path_from(PRIOR_START, 3)):
        assert frontend.process(scan_at(p), 0.1 * i, None, i).status is FrontendStatus.TRACKED
    # Carried off to another room with no odometry to tell: the local search fails twice.
    away = path_from(KIDNAPPED_TO, 4)
    outs = [frontend.process(scan_at(p), 1.0 + 0.1 * i, None, 3 + i) for i, p in enumerate(away)]
    assert [o.status for o in outs[:2]] == [FrontendStatus.REJECTED] * 2
    assert outs[2].status is FrontendStatus.LOCALISED and near(outs[2].pose, away[2])
    assert outs[3].status is FrontendStatus.TRACKED and near(outs[3].pose, away[3])
    # Lost for good (a map of elsewhere): a search every second rejection, not on every scan.
    lost = Frontend(
        kidnap,
        initial_pose=PRIOR_MAP_FROM_WORLD * PRIOR_START,
        grid=prior_grid(scan_at, PRIOR_MAP_FROM_WORLD),
    )
    far_away = [np.column_stack((np.full(40, 30.0), np.linspace(-5.0, 5.0, 40)))] * 6
    outs = [lost.process(points, 0.1 * i, None, i) for i, points in enumerate(far_away)]
    searched = ["whole-map search" in o.message for o in outs]
    assert searched == [False, False, True, False, True, False]
    assert all(o.status is FrontendStatus.REJECTED for o in outs)
    # Without the setting it stays lost.
    never = kidnap.model_copy(update={"global_after_rejections": 0})
    stays = Frontend(
        never,
        initial_pose=PRIOR_MAP_FROM_WORLD * PRIOR_START,
        grid=prior_grid(scan_at, PRIOR_MAP_FROM_WORLD),
    )
    stays.process(scan_at(PRIOR_START), 0.0)
    lost = [stays.process(scan_at(p), 1.0 + 0.1 * i, None, 1 + i) for i, p in enumerate(away)]
    assert all(o.status is FrontendStatus.REJECTED for o in lost)


def test_an_operators_pose_replaces_the_search_and_puts_a_lost_robot_back(
    settings: FrontendSettings, scan_at: Scanner, prior_grid: PriorGrid
) -> None:
    frontend = Frontend(settings, grid=prior_grid(scan_at, PRIOR_MAP_FROM_WORLD))
    frontend.set_pose(PRIOR_MAP_FROM_WORLD * PRIOR_START)  # before the first scan: the start
    first = frontend.process(scan_at(PRIOR_START), 0.0)
    assert first.status is FrontendStatus.TRACKED and near(first.pose, PRIOR_START)
    # Carried off, no search, no fallback: lost, until told where it is.
    stay_lost = settings.model_copy(update={"global_after_rejections": 0, "fallback_method": ""})
    lost = Frontend(
        stay_lost,
        initial_pose=PRIOR_MAP_FROM_WORLD * PRIOR_START,
        grid=prior_grid(scan_at, PRIOR_MAP_FROM_WORLD),
    )
    lost.process(scan_at(PRIOR_START), 0.0)
    away = path_from(KIDNAPPED_TO, 3)
    assert lost.process(scan_at(away[0]), 1.0).status is FrontendStatus.REJECTED
    lost.set_pose(PRIOR_MAP_FROM_WORLD * away[0] * Pose2D(0.15, -0.1, 0.05))  # roughly there
    back = lost.process(scan_at(away[1]), 1.1)
    assert back.status is FrontendStatus.TRACKED and near(back.pose, away[1])
    assert back.prediction_source == "hold"  # the decreed pose, not a velocity from the jump
    with pytest.raises(ValueError, match="finite"):
        lost.set_pose(Pose2D(math.inf, 0.0, 0.0))


def test_an_operators_pose_for_a_past_scan_is_carried_to_the_next_by_the_odometry(
    settings: FrontendSettings, scan_at: Scanner, prior_grid: PriorGrid
) -> None:
    """Told where the robot was at a scan since lost (a restarted matcher dropped it while it
    waited for the map server), with the odometry pose there: the next scan is predicted from
    the told pose moved by the odometry since, not at the told pose itself (a chaos test saw
    a robot tracked metres off, its map grown with it, from a pose applied seconds late)."""
    stay = settings.model_copy(update={"global_after_rejections": 0, "fallback_method": ""})
    frontend = Frontend(stay, grid=prior_grid(scan_at, PRIOR_MAP_FROM_WORLD))
    odom_from_world = Pose2D(-3.0, 4.0, 1.2)  # the odometry's own frame
    away = path_from(KIDNAPPED_TO, 40)[::8]  # 0.4 m and 8 deg apart
    frontend.set_pose(PRIOR_MAP_FROM_WORLD * away[0], 5.0, odom_from_world * away[0])
    out = frontend.process(scan_at(away[2]), 6.0, odom_from_world * away[2], 7)
    assert out.prediction_source == "odometry"
    assert out.status is FrontendStatus.TRACKED and near(out.pose, away[2])
    later = frontend.process(scan_at(away[3]), 6.1, odom_from_world * away[3], 8)
    assert later.status is FrontendStatus.TRACKED and near(later.pose, away[3])


def test_a_run_carried_on_across_a_gap_is_checked_by_the_widest_search(
    settings: FrontendSettings, scan_at: Scanner, prior_grid: PriorGrid
) -> None:
    """A matcher resumed after seconds out predicts the next scan by the odometry across the
    gap, which may have drifted metres: a chaos test saw the +-1 m fallback latch on to a
    look-alike 4 m off, tracked for good. The first scan after it is searched over the widest
    window (fallback_max_*), and its correction may reach as far. (An operator's pose carried
    over lost scans is the operator's word: not searched so.)"""
    truth = path_from(KIDNAPPED_TO, 3)
    odom_from_world = Pose2D(-3.0, 4.0, 1.2)
    drift = Pose2D(1.8, -1.5, math.radians(25.0))  # the odometry's error across the gap
    start = PRIOR_MAP_FROM_WORLD * truth[0] * drift.inverse()  # what the odometry carries on
    for widest in (settings, settings.model_copy(update={"fallback_max_linear_m": 1.0,
                                                         "fallback_max_angular_deg": 30.0})):
        frontend = Frontend(widest, grid=prior_grid(scan_at, PRIOR_MAP_FROM_WORLD))
        frontend.carry_on(0.0, start, odom_from_world * truth[0])
        outs = [frontend.process(scan_at(p), 20.0 + 0.1 * i, odom_from_world * p, i)
                for i, p in enumerate(truth[1:])]
        if widest is settings:
            assert outs[0].status is FrontendStatus.RECOVERED, outs[0].message
            assert "+-5.00 m, +-180 deg" in outs[0].message and near(outs[0].pose, truth[1])
            assert outs[1].status is FrontendStatus.TRACKED and near(outs[1].pose, truth[2])
        else:  # the search as wide as before: the robot is not found
            assert not near(outs[0].pose, truth[1], metres=0.5)


def test_a_widened_search_past_the_caps_falls_back_to_the_settings_window(
    scan_at: Scanner, monkeypatch: pytest.MonkeyPatch
) -> None:
    """+-180 deg over many far-reaching points exceeds csm's angles x points cap (a review:
    the scan was rejected, and every later one, the gap's check never passing)."""
    from scanflow.frontend import tracker
    from scanflow.matching import MatchInputError

    truth = straight_path(START, 0.1, 6)
    frontend = Frontend(FrontendSettings.model_construct(), initial_pose=START_IN_MAP)
    run(frontend, scan_at, truth, odometry_with_drift(truth, 1.0))
    real, windows = tracker.match, []

    def capped(points, target, guess, method, **options):
        if method == "csm":
            windows.append(options["linear_m"])
            if options["linear_m"] > 1.0:
                raise MatchInputError("search too large: angles x source points")
        return real(points, target, guess, method=method, **options)

    monkeypatch.setattr(tracker, "match", capped)
    far = MAP_FROM_WORLD * truth[-1] * Pose2D(0.3, -0.2, math.radians(10.0))
    found, status, note = frontend.relocalise(scan_at(truth[-1]), far, np.diag([9.0] * 3))
    assert windows == [5.0, 1.0] and status is FrontendStatus.RECOVERED, note
    assert error(found.pose, truth[-1])[0] < 0.03


def _over_the_caps_below(level_that_fits: int, monkeypatch: pytest.MonkeyPatch) -> list[int]:
    """The whole-map search refuses levels finer than `level_that_fits`, as it does a map
    too large for them (its caps); returns the levels tried."""
    from scanflow.frontend import tracker
    from scanflow.matching import MatchInputError

    tried: list[int] = []
    real = tracker.localise_globally

    def search(points, target, *, level: int, **options):
        tried.append(level)
        if level < level_that_fits:
            raise MatchInputError(f"a search of 2e9 candidates at level {level} is over the cap")
        return real(points, target, level=level, **options)

    monkeypatch.setattr(tracker, "localise_globally", search)
    return tried


@pytest.mark.parametrize(("fits_at", "tried"), [(2, [1, 2]), (99, [1, 2, 3, 4])])
def test_a_map_too_large_for_the_search_level_is_searched_coarser_or_the_scan_rejected(
    settings: FrontendSettings, scan_at: Scanner, prior_grid: PriorGrid,
    monkeypatch: pytest.MonkeyPatch,
    fits_at: int, tried: list[int],
) -> None:
    levels = _over_the_caps_below(fits_at, monkeypatch)
    out = Frontend(settings, grid=prior_grid(scan_at, PRIOR_MAP_FROM_WORLD)).process(
        scan_at(PRIOR_START), 0.0
    )
    assert levels == tried
    if fits_at <= 4:
        assert out.status is FrontendStatus.LOCALISED and near(out.pose, PRIOR_START)
    else:
        assert out.status is FrontendStatus.REJECTED
        assert "too large even at level 4" in out.message and "over the cap" in out.message



def test_a_match_that_refuses_its_input_rejects_the_scan_and_keeps_the_map(
    settings: FrontendSettings,
) -> None:
    """A sensor 20 km from the robot's origin (the front end takes any mount; a LaserScan
    would refuse it) asks the fallback search for 4e5 angles, over its cap: the scan is
    rejected saying so, nothing raises, the map keeps what it had."""
    angles = np.linspace(-math.pi, math.pi, 360, endpoint=False)
    points = np.column_stack((2e4 + 5.0 * np.cos(angles), 5.0 * np.sin(angles)))
    points[::7, 1] *= 2.0
    mount = Pose2D(2e4, 0.0, 0.0)
    frontend = Frontend(settings)
    assert frontend.process(points, 0.0, mount=mount).status is FrontendStatus.INITIALISED
    revision = frontend.map.revision
    out = frontend.process(points, 0.1, seq=1, mount=mount)
    assert out.status is FrontendStatus.REJECTED and not out.inserted
    assert out.message.startswith("no motion prior: held; the match refused its input: ")
    assert "search too large" in out.message
    assert frontend.map.revision == revision
