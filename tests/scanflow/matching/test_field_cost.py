"""The likelihood-field cost shared by gn and lm: its value, Gauss-Newton terms, fields and
pyramids, the well-determined step, and the coarse-to-fine driver with its final checks."""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from numpy.typing import NDArray
from scanflow.geometry import Pose2D
from scanflow.maps.field import LikelihoodField
from scanflow.maps.grid import GridSpec
from scanflow.matching import MatchInputError, MatchStatus, match
from scanflow.matching.checks import DEGENERATE_RATIO
from scanflow.matching.covariance import least_squares_covariance
from scanflow.matching.field_cost import (
    COARSE_TOLERANCE_FACTOR,
    CUTOFF_SIGMAS,
    DIVERGENCE_RATIO,
    MIN_POINTS,
    LevelOutcome,
    assess_field_match,
    check_inputs,
    converged_step,
    dense_points_field,
    field_cost,
    field_hits,
    field_pyramid,
    finest_normals,
    is_empty_target,
    level_tolerances,
    linearise,
    moved_points,
    out_of_iterations,
    points_field,
    run_coarse_to_fine,
    solve_well_determined,
)

Caster = Callable[..., NDArray[np.float64]]
ROOM_POSE = Pose2D(0.3, 0.2, 0.4)


class _FieldMap:
    """A map target: its own field pyramid, given fine level first."""

    def __init__(self, fields: list[LikelihoodField]) -> None:
        self.fields = fields

    def likelihood_field(self, level: int = 0) -> LikelihoodField:
        return self.fields[level]

    def likelihood_pyramid(self, levels: int) -> list[LikelihoodField]:
        return self.fields[:levels]


def _residuals(field: LikelihoodField, points: np.ndarray, pose: np.ndarray) -> np.ndarray:
    """1 - M(T p) per point, from LikelihoodField.sample and Pose2D's own transform."""
    return 1.0 - field.sample(Pose2D.from_array(pose).transform_points(points))[0]


@settings(max_examples=50, deadline=None)
@given(
    x=st.floats(-100, 100), y=st.floats(-100, 100), theta=st.floats(-10, 10),
    seed=st.integers(0, 2**31),
)
def test_moved_points_equal_the_poses_transform(
    x: float, y: float, theta: float, seed: int
) -> None:
    points = np.random.default_rng(seed).uniform(-20, 20, (30, 2))
    np.testing.assert_allclose(
        moved_points(points, np.array([x, y, theta])),
        Pose2D(x, y, theta).transform_points(points), rtol=0.0, atol=1e-12,
    )


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**31), rows=st.integers(2, 12), cols=st.integers(2, 12))
def test_cost_and_gauss_newton_terms_equal_the_sampled_field_on_a_random_grid(
    seed: int, rows: int, cols: int
) -> None:
    """Any field values, non-zero up to the grid's border, points on it and around it: cost,
    hits, J^T J and J^T r with J from LikelihoodField.sample's value and gradient."""
    rng = np.random.default_rng(seed)
    spec = GridSpec(rng.uniform(-5, 5), rng.uniform(-5, 5), 0.1, rows, cols)
    values = rng.uniform(0.0, 1.0, spec.shape) * (rng.random(spec.shape) < 0.8)
    field = LikelihoodField(spec, values, 0.1)
    lo = np.array([spec.origin_x_m, spec.origin_y_m])
    points = lo + rng.uniform(-0.2, 1.2, (100, 2)) * [spec.width_m, spec.height_m]
    pose = np.array([rng.uniform(-0.05, 0.05), rng.uniform(-0.05, 0.05), rng.uniform(-0.1, 0.1)])
    moved = moved_points(points, pose)
    value, grad = field.sample(moved)
    c, s = math.cos(pose[2]), math.sin(pose[2])
    d_theta = np.column_stack((-s * points[:, 0] - c * points[:, 1],
                               c * points[:, 0] - s * points[:, 1]))
    jac = -np.column_stack((grad, np.sum(grad * d_theta, axis=1)))
    r = 1.0 - value
    lin = linearise(field, points, pose)
    assert field_cost(field, points, pose) == lin.cost == pytest.approx(r @ r, rel=1e-12)
    assert field_hits(field, points, pose) == lin.hits == np.count_nonzero(value)
    np.testing.assert_allclose(lin.hessian, jac.T @ jac, rtol=1e-10, atol=1e-9)
    np.testing.assert_allclose(lin.gradient, jac.T @ r, rtol=1e-10, atol=1e-9)



@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**31))
def test_with_normals_the_terms_take_the_sampled_slope_across_each_surface(seed: int) -> None:
    """With a normal per point (source frame; zero: none), J holds the sampled gradient
    projected onto the normal turned by the pose, and the whole gradient where it is zero; the
    cost and hits do not change."""
    rng = np.random.default_rng(seed)
    spec = GridSpec(-1.0, -1.0, 0.1, 20, 20)
    field = LikelihoodField(spec, rng.uniform(0.0, 1.0, spec.shape), 0.1)
    points = rng.uniform(-0.8, 0.8, (60, 2))
    angle = rng.uniform(-math.pi, math.pi, len(points))
    normals = np.column_stack((np.cos(angle), np.sin(angle))) * (rng.random(60) < 0.7)[:, None]
    pose = np.array([rng.uniform(-0.05, 0.05), rng.uniform(-0.05, 0.05), rng.uniform(-1, 1)])
    value, grad = field.sample(moved_points(points, pose))
    turned = moved_points(normals, np.array([0.0, 0.0, pose[2]]))
    has = np.any(normals != 0.0, axis=1)
    grad[has] = np.sum(grad[has] * turned[has], axis=1)[:, None] * turned[has]
    c, s = math.cos(pose[2]), math.sin(pose[2])
    d_theta = np.column_stack((-s * points[:, 0] - c * points[:, 1],
                               c * points[:, 0] - s * points[:, 1]))
    jac = -np.column_stack((grad, np.sum(grad * d_theta, axis=1)))
    r = 1.0 - value
    lin = linearise(field, points, pose, normals)
    whole = linearise(field, points, pose)
    assert lin.cost == whole.cost and lin.hits == whole.hits
    np.testing.assert_allclose(lin.hessian, jac.T @ jac, rtol=1e-10, atol=1e-9)
    np.testing.assert_allclose(lin.gradient, jac.T @ r, rtol=1e-10, atol=1e-9)
    with pytest.raises(ValueError, match="normals must have shape"):
        linearise(field, points, pose, normals[:-1])


def test_the_finest_level_takes_normals_only_where_they_still_pin_the_pose(
    room: np.ndarray, corridor: np.ndarray, caster: Caster, room_map_points: np.ndarray,
    corridor_map_points: np.ndarray,
) -> None:
    """In the room most points get their wall's normal (corners none); along a corridor whose
    walls are exact, where the slope across them says nothing of the axis, every point gets
    none. (With noise their normals tilt and can fake a constraint along the axis, as a near
    wall's do in `surface_conditioning`; the checks after the match judge that.)"""
    in_room = caster(room, ROOM_POSE, noise_m=0.005)
    normals = finest_normals(points_field(room_map_points, 0.05, 0.1), in_room,
                             ROOM_POSE.to_array())
    has = np.any(normals != 0.0, axis=1)
    assert has.mean() > 0.8
    np.testing.assert_allclose(np.hypot(*normals[has].T), 1.0)
    along = caster(corridor, Pose2D(0.0, 0.2, 0.1))
    none = finest_normals(points_field(corridor_map_points, 0.05, 0.1), along,
                          np.array([0.0, 0.2, 0.1]))
    assert not np.any(none)

def test_gauss_newton_terms_equal_a_finite_difference_jacobian(
    room_map_points: np.ndarray, room: np.ndarray, caster: Caster
) -> None:
    """H = J^T J and g = J^T r with J the per-point Jacobian of r = 1 - M(T p) by central
    differences of the sampled field over (x, y, theta)."""
    field = points_field(room_map_points, 0.05, 0.1)
    points = caster(room, ROOM_POSE, noise_m=0.01)
    h = 1e-7
    rng = np.random.default_rng(4)
    for _ in range(5):
        pose = ROOM_POSE.to_array() + rng.normal(0.0, [0.03, 0.03, 0.02])
        jac = np.column_stack([
            (_residuals(field, points, pose + h * e) - _residuals(field, points, pose - h * e))
            / (2 * h)
            for e in np.eye(3)
        ])
        r = _residuals(field, points, pose)
        lin = linearise(field, points, pose)
        scale = np.abs(jac.T @ jac).max()
        np.testing.assert_allclose(lin.hessian, jac.T @ jac, rtol=1e-5, atol=1e-6 * scale)
        np.testing.assert_allclose(lin.gradient, jac.T @ r, rtol=1e-5, atol=1e-6 * scale)
        assert lin.hits == np.count_nonzero(r != 1.0)


def test_jacobian_matches_finite_differences(
    room_map_points: np.ndarray, room: np.ndarray, caster: Caster
) -> None:
    field = points_field(room_map_points, 0.05, 0.1)
    pts = caster(room, Pose2D(0.3, 0.2, 0.4))
    pose = np.array([0.33, 0.17, 0.41])
    lin = linearise(field, pts, pose)
    eps = 1e-6
    num = [
        (field_cost(field, pts, pose + eps * e) - field_cost(field, pts, pose - eps * e))
        / (2 * eps)
        for e in np.eye(3)
    ]
    # d(sum r^2)/dpose = 2 J^T r
    np.testing.assert_allclose(2 * lin.gradient, num, rtol=1e-3, atol=1e-3)


def test_compiled_linearisation_equals_the_sampled_field(room_map_points: np.ndarray) -> None:
    """Cost, hits, J^T J and J^T r from one compiled pass equal LikelihoodField.sample's,
    points off the grid included (value 0, no gradient)."""
    field = points_field(room_map_points, 0.05, 0.1)
    rng = np.random.default_rng(2)
    pts = np.vstack((rng.uniform(-5, 5, (300, 2)), [[40.0, 0.0], [0.0, -40.0]]))
    pose = np.array([0.05, -0.02, 0.1])
    c, s = math.cos(pose[2]), math.sin(pose[2])
    moved = pts @ np.array([[c, s], [-s, c]]) + pose[:2]
    value, grad = field.sample(moved)
    d_theta = np.column_stack((-s * pts[:, 0] - c * pts[:, 1], c * pts[:, 0] - s * pts[:, 1]))
    jac = -np.column_stack((grad, (grad * d_theta).sum(axis=1)))
    r = 1.0 - value
    lin = linearise(field, pts, pose)
    assert lin.cost == pytest.approx(r @ r, rel=1e-12)
    assert lin.hits == np.count_nonzero(value)
    np.testing.assert_allclose(lin.hessian, jac.T @ jac, rtol=1e-10, atol=1e-9)
    np.testing.assert_allclose(lin.gradient, jac.T @ r, rtol=1e-10, atol=1e-9)


def test_a_grid_too_small_to_interpolate_holds_no_point() -> None:
    field = LikelihoodField(GridSpec(0.0, 0.0, 0.05, 1, 5), np.ones((1, 5)), 0.1)
    points = np.array([[0.025, 0.025], [0.1, 0.025], [0.2, 0.0]])
    assert field_cost(field, points, np.zeros(3)) == 3.0
    assert field_hits(field, points, np.zeros(3)) == 0


@settings(max_examples=25, deadline=None)
@given(
    seed=st.integers(0, 2**31),
    n=st.integers(1, 40),
    resolution_m=st.sampled_from([0.05, 0.1]),
    sigma_m=st.floats(0.03, 0.2),
)
def test_dense_points_field_is_the_gaussian_of_the_distance_to_the_nearest_cell_mean(
    seed: int, n: int, resolution_m: float, sigma_m: float
) -> None:
    """At every cell centre, exp(-d^2 / 2 sigma^2) with d to the nearest mean point of an
    occupied cell (by a brute-force search), exactly 0 beyond CUTOFF_SIGMAS sigma; the grid
    reaches past every point by that cut-off."""
    points = np.random.default_rng(seed).uniform(-1.0, 1.0, (n, 2))
    field = dense_points_field(points, resolution_m, sigma_m)
    spec = field.spec
    assert field.sigma_m == sigma_m and spec.resolution_m == resolution_m
    cutoff_m = CUTOFF_SIGMAS * sigma_m
    lo = np.array([spec.origin_x_m, spec.origin_y_m])
    assert np.all(points - cutoff_m >= lo)
    assert np.all(points + cutoff_m <= lo + np.array([spec.width_m, spec.height_m]))
    cell = np.floor((points - lo) / resolution_m).astype(np.int64)
    _, member = np.unique(cell[:, 1] * spec.cols + cell[:, 0], return_inverse=True)
    means = np.column_stack([np.bincount(member, points[:, a]) for a in (0, 1)])
    means /= np.bincount(member)[:, None]
    rows, cols = np.indices(spec.shape)
    centres = lo + (np.column_stack((cols.ravel(), rows.ravel())) + 0.5) * resolution_m
    d = np.sqrt(np.min(np.sum((centres[:, None] - means[None]) ** 2, axis=2), axis=1))
    expected = np.where(d <= cutoff_m, np.exp(-0.5 * (d / sigma_m) ** 2), 0.0)
    near_cutoff = np.abs(d - cutoff_m) < 1e-9
    np.testing.assert_allclose(
        field.values.ravel()[~near_cutoff], expected[~near_cutoff], rtol=1e-9, atol=1e-12
    )


def test_points_field_bridges_the_gaps_along_a_sparse_scans_surface() -> None:
    """A wall 5 m off seen 3.4 deg apart (30 cm, within one surface's gap at that range): its
    field is a ridge all along, midway between the points too; the same points' field built
    as dense (`dense_points_field`) has a bump per point."""
    bearings = np.radians(np.arange(-20.0, 20.0, 3.4))
    wall = np.column_stack((np.full(bearings.size, 5.0), 5.0 * np.tan(bearings)))
    midway = 0.5 * (wall[1:] + wall[:-1])
    bridged = points_field(wall, 0.05, 0.05)
    assert np.all(bridged.sample(midway)[0] > 0.9 * bridged.sample(wall)[0].min())
    assert np.all(dense_points_field(wall, 0.05, 0.05).sample(midway)[0] < 0.1)


def test_pyramid_of_points_doubles_cell_and_sigma_per_level_coarse_first(
    room: np.ndarray, caster: Caster
) -> None:
    target = caster(room, Pose2D())
    pyramid = field_pyramid(target, 3, 0.05, 0.1)
    assert [f.spec.resolution_m for f in pyramid] == [0.2, 0.1, 0.05]
    assert [f.sigma_m for f in pyramid] == pytest.approx([0.4, 0.2, 0.1])
    np.testing.assert_array_equal(pyramid[-1].values, points_field(target, 0.05, 0.1).values)


def test_pyramid_of_a_map_is_its_own_coarse_first(room_map_points: np.ndarray) -> None:
    fine_first = [dense_points_field(room_map_points, 0.05 * 2**k, 0.1 * 2**k) for k in range(4)]
    pyramid = field_pyramid(_FieldMap(fine_first), 3, 0.05, 0.1)
    assert [id(f) for f in pyramid] == [id(f) for f in fine_first[2::-1]]


def test_pyramid_needs_a_level() -> None:
    with pytest.raises(ValueError, match="levels must be >= 1"):
        field_pyramid(np.ones((20, 2)), 0, 0.05, 0.1)


def test_an_empty_target_is_one_without_points_or_a_map_with_a_zero_field() -> None:
    assert is_empty_target(np.zeros((0, 2))) and is_empty_target([])
    assert not is_empty_target(np.zeros((1, 2)))
    spec = GridSpec(0.0, 0.0, 0.05, 4, 4)
    assert is_empty_target(_FieldMap([LikelihoodField(spec, np.zeros((4, 4)), 0.1)]))
    values = np.zeros((4, 4))
    values[2, 1] = 1e-3
    assert not is_empty_target(_FieldMap([LikelihoodField(spec, values, 0.1)]))


def test_convergence_needs_small_translation_and_small_absolute_rotation() -> None:
    assert converged_step(np.array([1e-5, 0.0, -1e-5]), 1e-3, 1e-3)
    assert not converged_step(np.array([1e-5, 0.0, -0.2]), 1e-3, 1e-3)  # the seed's bug
    assert not converged_step(np.array([0.01, 0.0, 0.0]), 1e-3, 1e-3)


def test_coarse_levels_have_relaxed_tolerances_and_may_run_out_of_iterations() -> None:
    assert level_tolerances(True, 1e-3, 2e-3) == (1e-3, 2e-3)
    assert level_tolerances(False, 1e-3, 2e-3) == pytest.approx(
        (COARSE_TOLERANCE_FACTOR * 1e-3, COARSE_TOLERANCE_FACTOR * 2e-3))
    pose = np.array([1.0, 2.0, 0.3])
    coarse, finest = out_of_iterations(pose, 7, False), out_of_iterations(pose, 7, True)
    assert coarse.status is None and coarse.iterations == 7 and coarse.pose is pose
    assert finest.status is MatchStatus.MAX_ITERATIONS and finest.iterations == 7
    assert finest.pose is pose and "7 iterations" in finest.message


def _spd(rng: np.random.Generator, eigenvalues: NDArray[np.float64]) -> NDArray[np.float64]:
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    return q @ np.diag(eigenvalues) @ q.T


@settings(max_examples=50, deadline=None)
@given(seed=st.integers(0, 2**31))
def test_well_determined_step_is_the_newton_step_when_every_direction_is(seed: int) -> None:
    rng = np.random.default_rng(seed)
    hessian = _spd(rng, rng.uniform(0.1, 10.0, 3))
    rhs = rng.normal(size=3)
    step = solve_well_determined(hessian, rhs, 1.0)
    assert step is not None
    np.testing.assert_allclose(step, np.linalg.solve(hessian, rhs), rtol=1e-9, atol=1e-12)


@settings(max_examples=50, deadline=None)
@given(seed=st.integers(0, 2**31), axis_rad=st.floats(-math.pi, math.pi))
def test_well_determined_step_is_zero_along_an_unconstrained_direction(
    seed: int, axis_rad: float
) -> None:
    """A corridor along `axis_rad`: H has no curvature along it; the step has no component
    along it and solves H step = rhs in the directions H constrains."""
    rng = np.random.default_rng(seed)
    along = np.array([math.cos(axis_rad), math.sin(axis_rad), 0.0])
    across = np.linalg.qr(np.column_stack((along, rng.normal(size=(3, 2)))))[0][:, 1:]
    hessian = across @ np.diag(rng.uniform(0.5, 5.0, 2)) @ across.T
    rhs = rng.normal(size=3)
    step = solve_well_determined(hessian, rhs, 1.0)
    assert step is not None
    assert abs(step @ along) < 1e-9
    np.testing.assert_allclose(hessian @ step, rhs - (rhs @ along) * along, atol=1e-9)


def test_well_determined_step_scales_rotation_by_the_points_spread() -> None:
    """H = diag(1, 1, 0.01): rotation counts as constrained for points 1 m across, not for
    points 10 m across (0.01 / 10^2 is below DEGENERATE_RATIO), whose step keeps theta."""
    hessian, rhs = np.diag([1.0, 1.0, 0.01]), np.array([0.2, -0.1, 0.05])
    assert 0.01 > DEGENERATE_RATIO > 0.01 / 10.0**2
    np.testing.assert_allclose(solve_well_determined(hessian, rhs, 1.0), [0.2, -0.1, 5.0])
    np.testing.assert_allclose(solve_well_determined(hessian, rhs, 10.0), [0.2, -0.1, 0.0])


@pytest.mark.parametrize(
    "hessian",
    [np.diag([1.0, 0.0, 0.0]), np.zeros((3, 3)), -np.eye(3), np.diag([1.0, np.nan, 1.0])],
    ids=["one-direction", "zero", "negative", "nan"],
)
def test_well_determined_step_is_none_with_fewer_than_two_directions(hessian: np.ndarray) -> None:
    assert solve_well_determined(hessian, np.ones(3), 1.0) is None


def test_inputs_too_few_or_empty_give_a_failed_result() -> None:
    guess = Pose2D(0.1, 0.2, 0.3)
    points = np.random.default_rng(0).uniform(-2, 2, (MIN_POINTS, 2))
    assert check_inputs("gn", points, points, guess) is None
    few = check_inputs("gn", points[:-1], points, guess)
    assert few is not None and few.status is MatchStatus.TOO_FEW_POINTS
    assert f"source has {MIN_POINTS - 1} points" in few.message
    empty = check_inputs("gn", points, np.zeros((0, 2)), guess)
    assert empty is not None and empty.status is MatchStatus.EMPTY_MAP
    for failed in (few, empty):
        assert failed.pose == guess and failed.method == "gn" and not failed.converged
        assert np.all(np.isinf(np.diag(failed.covariance)))


def _fixed_solver(
    calls: list[tuple[float, bool]], pose: NDArray[np.float64], iterations: int = 2,
    status: MatchStatus | None = None,
) -> Callable[..., LevelOutcome]:
    """A level solver that records (cell size, finest) and always answers `pose`."""

    def solve(
        field: LikelihoodField, source: np.ndarray, normals: np.ndarray, start: np.ndarray,
        finest: bool,
    ) -> LevelOutcome:
        calls.append((field.spec.resolution_m, finest))
        return LevelOutcome(pose, iterations, status, "stub" if status else "")

    return solve


def test_coarse_to_fine_runs_each_level_coarse_first_and_assesses_the_last_pose(
    room: np.ndarray, caster: Caster, room_map_points: np.ndarray
) -> None:
    source = caster(room, ROOM_POSE, noise_m=0.01)
    calls: list[tuple[float, bool]] = []
    solver = _fixed_solver(calls, ROOM_POSE.to_array())
    r = run_coarse_to_fine("stub", source, room_map_points, Pose2D(), solver, 3, 0.05, 0.1)
    assert calls == [(0.2, False), (0.1, False), (0.05, True)]
    assert r.status is MatchStatus.OK and r.method == "stub" and r.iterations == 6
    assert r.pose.relative_to(ROOM_POSE).translation_norm() < 1e-12


def test_coarse_to_fine_reports_a_levels_failure_with_the_guess(
    room: np.ndarray, caster: Caster, room_map_points: np.ndarray
) -> None:
    source = caster(room, ROOM_POSE)
    guess = ROOM_POSE * Pose2D(0.02, 0.0, 0.0)
    calls: list[tuple[float, bool]] = []
    solver = _fixed_solver(calls, ROOM_POSE.to_array(), 3, MatchStatus.STEP_LIMIT)
    r = run_coarse_to_fine("stub", source, room_map_points, guess, solver, 3, 0.05, 0.1)
    assert len(calls) == 1 and r.iterations == 3
    assert r.status is MatchStatus.STEP_LIMIT and r.message == "stub" and r.pose == guess


def test_coarse_to_fine_refuses_no_overlap(
    room: np.ndarray, caster: Caster, room_map_points: np.ndarray
) -> None:
    calls: list[tuple[float, bool]] = []
    far = run_coarse_to_fine("stub", caster(room, ROOM_POSE) + 500.0, room_map_points, ROOM_POSE,
                             _fixed_solver(calls, ROOM_POSE.to_array()), 2, 0.05, 0.1)
    assert far.status is MatchStatus.NO_OVERLAP and calls == []


@pytest.mark.parametrize(("end_dx_m", "diverged"), [(0.055, False), (0.065, True)])
def test_coarse_to_fine_refuses_a_fine_cost_risen_past_the_divergence_ratio(
    room: np.ndarray, caster: Caster, room_map_points: np.ndarray, end_dx_m: float,
    diverged: bool,
) -> None:
    """From a guess 5 cm off, solvers ending 5.5 cm off (the fine cost up 1.3x) and 6.5 cm off
    (up 2.1x): only the second passes DIVERGENCE_RATIO."""
    source = caster(room, ROOM_POSE)
    guess = ROOM_POSE * Pose2D(0.05, 0.0, 0.0)
    end = ROOM_POSE * Pose2D(end_dx_m, 0.0, 0.0)
    fine = points_field(room_map_points, 0.05, 0.1)
    rise = field_cost(fine, source, end.to_array()) / field_cost(fine, source, guess.to_array())
    assert rise > 1.0 and (rise > DIVERGENCE_RATIO) is diverged
    calls: list[tuple[float, bool]] = []
    r = run_coarse_to_fine("stub", source, room_map_points, guess,
                           _fixed_solver(calls, end.to_array()), 2, 0.05, 0.1)
    assert (r.status is MatchStatus.DIVERGED) is diverged and r.iterations == 4
    assert r.pose == (guess if diverged else end)


def test_assessed_match_has_the_least_squares_covariance_at_its_pose(
    room: np.ndarray, caster: Caster, room_map_points: np.ndarray
) -> None:
    """Covariance sigma^2 H^-1 from the points on the field (20 far outliers are not), the
    score from all points, the pose as given."""
    rng = np.random.default_rng(1)
    source = np.vstack((caster(room, ROOM_POSE, noise_m=0.01, rng=rng),
                        rng.uniform(40.0, 50.0, (20, 2))))
    field = points_field(room_map_points, 0.05, 0.1)
    pose = ROOM_POSE.to_array()
    r = assess_field_match("gn", field, source, pose, 9, Pose2D())
    lin = linearise(field, source, pose)
    assert lin.hits == len(source) - 20
    assert r.status is MatchStatus.OK and r.converged and r.iterations == 9
    assert r.pose.relative_to(ROOM_POSE).translation_norm() < 1e-12
    np.testing.assert_allclose(r.covariance, least_squares_covariance(lin.hessian, lin.cost,
                                                                      lin.hits))
    assert r.inliers == lin.hits and r.score == pytest.approx(1.0 - lin.cost / len(source))


def test_assessed_match_in_a_corridor_keeps_the_guess_along_it(
    corridor: np.ndarray, caster: Caster, corridor_map_points: np.ndarray
) -> None:
    """Along the corridor (1 cm range noise) the field has no slope: DEGENERATE along x,
    which takes the guess's value; across it the pose stays."""
    truth = Pose2D(0.3, 0.05, 0.03)
    source = caster(corridor, truth, max_range_m=8.0, noise_m=0.01, rng=np.random.default_rng(0))
    field = points_field(corridor_map_points, 0.05, 0.1)
    guess = Pose2D(1.0, 0.0, 0.03)
    r = assess_field_match("gn", field, source, truth.to_array(), 5, guess)
    assert r.status is MatchStatus.DEGENERATE and abs(r.weak_direction[0]) > 0.95
    assert abs(r.pose.x - guess.x) < 0.02 and abs(r.pose.y - truth.y) < 0.01
    assert abs(r.pose.theta - truth.theta) < 0.005


@pytest.mark.parametrize(
    ("method", "extra_point", "options"),
    [
        (method, extra_point, options)
        for method in ("gn", "lm", "gn+plicp", "csm", "csm+plicp")
        for extra_point, options in (
            ([1e4, 1e4], {}),  # one return 10 km off: numpy asked for 298 GiB
            ([1e6, 0.0], {}),
            (None, {"sigma_m": 1e6}),  # its field's margin: 182 PiB
            (None, {"resolution_m": 1e-12}),  # densified along its surfaces: 198 TiB
        )
        if method != "csm+plicp" or "sigma_m" not in options  # not one of its options
    ],
)
def test_a_field_too_large_for_memory_is_a_match_input_error_not_a_memory_error(
    room: np.ndarray, caster: Caster, method: str, extra_point: list[float] | None,
    options: dict[str, float],
) -> None:
    """A point target's field covers its bounding box: a far glitch point or an option out of
    scale is refused naming the target and the options (docs/matching.md, bad input), before numpy
    allocates anything."""
    target = caster(room, Pose2D())
    if extra_point is not None:
        target = np.vstack((target, [extra_point]))
    # (csm's sigma_m is out of its range first: at most 1000 m.)
    with pytest.raises(MatchInputError, match=r"too large|sigma_m must be <= 1000"):
        match(caster(room, ROOM_POSE), target, ROOM_POSE, method=method, **options)
