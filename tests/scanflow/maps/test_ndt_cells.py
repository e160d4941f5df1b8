"""NDTCells: per-cell moments, eigenvalue floor, lookups and the four shifted grids."""

import math

import numpy as np
import pytest
from scanflow.maps.ndt_cells import (
    MIN_CELL_POINTS,
    GridNDTCells,
    GridOverlappingCells,
    NDTCells,
    OverlappingCells,
)
from scanflow.maps.ndt_moments import EIGEN_FLOOR_M2, EIGEN_FLOOR_RATIO
from scanflow.maps.occupancy import OccupancyGrid, OccupancyParams


def test_cells_hold_the_mean_and_inverse_covariance_of_their_points() -> None:
    rng = np.random.default_rng(3)
    cov = np.array([[0.02, 0.01], [0.01, 0.03]])
    pts = rng.multivariate_normal([10.5, -20.5], cov, size=400)
    pts = pts[(np.abs(pts - [10.5, -20.5]) < 0.5).all(axis=1)]
    cells = NDTCells.from_points(pts, 1.0, offset_m=(0.0, 0.0))
    k = cells.lookup(np.array([[10.5, -20.5]]))[0]
    assert k >= 0 and cells.counts[k] == len(pts)
    np.testing.assert_allclose(cells.means[k], pts.mean(axis=0), atol=1e-12)
    np.testing.assert_allclose(np.linalg.inv(cells.inv_covs[k]), np.cov(pts.T), rtol=1e-9)


def test_collinear_points_get_a_floored_covariance() -> None:
    x = np.linspace(0.05, 0.95, 50)
    cells = NDTCells.from_points(np.column_stack((x, np.full_like(x, 0.5))), 1.0)
    vals = np.linalg.eigvalsh(np.linalg.inv(cells.inv_covs[0]))
    assert vals[0] == pytest.approx(max(EIGEN_FLOOR_RATIO * vals[1], EIGEN_FLOOR_M2))
    assert np.all(np.isfinite(cells.inv_covs))


def test_sparse_cells_are_dropped_and_lookups_outside_return_minus_one() -> None:
    pts = np.array([[0.1, 0.1]] * MIN_CELL_POINTS + [[2.5, 2.5]] * (MIN_CELL_POINTS - 1))
    cells = NDTCells.from_points(pts, 1.0)
    assert len(cells) == 1
    got = cells.lookup(np.array([[0.5, 0.5], [2.5, 2.5], [-50.0, 3.0], [99.0, 99.0]]))
    np.testing.assert_array_equal(got, [0, -1, -1, -1])


def test_empty_point_set_gives_no_cells() -> None:
    cells = NDTCells.from_points(np.zeros((0, 2)), 0.5)
    assert len(cells) == 0
    assert (cells.lookup(np.array([[0.0, 0.0]])) == -1).all()


@pytest.mark.parametrize("anchor", [(0.0, 0.0), (0.3, -0.2)])
def test_overlapping_cells_are_the_four_half_shifted_grids(anchor) -> None:
    rng = np.random.default_rng(0)
    pts = rng.uniform(-3, 3, (2000, 2)) + np.array([10.3, -7.1])
    both = OverlappingCells.from_points(pts, 1.0, anchor)
    shifts = ((0.0, 0.0), (0.5, 0.0), (0.0, 0.5), (0.5, 0.5))
    grids = [NDTCells.from_points(pts, 1.0, (anchor[0] + dx, anchor[1] + dy)) for dx, dy in shifts]
    queries = rng.uniform(-4, 4, (500, 2)) + np.array([10.3, -7.1])
    found = both.lookup(queries)
    assert len(both) == sum(len(g) for g in grids)
    for g, grid in enumerate(grids):
        k = grid.lookup(queries)
        hit = k >= 0
        np.testing.assert_array_equal(found[:, g] >= 0, hit)
        np.testing.assert_allclose(both.means[found[hit, g]], grid.means[k[hit]], atol=1e-12)
        np.testing.assert_allclose(both.inv_covs[found[hit, g]], grid.inv_covs[k[hit]], rtol=1e-9)
        np.testing.assert_array_equal(both.counts[found[hit, g]], grid.counts[k[hit]])


def test_overlapping_cells_of_nothing_are_empty() -> None:
    cells = OverlappingCells.from_points(np.zeros((0, 2)), 0.5)
    assert len(cells) == 0
    assert (cells.lookup(np.array([[0.0, 0.0]])) == -1).all()


@pytest.mark.parametrize("build", [NDTCells.from_points, OverlappingCells.from_points])
def test_cells_built_from_points_are_read_only_like_a_maps(build) -> None:
    """Cells never change once made; a map's are read-only views, and a scan's must have the
    same array types so that the compiled scorer is not compiled twice (test_warmup)."""
    cells = build(np.random.default_rng(1).uniform(0, 3, (300, 2)), 1.0)
    for a in (cells.index, cells.means, cells.inv_covs, cells.counts):
        assert not a.flags.writeable
    with pytest.raises(ValueError, match="read-only"):
        cells.means[0, 0] = 1.0


def test_bad_cell_size_is_rejected() -> None:
    with pytest.raises(ValueError, match="cell_size_m"):
        NDTCells.from_points(np.zeros((5, 2)), 0.0)


@pytest.mark.parametrize("build", [NDTCells.from_points, OverlappingCells.from_points])
@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_non_finite_points_are_refused_by_name(build, bad: float) -> None:
    """A NaN or infinite point is a ValueError naming it (OverlappingCells sized its block
    arrays from it and the compiled loop wrote out of bounds: a segmentation fault)."""
    pts = np.array([[0.1, 0.2], [bad, 0.3], [0.4, 0.5]])
    with pytest.raises(ValueError, match=r"points has 1 non-finite row"):
        build(pts, 0.5)


def test_points_just_below_a_cell_border_are_kept() -> None:
    """-127.70000000000002 / 0.1 rounds to -1277 exactly: the grid's first column began at
    -127.7, just above the lowest point, which fell outside every cell and was dropped (here
    with its cell: three points at one spot gave no cell at all)."""
    pts = np.full((MIN_CELL_POINTS, 2), [-127.70000000000002, 0.05])
    cells = NDTCells.from_points(pts, 0.1)
    assert len(cells) == 1 and cells.counts[0] == MIN_CELL_POINTS
    assert (cells.lookup(pts) == 0).all()
    rng = np.random.default_rng(5)
    for size in (0.1, 0.3, 0.7):
        for _ in range(300):  # lowest points on or beside a border of the lattice
            x = np.nextafter(rng.integers(-3000, 3000) * size, rng.choice([-np.inf, np.inf]))
            low = np.array([[x, 0.0], [x + 0.25 * size, 0.1 * size], [x, 0.2 * size]])
            got = NDTCells.from_points(low, size)
            assert (got.spec.contains(got.spec.world_to_cell(low))).all(), (size, x)


def _by_location(cells: NDTCells | OverlappingCells, anchor: np.ndarray, step_m: float):
    """(lattice (row, col) of each cell or block from the anchor, its count, its mean), sorted."""
    corner = (
        (cells.spec.origin_y_m, cells.spec.origin_x_m)
        if isinstance(cells, NDTCells)
        else (cells.origin_y_m, cells.origin_x_m)
    )
    start = np.round((np.array(corner) - anchor[::-1]) / step_m).astype(np.int64)
    rc = np.argwhere(cells.index >= 0)
    k = cells.index[rc[:, 0], rc[:, 1]]
    rc += start
    order = np.lexsort((rc[:, 1], rc[:, 0]))
    return rc[order], cells.counts[k[order]], cells.means[k[order]]


@pytest.mark.parametrize(
    ("resolution_m", "kind", "cell_size_m"),
    [(0.1, GridOverlappingCells, 0.3), (0.04, GridNDTCells, 0.3), (0.02, GridNDTCells, 0.15)],
)
def test_blocks_kept_current_equal_blocks_built_anew_when_borders_cross_cell_centres(
    resolution_m: float, kind: type, cell_size_m: float
) -> None:
    """Where a lattice line runs through fine cell centres (half-cells of 1.5 fine cells), the
    refresh binned each centre from the corner of whichever box it recomputed, so rounding put
    one on either side of the line: a refresh counted it in a block another box had counted it
    in already, or in a block its flip had not marked dirty."""
    rng = np.random.default_rng(11)
    grid = OccupancyGrid(OccupancyParams(resolution_m, p_hit=0.7, p_miss=0.3),
                         initial_capacity_cells=4)
    kept = kind(grid, cell_size_m)
    for _ in range(12):
        centre = rng.uniform(-4.0, 4.0, 2)
        a = np.linspace(-math.pi, math.pi, 90, endpoint=False)
        d = np.column_stack((np.cos(a), np.sin(a)))
        walls = centre + d * (rng.uniform(0.5, 3.0) / np.abs(d).max(axis=1))[:, None]
        kept.mark_dirty(grid.insert_scan(walls, centre).occupied_cells)
        kept.cells()
    step = cell_size_m if kind is GridNDTCells else 0.5 * cell_size_m
    got = _by_location(kept.cells(), np.zeros(2), step)
    want = _by_location(kind(grid, cell_size_m).cells(), np.zeros(2), step)
    np.testing.assert_array_equal(got[0], want[0])
    np.testing.assert_array_equal(got[1], want[1])
    np.testing.assert_allclose(got[2], want[2], rtol=0, atol=1e-9)
