"""Nearest-neighbour association: the bucket grid and its lookups, target line fits, dense-target
thinning and the adaptive gate, each against an independent numpy computation."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from numpy.typing import NDArray
from scanflow.geometry import Pose2D
from scanflow.matching.correspondence import (
    MAD_TO_SIGMA,
    MAX_GRID_CELLS,
    THIN_BELOW_DEG,
    THIN_DEPTH_M,
    GridIndex,
    adaptive_gate_m,
    grid_k_nearest,
    grid_nearest_all,
    target_lines,
    thin_dense_target,
)
from scanflow.matching.surface import surface_gap_m
from scanflow.sim import get_world, static_scan
from scipy.spatial import cKDTree

# The dense "rooms" scans of test_dense_target.py (test files share no code, so its helper too).
TARGET_POSE = Pose2D(2.5, 2.0, 0.2) * Pose2D(0.05, 0.0, 0.01)


def scan_points(pose: Pose2D, seed: int, beams: int = 360) -> np.ndarray:
    """A still 360-deg sweep of `beams` in the "rooms" world, 1 cm range noise (the sim's lidar
    model stops at 1,440 beams)."""
    angles = np.arange(beams) * (2 * math.pi / beams)
    rng = np.random.default_rng(seed)
    return static_scan(get_world("rooms").segments, pose, angles, 12.0, 0.01, rng)


def _walls_and_clutter(seed: int) -> NDArray[np.float64]:
    """A few noisy straight walls at random places and spacings, near the origin (points up to
    15 cm apart) or far from it (up to 1.5 m apart: beyond the fixed radius, within the surface
    gap at their range), plus scattered clutter."""
    rng = np.random.default_rng(seed)
    parts = []
    for _ in range(rng.integers(1, 5)):
        far = rng.random() < 0.3
        start = rng.uniform(-4, 4, 2) + (rng.uniform(20, 40) if far else 0.0)
        heading = rng.uniform(-math.pi, math.pi)
        spacing = rng.uniform(0.6, 1.5) if far else rng.uniform(0.02, 0.15)
        t = np.arange(0.0, rng.uniform(0.3, 3.0) * (10 if far else 1), spacing)
        wall = start + t[:, None] * np.array([math.cos(heading), math.sin(heading)])
        parts.append(wall + rng.normal(0.0, rng.uniform(0.0, 0.02), wall.shape))
    parts.append(rng.uniform(-5, 5, (rng.integers(0, 30), 2)))
    return np.vstack(parts)


def _brute_force_neighbours(
    points: NDArray[np.float64], i: int, k: int, fit_radius_m: float, reach_m: float
) -> NDArray[np.int64]:
    """Indices of point i's line neighbours by a full sort: up to k within the fit radius, else
    the nearest two within `reach_m` (itself included); empty when fewer than two."""
    d2 = np.sum((points - points[i]) ** 2, axis=1)
    order = np.argsort(d2, kind="stable")
    near = order[d2[order] <= fit_radius_m**2][:k]
    if len(near) < 2:
        near = order[d2[order] <= reach_m**2][:2]
    return near if len(near) >= 2 else near[:0]


def test_gate_follows_the_robust_spread_within_bounds() -> None:
    assert adaptive_gate_m(np.full(10, 0.01), 0.15, 1.0) == 0.15
    assert adaptive_gate_m(np.full(10, 10.0), 0.15, 1.0) == 1.0
    assert np.isclose(adaptive_gate_m(np.full(10, 0.1), 0.15, 1.0), 3 * 1.4826 * 0.1)
    assert adaptive_gate_m(np.zeros(0), 0.15, 1.0) == 1.0


@settings(max_examples=60, deadline=None)
@given(
    n=st.integers(1, 100),
    seed=st.integers(0, 2**31),
    floor=st.floats(0.0, 0.5),
    extra=st.floats(0.0, 2.0),
)
def test_gate_is_three_robust_sigmas_of_the_median_distance_clipped_to_its_bounds(
    n: int, seed: int, floor: float, extra: float
) -> None:
    d = np.random.default_rng(seed).exponential(0.1, n)
    expected = np.clip(3.0 * MAD_TO_SIGMA * np.median(d), floor, floor + extra)
    assert adaptive_gate_m(d, floor, floor + extra) == pytest.approx(expected, rel=1e-12)


@pytest.mark.parametrize("cell_m", [0.0, -0.25, math.nan])
def test_grid_refuses_a_cell_size_that_is_not_positive(cell_m: float) -> None:
    with pytest.raises(ValueError, match="cell_m"):
        GridIndex.build(np.zeros((3, 2)), cell_m)


def test_grid_refuses_no_points() -> None:
    with pytest.raises(ValueError, match="at least one point"):
        GridIndex.build(np.zeros((0, 2)))


@pytest.mark.parametrize(("extent_m", "grows"), [(5.0, False), (2000.0, True)])
def test_grid_buckets_every_point_in_its_cell_and_grows_cells_on_a_wide_target(
    extent_m: float, grows: bool
) -> None:
    """Each point sits in the bucket of the cell its coordinates fall in; a target too wide for
    MAX_GRID_CELLS cells of the requested size gets larger cells, and about that many."""
    pts = np.random.default_rng(5).uniform(0.0, extent_m, (500, 2))
    grid = GridIndex.build(pts, 0.25)
    assert (grid.cell_m > 0.25) is grows
    assert grid.rows * grid.cols <= 1.05 * MAX_GRID_CELLS
    assert np.array_equal(np.sort(grid.order), np.arange(len(pts)))
    assert grid.starts[0] == 0 and grid.starts[-1] == len(pts)
    assert np.all(np.diff(grid.starts) >= 0)
    col = np.floor((pts[:, 0] - grid.origin_x_m) / grid.cell_m).astype(np.int64)
    row = np.floor((pts[:, 1] - grid.origin_y_m) / grid.cell_m).astype(np.int64)
    assert np.all((col >= 0) & (col < grid.cols) & (row >= 0) & (row < grid.rows))
    for j, cell in enumerate(row * grid.cols + col):
        assert j in grid.order[grid.starts[cell] : grid.starts[cell + 1]]
    assert grid.arrays[0] is pts and grid.arrays[3:] == (
        grid.origin_x_m, grid.origin_y_m, grid.cell_m, grid.cols, grid.rows)


@settings(max_examples=40, deadline=None)
@given(
    seed=st.integers(0, 2**31),
    gate=st.floats(0.05, 2.0),
    k=st.sampled_from([1, 3, 8]),
    cell=st.sampled_from([0.05, 0.25, 1.0]),
)
def test_grid_k_nearest_matches_kdtree(seed: int, gate: float, k: int, cell: float) -> None:
    """The ring search (which stops early) finds the same k nearest as scipy's KD-tree."""
    rng = np.random.default_rng(seed)
    pts = rng.uniform(-10, 10, (200, 2))
    queries = rng.uniform(-11, 11, (50, 2))
    grid = GridIndex.build(pts, cell)
    dist, _ = cKDTree(pts).query(queries, k=k, distance_upper_bound=gate)
    dist = dist.reshape(len(queries), k)
    best_d2, best_j = np.empty(k), np.empty(k, dtype=np.int64)
    for q, d in zip(queries, dist, strict=True):
        found = grid_k_nearest(grid.arrays, q[0], q[1], gate, best_d2, best_j)
        expected = d[np.isfinite(d)]
        assert found == len(expected) and np.all(best_j[found:] == -1)
        assert np.allclose(np.sqrt(best_d2[:found]), expected, rtol=1e-12, atol=0.0)
        assert np.allclose(np.hypot(*(pts[best_j[:found]] - q).T), expected, rtol=1e-12, atol=0.0)


@settings(max_examples=40, deadline=None)
@given(
    seed=st.integers(0, 2**31),
    gate=st.sampled_from([0.125, 0.25, 0.375, 0.5, 1.0]),
    k=st.sampled_from([1, 2, 16]),
)
def test_grid_k_nearest_on_cell_edges_equals_a_brute_force_search(
    seed: int, gate: float, k: int
) -> None:
    """Points and queries on the cells' edges and corners, with duplicates, where a distance
    equals the radius or the skip and stop bounds exactly: no cell skipped holds one of the k."""
    rng = np.random.default_rng(seed)
    pts = rng.integers(-8, 8, (300, 2)) * 0.125
    queries = np.vstack((rng.integers(-10, 10, (40, 2)) * 0.125, pts[:10]))
    grid = GridIndex.build(pts, 0.25)
    best_d2, best_j = np.empty(k), np.empty(k, dtype=np.int64)
    for q in queries:
        found = grid_k_nearest(grid.arrays, q[0], q[1], gate, best_d2, best_j)
        d2 = np.sort(np.sum((pts - q) ** 2, axis=1))  # brute force; the gate is inclusive
        expected = d2[d2 <= gate * gate][:k]
        assert found == len(expected)
        np.testing.assert_array_equal(np.sum((pts[best_j[:found]] - q) ** 2, axis=1), expected)


@settings(max_examples=40, deadline=None)
@given(
    seed=st.integers(0, 2**31),
    scale=st.sampled_from([1.0, 1000.0]),
    cell=st.sampled_from([0.05, 0.25, 1.0]),
)
def test_grid_nearest_all_equals_a_brute_force_search(seed: int, scale: float, cell: float) -> None:
    """Each query's nearest point within its own radius (-1 if none), queries far outside the
    grid included; at 1000x the scale the grid's cells have grown to bound its size."""
    rng = np.random.default_rng(seed)
    pts = rng.uniform(-10, 10, (150, 2)) * scale
    queries = rng.uniform(-30, 30, (60, 2)) * scale
    radii = rng.uniform(0.0, 25.0, 60) * scale
    got = grid_nearest_all(GridIndex.build(pts, cell).arrays, queries, radii)
    d2 = np.sum((queries[:, None, :] - pts[None, :, :]) ** 2, axis=2)
    nearest = np.argmin(d2, axis=1)
    inside = d2[np.arange(len(queries)), nearest] <= radii**2
    np.testing.assert_array_equal(got, np.where(inside, nearest, -1))


@settings(max_examples=30, deadline=None)
@given(
    seed=st.integers(0, 2**31),
    k=st.sampled_from([2, 5, 8]),
    fit_radius_m=st.floats(0.05, 0.4),
    max_flatness=st.sampled_from([0.01, 0.05, 0.2]),
    seen_from_origin=st.booleans(),
)
def test_target_lines_equal_an_svd_fit_of_the_brute_force_neighbours(
    seed: int, k: int, fit_radius_m: float, max_flatness: float, seen_from_origin: bool
) -> None:
    """Per point, the neighbours a full sort picks decide: ok exactly where they pass the
    flatness test (numpy's SVD), and then the line keeps them, their centroid, the normal (the
    least singular direction) and the spread of their total-least-squares fit."""
    pts = _walls_and_clutter(seed)
    radius_m = 0.5
    lines = target_lines(GridIndex.build(pts), k, radius_m, fit_radius_m, max_flatness,
                         seen_from_origin)
    reach = np.full(len(pts), radius_m)
    if seen_from_origin:
        reach = np.maximum(reach, surface_gap_m(np.hypot(*pts.T)))
    for i in range(len(pts)):
        near = _brute_force_neighbours(pts, i, k, fit_radius_m, reach[i])
        row = lines.neighbours[i]
        if len(near) < 2:
            assert not lines.ok[i] and np.all(row == -1)
            continue
        centred = pts[near] - pts[near].mean(axis=0)
        _, sv, vt = np.linalg.svd(centred)
        major, minor = sv[0] ** 2, sv[1] ** 2
        if abs(minor - max_flatness * major) <= 1e-9 * major:
            continue  # on the flatness threshold: either answer is right
        assert lines.ok[i] == (major > 0.0 and minor <= max_flatness * major)
        if not lines.ok[i]:
            assert np.all(row == -1)
        else:
            np.testing.assert_array_equal(row[: len(near)], near)
            assert np.all(row[len(near) :] == -1)
            np.testing.assert_allclose(lines.centres[i], pts[near].mean(axis=0), atol=1e-12)
            assert abs(np.linalg.norm(lines.normals[i]) - 1.0) < 1e-12
            assert abs(lines.normals[i] @ vt[1]) == pytest.approx(1.0, abs=1e-9)
            assert lines.spread_m2[i] == pytest.approx(major - minor, rel=1e-9, abs=1e-15)


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 2**31), k=st.sampled_from([2, 5, 16]), share=st.floats(0.0, 1.0))
def test_wanted_lines_are_the_full_fits_at_those_points_and_their_partners(
    seed: int, k: int, share: float
) -> None:
    """With `wanted`, each wanted point's line, and the partner's of each wanted two-point
    line, is exactly the full fit's; every other row is an unusable empty line."""
    pts = _walls_and_clutter(seed)
    grid = GridIndex.build(pts)
    full = target_lines(grid, k, 0.5, 0.5, seen_from_origin=True)
    wanted = np.random.default_rng(seed).uniform(size=len(pts)) < share
    some = target_lines(grid, k, 0.5, 0.5, seen_from_origin=True, wanted=wanted)
    two_point = wanted & full.ok & (np.sum(full.neighbours >= 0, axis=1) == 2)
    fitted = wanted.copy()
    fitted[full.neighbours[two_point, 1]] = True
    for name in ("normals", "centres", "ok", "neighbours", "spread_m2"):
        np.testing.assert_array_equal(getattr(some, name)[fitted], getattr(full, name)[fitted])
    assert not some.ok[~fitted].any() and np.all(some.neighbours[~fitted] == -1)


def test_target_lines_refuse_a_wanted_mask_of_another_length() -> None:
    with pytest.raises(ValueError, match=r"^wanted must hold one flag per point \(3\)"):
        target_lines(GridIndex.build(np.zeros((3, 2))), wanted=np.ones(2, dtype=bool))


def test_target_lines_leave_points_without_a_neighbour_unusable() -> None:
    pts = np.array([[0.0, 0.0], [0.1, 0.0], [0.2, 0.0], [3.0, 3.0]])
    lines = target_lines(GridIndex.build(pts), radius_m=0.5)
    assert lines.ok.tolist() == [True, True, True, False]
    assert np.all(lines.neighbours[3] == -1)


@pytest.mark.parametrize(
    ("options", "name"),
    [({"k": 1}, "k"), ({"fit_radius_m": 0.0}, "fit_radius_m"),
     ({"radius_m": 0.1, "fit_radius_m": 0.2}, "fit_radius_m")],
)
def test_target_lines_refuse_bad_parameters_naming_them(options: dict, name: str) -> None:
    with pytest.raises(ValueError, match=rf"^{name} must be"):
        target_lines(GridIndex.build(np.zeros((3, 2))), **options)


def test_line_fit_uses_the_neighbours_within_the_fit_radius() -> None:
    """Dense wall points get a many-point line; an isolated pair the two-point fallback."""
    wall = np.column_stack((np.linspace(0.0, 2.0, 41), np.zeros(41)))
    pair = np.array([[5.0, 5.0], [5.3, 5.3]])
    lines = target_lines(GridIndex.build(np.vstack((wall, pair))), k=8, fit_radius_m=0.2)
    counts = np.sum(lines.neighbours >= 0, axis=1)
    assert counts[20] == 8 and np.all(counts[-2:] == 2)
    assert np.allclose(np.abs(lines.normals[:41, 1]), 1.0) and lines.ok.all()
    assert np.isclose(abs(lines.normals[-1] @ (pair[1] - pair[0])), 0.0)


def test_a_far_walls_points_get_lines_only_when_read_as_one_scan() -> None:
    """Points 1 deg apart along a wall 40 m away (0.7 m apart): no neighbour within the fixed
    0.5 m, one within the surface gap at their range."""
    bearings = np.radians(np.arange(-10.0, 10.5, 1.0))
    wall = np.column_stack((np.full(bearings.size, 40.0), 40.0 * np.tan(bearings)))
    grid = GridIndex.build(wall)
    assert not target_lines(grid).ok.any()
    lines = target_lines(grid, seen_from_origin=True)
    assert lines.ok.all()
    np.testing.assert_allclose(np.abs(lines.normals[:, 0]), 1.0, atol=1e-9)


@pytest.mark.parametrize("beams", [180, 360, 720])
def test_scans_with_beams_half_a_degree_apart_or_more_are_not_thinned(beams: int) -> None:
    target = scan_points(TARGET_POSE, 2, beams=beams)
    assert thin_dense_target(target) is target


def test_a_dense_scan_is_averaged_to_line_like_fits() -> None:
    dense = scan_points(TARGET_POSE, 2, beams=20_000)
    thinned = thin_dense_target(dense)
    # 0.4 deg bins: ~900 points around, each the mean of ~20 beams.
    assert 800 < len(thinned) < 1000
    raw_ok = target_lines(GridIndex.build(dense)).ok.mean()
    thinned_ok = target_lines(GridIndex.build(thinned)).ok.mean()
    assert raw_ok < 0.1 and thinned_ok > 0.9
    assert thin_dense_target(dense, below_deg=0.0) is dense


def _polar(ranges: NDArray[np.float64], bearings: NDArray[np.float64]) -> NDArray[np.float64]:
    return np.column_stack((ranges * np.cos(bearings), ranges * np.sin(bearings)))


@settings(max_examples=20, deadline=None)
@given(seed=st.integers(0, 2**31), n=st.integers(500, 5000))
def test_thinning_gives_each_bearing_bins_centroid_in_bearing_order(seed: int, n: int) -> None:
    """Points on one surface (ranges 2 cm apart at most: no gap, no depth cut) at random
    bearings: one point per occupied bin, the mean of its points, bins in increasing order."""
    rng = np.random.default_rng(seed)
    pts = _polar(rng.uniform(2.99, 3.01, n), rng.uniform(-math.pi, math.pi, n))
    thinned = thin_dense_target(pts)
    bins = np.floor(np.arctan2(pts[:, 1], pts[:, 0]) / math.radians(THIN_BELOW_DEG))
    occupied, member = np.unique(bins, return_inverse=True)
    expected = np.column_stack([np.bincount(member, pts[:, a]) for a in (0, 1)])
    expected /= np.bincount(member)[:, None]
    np.testing.assert_allclose(thinned, expected, rtol=0.0, atol=1e-12)
    assert len(occupied) == len(thinned)


def test_thinning_keeps_two_surfaces_in_one_bearing_bin_apart() -> None:
    """A near and a far wall seen through the same bins, 10 cm apart (an occlusion edge, well
    above THIN_GAP_M, within THIN_DEPTH_M), stay two walls: no centroid falls in between."""
    bearings = np.radians(np.linspace(0.0, 10.0, 500, endpoint=False))
    pts = np.vstack((_polar(np.full(500, 2.0), bearings), _polar(np.full(500, 2.1), bearings)))
    ranges = np.hypot(*thin_dense_target(pts).T)
    near = np.isclose(ranges, 2.0, atol=1e-9)
    far = np.isclose(ranges, 2.1, atol=1e-9)
    assert np.all(near | far) and near.sum() == far.sum() == 25


def test_thinning_cuts_a_surface_running_away_from_the_origin_into_depth_chunks() -> None:
    """Points 1 mm apart along one bearing from 1 m to 2 m: chunks THIN_DEPTH_M deep, each
    replaced by its centroid on the same ray."""
    ranges = np.linspace(1.0, 2.0, 1001)
    bearing = math.radians(30.1)
    thinned = thin_dense_target(_polar(ranges, np.full(ranges.size, bearing)))
    np.testing.assert_allclose(np.arctan2(thinned[:, 1], thinned[:, 0]), bearing, atol=1e-12)
    steps = np.diff(np.hypot(*thinned.T))
    assert len(thinned) == 5
    np.testing.assert_allclose(steps[:-1], THIN_DEPTH_M, atol=0.002)
