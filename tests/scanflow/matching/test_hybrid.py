"""csm+plicp: the correlative search brings large initial errors into plicp's basin."""

import math

import numpy as np
from scanflow.geometry import Pose2D
from scanflow.matching import MatchStatus, match
from scanflow.sim import (
    ConstantVelocityTrajectory,
    LidarModel,
    SimConfig,
    get_world,
    measure,
    simulate,
)


def _scan(pose: Pose2D, seed: int) -> np.ndarray:
    lidar = LidarModel(beams=360, fov_deg=360.0, range_noise_m=0.01)
    still = ConstantVelocityTrajectory(pose, 0.0, 0.0)
    return measure(lidar, still, get_world("rooms").segments, 0.0,
                   np.random.default_rng(seed)).scan.points()


def test_recovers_from_a_large_initial_error() -> None:
    base, moved = Pose2D(7.0, 2.5, 0.1), Pose2D(7.3, 2.3, 0.2)
    truth = moved.relative_to(base)
    guess = truth * Pose2D(0.35, -0.3, math.radians(15.0))
    r = match(_scan(moved, 2), _scan(base, 1), guess, method="csm+plicp")
    err = r.pose.relative_to(truth)
    assert r.ok and r.method == "csm+plicp"
    assert err.translation_norm() < 0.02 and abs(err.theta) < math.radians(0.3)
    assert isinstance(r.extra["csm_pose"], Pose2D)


def test_empty_target_is_reported() -> None:
    r = match(_scan(Pose2D(7.0, 2.5, 0.0), 1), np.zeros((0, 2)), method="csm+plicp")
    assert not r.ok and r.method == "csm+plicp"


def _segment(x0: float, y0: float, x1: float, y1: float, step_m: float) -> np.ndarray:
    n = max(round(math.hypot(x1 - x0, y1 - y0) / step_m), 1) + 1
    f = np.linspace(0.0, 1.0, n)[:, None]
    return np.array([x0, y0]) + f * np.array([x1 - x0, y1 - y0])


def _toothed_corridor(step_m: float) -> np.ndarray:
    """Two long walls, a tooth every PERIOD_M on each, one small landmark."""
    teeth = [_segment(k * PERIOD_M, 0.4, k * PERIOD_M, 1.0, step_m) for k in range(-16, 17)]
    teeth += [_segment(x, -1.0, x, -0.4, step_m) for x in np.arange(-16, 17) * PERIOD_M + 0.2]
    walls = [_segment(-10, 1.0, 10, 1.0, step_m), _segment(-10, -1.0, 10, -1.0, step_m)]
    landmark = _segment(PERIOD_M / 2, -1.0, PERIOD_M / 2, -0.8, step_m)
    return np.vstack([*walls, *teeth, landmark])


PERIOD_M = 0.625  # 12.5 csm cells: a wrong peak one period away sits on the lattice, truth not


def test_picks_the_right_basin_when_the_best_csm_peak_is_wrong() -> None:
    """Periodic teeth: one period off matches every tooth exactly on the csm lattice and loses
    only the small landmark, while the truth lies half a cell off the lattice. csm ranks the
    wrong peak first; the refined hypotheses are told apart by their overlap (the landmark is
    under the default switch margin, hence switch_margin=0 here)."""
    world = _toothed_corridor(0.02)
    truth = Pose2D(0.3, 0.0, 0.0)
    target = world[np.abs(world[:, 0]) <= 5.0]
    src_world = world[np.abs(world[:, 0] - truth.x) <= 4.0]
    source = truth.inverse().transform_points(src_world)
    guess = truth * Pose2D(5.5 * 0.05, 0.0, 0.0)  # the wrong peak is 7 cells from the guess
    window = {"linear_m": 0.5, "angular_rad": math.radians(5.0)}
    top = match(source, target, guess, method="csm", **window)
    assert abs(top.pose.relative_to(truth).x - PERIOD_M) < 0.03  # csm's best: one period off
    single = match(source, target, guess, method="csm+plicp", hypotheses=1, **window)
    assert single.pose.relative_to(truth).translation_norm() > 0.5
    multi = match(source, target, guess, method="csm+plicp", switch_margin=0.0, **window)
    err = multi.pose.relative_to(truth)
    assert multi.ok and multi.extra["hypothesis"] > 0
    assert err.translation_norm() < 0.01 and abs(err.theta) < math.radians(0.1)
    assert multi.extra["overlaps"][multi.extra["hypothesis"]] > multi.extra["overlaps"][0]
    cautious = match(source, target, guess, method="csm+plicp", **window)
    assert cautious.extra["hypothesis"] == 0  # within the default margin: csm's order stands


def test_along_a_corridor_the_guess_stands_where_the_search_cannot_tell(corridor_pairs) -> None:
    """Along the corridor, csm's best peak slides to its window's edge (0.5 m: the scans'
    extents tilt a flat score) and plicp stays there. A degenerate result keeps the guess's
    value along its weak direction, and csm+plicp's refinement across it."""
    degenerate = 0
    for source, target, truth in corridor_pairs:
        guess = truth * Pose2D(0.0, 0.03, 0.01)  # off across the corridor and in heading only
        r = match(source, target, guess, method="csm+plicp")
        err = r.pose.relative_to(truth)
        assert err.translation_norm() < 0.02 and abs(err.theta) < 0.005, (r.status, err)
        degenerate += r.status is MatchStatus.DEGENERATE
    assert degenerate >= len(corridor_pairs) // 2  # the case at hand: mostly unobservable



def test_a_degenerate_best_stands_against_a_worse_basin_that_looks_well_conditioned() -> None:
    """The campus lawn seen by the simulator's 30 m lidar, along a row of trees: csm's best
    peak refines to the right pose, rightly `degenerate` along the row; another peak 0.3 m
    along it refines to a pose 0.26 m off whose few matched points look well conditioned. It
    used to win (`ok`, 0.26 m off) for being `ok`; it overlaps the target less, so it loses."""
    sweeps = list(simulate(SimConfig(world="campus", duration_s=33.1)))
    before, after = sweeps[325], sweeps[330]
    truth = after.true_pose.relative_to(before.true_pose)
    r = match(after.true_points, before.true_points, truth * Pose2D(0.005, 0.0, 0.005),
              method="csm+plicp")
    err = r.pose.relative_to(truth)
    assert err.translation_norm() < 0.02 and abs(err.theta) < 0.01, (r.status, err)
    assert r.extra["hypothesis"] == 0
