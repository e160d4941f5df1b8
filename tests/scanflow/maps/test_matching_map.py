"""Matching views: incremental refresh must equal a rebuild from scratch, and stay local."""

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scanflow.geometry import Pose2D
from scanflow.maps import maxpool
from scanflow.maps.field import LikelihoodField
from scanflow.maps.grid import CellBox, tile_boxes
from scanflow.maps.matching_map import MatchingMap
from scanflow.maps.maxpool import MaxPoolStack
from scanflow.maps.ndt_cells import NDTCells, OverlappingCells
from scanflow.maps.ndt_moments import regularised_inverse
from scanflow.maps.occupancy import OccupancyGrid, OccupancyParams
from scanflow.maps.pyramid import TILE_CELLS
from scanflow.matching import MatchStatus, match
from scipy.spatial import cKDTree


def room_scan(center, half_size_m=3.0, beams=180, rng=None):
    """Endpoints of beams from `center` hitting an axis-aligned square room around it."""
    a = np.linspace(-math.pi, math.pi, beams, endpoint=False)
    d = np.column_stack((np.cos(a), np.sin(a)))
    with np.errstate(divide="ignore"):
        t = np.min(half_size_m / np.abs(d), axis=1)
    points = np.asarray(center) + d * t[:, None]
    if rng is not None:
        points += rng.normal(0.0, 0.01, points.shape)
    return points


ROOM_LO, ROOM_HI = np.array([-3.0, -2.01]), np.array([3.01, 2.01])


def half_room_scan(pose: Pose2D, beams: int = 181) -> np.ndarray:
    """Sensor-frame endpoints of a 180-degree scan (facing the pose's +x) from inside the room
    ROOM_LO..ROOM_HI: from (0, 0, 0) every wall it sees lies on the border of its own map."""
    a = pose.theta + np.linspace(-math.pi / 2, math.pi / 2, beams)
    d = np.column_stack((np.cos(a), np.sin(a)))
    origin = np.array([pose.x, pose.y])
    d_safe = np.where(np.abs(d) < 1e-12, 1e-12, d)  # axis-parallel beams: the far wall only
    t = np.min(np.where(d_safe > 0, ROOM_HI - origin, ROOM_LO - origin) / d_safe, axis=1)
    return pose.inverse().transform_points(origin + d * t[:, None])


def reference_field(grid: OccupancyGrid, level: int, sigma_m: float, cutoff_sigmas: float):
    """The level's field computed from scratch, point by point: exp(-d^2 / 2 sigma^2) with d to
    the nearest occupied coarse cell's mean hit point (a hit-less occupied cell: its centre),
    over the extent padded by the cut-off (ceil(cut-off / cell) + 1 cells)."""
    factor = 2**level
    sigma = sigma_m * factor
    margin = math.ceil(cutoff_sigmas * sigma / (grid.resolution_m * factor)) + 1
    coarse = grid.extent.coarsened(factor).expanded(margin)
    spec = grid.spec_of(coarse, factor)
    occupied = grid.occupied_mask()
    sums = grid.hit_sums.astype(np.float64)
    rows, cols = np.nonzero(occupied)
    count = sums[2, rows, cols]
    bare = count == 0
    frac_x = np.where(bare, 0.5, sums[0, rows, cols] / np.maximum(count, 1))
    frac_y = np.where(bare, 0.5, sums[1, rows, cols] / np.maximum(count, 1))
    weight = np.where(bare, 1.0, count)
    world = grid.spec.cell_centers(np.column_stack((rows, cols)))
    x = world[:, 0] - 0.5 * grid.resolution_m + frac_x * grid.resolution_m
    y = world[:, 1] - 0.5 * grid.resolution_m + frac_y * grid.resolution_m
    # Group the fine hits by coarse cell and weight by their counts.
    key = spec.world_to_cell(world)
    groups, inverse = np.unique(key, axis=0, return_inverse=True)
    inverse = inverse.reshape(-1)
    total = np.bincount(inverse, weight)
    mx = np.bincount(inverse, weight * x) / total
    my = np.bincount(inverse, weight * y) / total
    centres = spec.cell_centers(np.argwhere(np.ones(spec.shape, dtype=bool)))
    d, _ = cKDTree(np.column_stack((mx, my))).query(centres)
    values = np.where(d <= cutoff_sigmas * sigma, np.exp(-0.5 * (d / sigma) ** 2), 0.0)
    assert len(groups) == len(mx)
    return LikelihoodField(spec, values.reshape(spec.shape), sigma)


def assert_views_match_scratch(world: MatchingMap, levels=3, ulps=0):
    """Every level equals the point-by-point reference (to float32 precision) and a field built
    from scratch by a new map on the same grid: exactly, or within `ulps` float32 ulps (means
    are rounded in float64 relative to the corner of whichever box is computed, which can move
    a value across a float32 rounding boundary; on real logs no value differs)."""
    fresh = MatchingMap(world.grid, cutoff_sigmas=world.cutoff_sigmas)
    for level in range(levels):
        got = world.likelihood_field(level)
        want = reference_field(world.grid, level, world.sigma_m, world.cutoff_sigmas)
        assert got.spec == want.spec
        np.testing.assert_allclose(got.values, want.values, rtol=0, atol=1e-6)
        rebuilt = fresh.likelihood_field(level)
        assert rebuilt.spec == got.spec
        np.testing.assert_array_max_ulp(got.values, rebuilt.values, maxulp=ulps)


def test_empty_map():
    world = MatchingMap()
    assert world.is_empty
    field = world.likelihood_field()
    assert field.values.shape == (0, 0)
    value, grad = field.sample(np.array([[0.0, 0.0]]))
    assert value[0] == 0.0 and not grad.any()
    assert world.occupied_points().shape == (0, 2)


def test_free_space_only_is_still_empty():
    world = MatchingMap()
    world.update(np.empty((0, 2)), (0.0, 0.0), no_return_endpoints=[[3.0, 0.0]])
    assert world.is_empty


def test_incremental_views_equal_a_rebuild_after_many_updates():
    rng = np.random.default_rng(7)
    world = MatchingMap(OccupancyGrid(initial_capacity_cells=16))
    for i in range(40):
        center = (0.3 * i + rng.normal(0, 0.05), 2.0 * math.sin(0.2 * i))
        world.update(room_scan(center, 2.0 + 0.02 * i, rng=rng), center)
        if i % 7 == 0:  # views read in between: refreshes interleave with growth
            world.likelihood_pyramid(3)
    assert not world.is_empty
    assert world.grid.storage_generation > 1
    assert_views_match_scratch(world)


@settings(max_examples=20, deadline=None)
@given(
    scans=st.lists(
        st.tuples(st.floats(-3, 3), st.floats(-3, 3), st.floats(0.3, 2.5), st.booleans()),
        min_size=1,
        max_size=8,
    )
)
def test_incremental_equals_scratch_property(scans):
    world = MatchingMap(OccupancyGrid(initial_capacity_cells=4))
    for x, y, half, read_views in scans:
        world.update(room_scan((x, y), half, beams=60), (x, y))
        if read_views:
            world.likelihood_field(1)
    assert_views_match_scratch(world, ulps=1)


def corridor_map(tile_cells: int = TILE_CELLS) -> MatchingMap:
    """A 40 m long corridor of rooms mapped at 5 cm (a big map for small changes)."""
    world = MatchingMap(OccupancyGrid(initial_capacity_cells=1200), tile_cells=tile_cells)
    for x in np.arange(-20.0, 21.0, 2.0):
        world.update(room_scan((x, 0.0), 3.0, beams=90), (x, 0.0))
    return world


def record_sources(monkeypatch, world: MatchingMap) -> list:
    """The shapes of the boxes whose obstacles a field refresh reads from now on."""
    shapes = []
    real = world.grid.occupied_hit_means_in
    monkeypatch.setattr(
        world.grid,
        "occupied_hit_means_in",
        lambda boxes, *a: (
            shapes.extend(CellBox(*b).shape for b in boxes.tolist()) or real(boxes, *a)
        ),
    )
    return shapes


def test_refresh_touches_only_the_neighbourhood_of_the_change(monkeypatch):
    world = corridor_map()
    world.likelihood_field(0)
    shapes = record_sources(monkeypatch, world)
    # A new obstacle 0.5 m in front of the sensor: a small change in a big map.
    result = world.update([[0.5, 0.0]], (0.0, 0.0))
    world.likelihood_field(0)
    margin = math.ceil(world.cutoff_sigmas * world.sigma_m / world.resolution_m) + 1
    (tile,) = tile_boxes(result.occupied_cells, TILE_CELLS).tolist()
    assert shapes == [CellBox(*tile).expanded(2 * margin).shape]
    assert CellBox(*tile).contains_box(result.occupied_changed)
    rows, cols = shapes[0]
    assert rows * cols < world.grid.spec.rows * world.grid.spec.cols / 50
    assert_views_match_scratch(world, levels=1)


def test_changes_far_apart_refresh_apart(monkeypatch):
    """Two obstacles 30 m apart in one scan: the refresh reads the obstacles around each (its
    tile and twice the cut-off), not the box spanning both; after a scan of a big room it reads
    a band along the room's walls, a fraction of their bounding box."""
    world = corridor_map()
    world.likelihood_pyramid(3)
    shapes = record_sources(monkeypatch, world)
    result = world.update([[-15.0, 1.0], [15.0, -1.0]], (0.0, 0.0))
    world.likelihood_field(0)
    margin = math.ceil(world.cutoff_sigmas * world.sigma_m / world.resolution_m) + 1
    assert result.occupied_changed.shape[1] > 590  # one box would span the corridor
    tiles = tile_boxes(result.occupied_cells, TILE_CELLS)
    want = sorted(CellBox(*t).expanded(2 * margin).shape for t in tiles.tolist())
    assert sorted(shapes) == want
    assert len(shapes) == 2
    assert_views_match_scratch(world)
    shapes.clear()
    center = (0.7, 30.3)  # a new 16 m square room beside the corridor
    result = world.update(room_scan(center, 8.0, beams=1440), center)
    world.likelihood_field(0)
    read = sum(rows * cols for rows, cols in shapes)
    changed = CellBox.around(np.concatenate((result.occupied_cells, result.means_cells)))
    rows, cols = changed.expanded(2 * margin).shape
    assert read < 0.6 * rows * cols
    assert_views_match_scratch(world)


@settings(max_examples=10, deadline=None)
@given(
    scans=st.lists(
        st.tuples(st.floats(-3, 3), st.floats(-3, 3), st.floats(0.3, 2.5), st.integers(0, 7)),
        min_size=1,
        max_size=6,
    ),
    tile_cells=st.sampled_from([1, 3, 8, 32]),
)
def test_every_tile_size_refreshes_exactly_property(scans, tile_cells):
    """Whatever the tile size, levels read after random scans (some levels skipped, so their
    changes pile up) equal the field from scratch."""
    world = MatchingMap(OccupancyGrid(initial_capacity_cells=4), tile_cells=tile_cells)
    for x, y, half, read in scans:
        world.update(room_scan((x, y), half, beams=60), (x, y))
        for level in range(3):
            if read >> level & 1:
                world.likelihood_field(level)
    assert_views_match_scratch(world, ulps=1)


def test_direct_grid_writes_are_noticed():
    world = MatchingMap()
    world.update(room_scan((0.0, 0.0)), (0.0, 0.0))
    world.likelihood_field(0)
    points_before = world.occupied_points().shape[0]
    world.grid.insert_scan(room_scan((0.5, 0.0), 4.0), (0.5, 0.0))
    assert world.occupied_points().shape[0] > points_before
    assert_views_match_scratch(world)


def test_field_peaks_on_walls_and_vanishes_in_the_open():
    world = MatchingMap()
    world.update(room_scan((0.0, 0.0), 3.0, beams=720), (0.0, 0.0))
    field = world.likelihood_field()
    wall, _ = field.sample(np.array([[3.0, 0.5], [-3.0, -1.0], [0.2, 3.0]]))
    open_space, grad = field.sample(np.array([[0.0, 0.0], [1.0, 1.0]]))
    assert (wall > 0.8).all()
    assert not open_space.any() and not grad.any()
    near, grad = field.sample(np.array([[2.9, 0.0]]))
    assert 0.0 < near[0] < 1.0 and grad[0, 0] > 0  # rises towards the wall at x = 3


def test_pyramid_is_coarse_to_fine():
    world = MatchingMap(OccupancyGrid(OccupancyParams(resolution_m=0.1)))
    world.update(room_scan((0.0, 0.0)), (0.0, 0.0))
    fields = world.likelihood_pyramid(3)
    assert [f.spec.resolution_m for f in fields] == pytest.approx([0.4, 0.2, 0.1])
    assert [f.sigma_m for f in fields] == pytest.approx([0.8, 0.4, 0.2])
    with pytest.raises(ValueError, match="levels"):
        world.likelihood_pyramid(0)


def test_occupied_points_are_occupied_cell_centres():
    world = MatchingMap()
    world.update([[1.025, 0.025], [0.025, 2.025]], (0.025, 0.025))
    np.testing.assert_allclose(
        np.sort(world.occupied_points(), axis=0), [[0.025, 0.025], [1.025, 2.025]]
    )


def test_maxpool_stack_follows_the_field():
    world = MatchingMap()
    world.update(room_scan((0.0, 0.0)), (0.0, 0.0))
    stack = world.maxpool_stack(depth=3)
    field = world.likelihood_field()
    assert stack.depth == 3 and stack.spec == field.spec
    assert world.maxpool_stack(depth=3) is stack
    world.update(room_scan((0.2, 0.0)), (0.2, 0.0))
    assert world.maxpool_stack(depth=3) is not stack


def test_cellbox_rejects_inverted_bounds():
    with pytest.raises(ValueError, match="inverted"):
        CellBox(2, 0, 1, 5)


def test_ndt_cells_follow_occupied_points_and_the_lattice():
    world = MatchingMap()
    world.update(room_scan((0.0, 0.0), 2.0, beams=720), (0.0, 0.0))
    cells = world.ndt_cells(0.5)
    assert len(cells) > 10
    assert cells.counts.sum() <= world.occupied_points().shape[0]
    # Cell corners sit on the lattice anchored at the map anchor (0, 0).
    assert cells.spec.origin_x_m / 0.5 == pytest.approx(round(cells.spec.origin_x_m / 0.5))
    assert world.ndt_cells(0.5) is cells
    world.update(room_scan((0.0, 0.0), 2.0, beams=720), (0.0, 0.0))  # nothing flips
    assert world.ndt_cells(0.5) is cells
    overlapping = world.overlapping_ndt_cells(0.5)
    assert world.overlapping_ndt_cells(0.5) is overlapping
    world.update([[1.0, 1.0], [1.02, 1.0], [1.0, 1.02]], (0.0, 0.0))
    assert world.ndt_cells(0.5) is not cells
    assert world.overlapping_ndt_cells(0.5) is not overlapping
    assert world.nbytes > world.grid.nbytes


def test_field_measures_distances_to_the_mean_hit_point_not_the_cell_centre():
    """A wall at x = 2.0123 (5 cm cells, centres at 2.025): the field at the cell centres near
    it is the Gaussian of the distance to the wall; without hit sums, to the cell centres."""
    y = np.linspace(-1.0, 1.0, 801)
    wall = np.column_stack((np.full_like(y, 2.0123), y))
    world = MatchingMap()
    for _ in range(3):
        world.update(wall, (0.0, 0.0))
    xs = 1.875 + 0.05 * np.arange(8)  # cell centres on both sides of the wall (the map's edge)
    probe = np.column_stack((xs, np.full_like(xs, 0.025)))
    sigma = world.sigma_m
    value, _ = world.likelihood_field(0).sample(probe)
    np.testing.assert_allclose(value, np.exp(-0.5 * ((xs - 2.0123) / sigma) ** 2), atol=2e-3)
    grid = world.grid
    bare = OccupancyGrid.from_arrays(grid.log_odds, grid.observed, grid.extent, 0.0, 0.0)
    centres = MatchingMap(bare)
    value, _ = centres.likelihood_field(0).sample(probe)
    np.testing.assert_allclose(value, np.exp(-0.5 * ((xs - 2.025) / sigma) ** 2), atol=2e-3)


def test_field_extends_past_walls_on_the_border_of_the_map():
    """Walls on the outermost cells of the extent keep their whole field: the field is padded
    by its cut-off, at every level."""
    world = MatchingMap()
    world.update(half_room_scan(Pose2D(0.0, 0.0, 0.0)), (0.0, 0.0))
    assert world.grid.spec.origin_x_m + world.grid.spec.width_m == pytest.approx(3.05)
    for level, field in enumerate(reversed(world.likelihood_pyramid(3))):
        assert field.values.dtype == np.float32
        sigma = world.sigma_m * 2**level
        beyond = np.array([[3.01 + sigma, 0.3], [0.5, 2.01 + sigma], [0.5, -2.01 - sigma]])
        value, grad = field.sample(beyond)
        np.testing.assert_allclose(value, np.exp(-0.5), atol=0.1 * 2**level)
        assert grad[0, 0] < 0 and grad[1, 1] < 0 and grad[2, 1] > 0  # falling away outwards
        far, _ = field.sample(np.array([[3.01 + 4.5 * sigma, 0.3]]))
        assert far[0] == 0.0


def test_gn_localises_a_scan_whose_walls_lie_on_the_map_border():
    world = MatchingMap()
    world.update(half_room_scan(Pose2D(0.0, 0.0, 0.0)), (0.0, 0.0))
    truth = Pose2D(0.15, -0.1, 0.05)
    result = match(half_room_scan(truth), world, Pose2D(0.0, 0.0, 0.0), method="gn")
    assert result.status == MatchStatus.OK, result.message
    assert abs(result.pose.x - truth.x) < 0.02 and abs(result.pose.y - truth.y) < 0.02
    assert abs(result.pose.theta - truth.theta) < 0.01


def test_view_memory_follows_the_extent_not_the_storage():
    """A grid with a large spare capacity: the fields cover the padded extent only."""
    world = MatchingMap(OccupancyGrid(initial_capacity_cells=2000))
    world.update(room_scan((0.0, 0.0), 2.0), (0.0, 0.0))
    fields = world.likelihood_pyramid(3)
    margin = math.ceil(world.cutoff_sigmas * world.sigma_m / world.resolution_m) + 1
    padded = [world.grid.extent.coarsened(2**k).expanded(margin).shape for k in (2, 1, 0)]
    assert [f.values.shape for f in fields] == padded
    assert world.nbytes - world.grid.nbytes == sum(4 * r * c for r, c in padded)  # float32
    assert world.grid.nbytes >= 2000 * 2000 * 10


def assert_maxpool_matches_scratch(world: MatchingMap, depth: int, level: int) -> None:
    """The incrementally kept stack is exactly a rebuild from the level's field."""
    got = world.maxpool_stack(depth, level)
    field = world.likelihood_field(level)
    want = MaxPoolStack.from_values(field.spec, field.values, depth)
    assert got.spec == want.spec and got.pad_cells == want.pad_cells
    np.testing.assert_array_equal(got.levels, want.levels)


def assert_close_matrices(a: np.ndarray, b: np.ndarray, relative: float) -> None:
    """(K, 2, 2) matrices equal within `relative` of each of b's largest entries."""
    scale = np.abs(b).max(axis=(1, 2))
    assert (np.abs(a - b).max(axis=(1, 2)) <= relative * scale).all()


def assert_two_pass_distributions(
    counts: np.ndarray, inv_covs: np.ndarray, points: np.ndarray, k: np.ndarray
) -> None:
    """Cells 0..K-1 hold the counts and (within 1e-12) the regularised inverse covariances of
    the points `k` puts in them (-1: none), computed in two passes (mean first)."""
    inside = k >= 0
    k, p, cells = k[inside], points[inside], len(counts)
    n = np.bincount(k, minlength=cells)
    mean = np.column_stack([np.bincount(k, p[:, i], cells) for i in (0, 1)]) / n[:, None]
    d = p - mean[k]
    cov = np.empty((cells, 2, 2))
    for i, j in ((0, 0), (0, 1), (1, 0), (1, 1)):
        cov[:, i, j] = np.bincount(k, d[:, i] * d[:, j], cells) / (n - 1)
    np.testing.assert_array_equal(n, counts)
    assert_close_matrices(inv_covs, regularised_inverse(cov), 1e-12)


def assert_overlapping_matches_scratch(world: MatchingMap, size: float) -> None:
    """The map's overlapping cells hold, at every block location of the anchored half-cell
    lattice, what `OverlappingCells.from_points` of the occupied centres holds there (numbering
    aside); lookups agree; each of the four grids passes the two-pass check."""
    got = world.overlapping_ndt_cells(size)
    anchor = np.array([world.grid.anchor_x_m, world.grid.anchor_y_m])
    points = world.occupied_points()
    want = OverlappingCells.from_points(points, size, tuple(anchor))
    assert len(got) == len(want) and got.half_size_m == want.half_size_m
    np.testing.assert_array_equal(np.sort(got.index[got.index >= 0]), np.arange(len(got)))

    def blocks(cells: OverlappingCells) -> tuple[np.ndarray, np.ndarray]:
        """(absolute half-cell (row, col) of each block, its number), sorted by location."""
        start = (np.array([cells.origin_y_m, cells.origin_x_m]) - anchor[::-1]) / size * 2
        np.testing.assert_allclose(start, np.round(start), atol=1e-9)
        rc = np.argwhere(cells.index >= 0)
        k = cells.index[rc[:, 0], rc[:, 1]]
        rc += np.round(start).astype(np.int64)
        order = np.lexsort((rc[:, 1], rc[:, 0]))
        return rc[order], k[order]

    rc_got, k_got = blocks(got)
    rc_want, k_want = blocks(want)
    np.testing.assert_array_equal(rc_got, rc_want)
    np.testing.assert_array_equal(got.counts[k_got], want.counts[k_want])
    np.testing.assert_allclose(got.means[k_got], want.means[k_want], rtol=0, atol=1e-12)
    assert_close_matrices(got.inv_covs[k_got], want.inv_covs[k_want], 1e-9)
    rng = np.random.default_rng(0)
    lo, hi = (points.min(axis=0), points.max(axis=0)) if len(points) else (anchor, anchor)
    queries = np.vstack((points, rng.uniform(lo - size, hi + size, (500, 2))))
    found, expected = got.lookup(queries), want.lookup(queries)
    np.testing.assert_array_equal(found >= 0, expected >= 0)
    hit = found >= 0
    np.testing.assert_allclose(got.means[found[hit]], want.means[expected[hit]], atol=1e-12)
    in_grid = got.lookup(points)
    for g in range(4):
        k = in_grid[:, g]
        grid_cells = np.unique(k[k >= 0])
        renumbered = np.where(k >= 0, np.searchsorted(grid_cells, k), -1)
        assert_two_pass_distributions(
            got.counts[grid_cells], got.inv_covs[grid_cells], points, renumbered
        )


def assert_ndt_matches_scratch(world: MatchingMap, size: float) -> None:
    """Same cells, counts and means as binning the occupied centres from scratch (numbering
    aside). Inverse covariances: within 1e-9 of the scratch build's and 1e-12 of a two-pass
    computation per cell (of each matrix's scale)."""
    got = world.ndt_cells(size)
    anchor = (world.grid.anchor_x_m, world.grid.anchor_y_m)
    points = world.occupied_points()
    want = NDTCells.from_points(points, size, anchor)
    assert len(got) == len(want)
    np.testing.assert_array_equal(np.sort(got.index[got.index >= 0]), np.arange(len(got)))
    cells = np.argwhere(want.index >= 0)
    k_want = want.index[cells[:, 0], cells[:, 1]]
    k_got = got.lookup(want.spec.cell_centers(cells))
    assert (k_got >= 0).all()
    np.testing.assert_array_equal(got.counts[k_got], want.counts[k_want])
    np.testing.assert_allclose(got.means[k_got], want.means[k_want], rtol=0, atol=1e-12)

    assert_close_matrices(got.inv_covs[k_got], want.inv_covs[k_want], 1e-9)
    assert_two_pass_distributions(got.counts, got.inv_covs, points, got.lookup(points))
    origin_cells = np.array([got.spec.origin_x_m, got.spec.origin_y_m]) - anchor
    np.testing.assert_allclose(origin_cells / size, np.round(origin_cells / size), atol=1e-9)


@settings(max_examples=25, deadline=None)
@given(
    scans=st.lists(
        st.tuples(
            st.floats(-4, 4),
            st.floats(-4, 4),
            st.floats(0.3, 3.0),
            st.integers(1, 4),  # repeats: walls firm up, and a bigger room clears old ones
            st.integers(0, 15),  # which views to read after the scan (bits)
        ),
        min_size=1,
        max_size=8,
    ),
    anchor=st.tuples(st.floats(-1, 1), st.floats(-1, 1)),
)
def test_stacks_and_ndt_cells_equal_a_rebuild_property(scans, anchor):
    """Scans grow the map in every direction and flip cells both ways; views read at random
    points in between (refreshes interleave with re-layouts) still equal a rebuild with the
    map's lattice anchor. One hit makes a cell occupied and one miss frees it again, so NDT
    cells come and go often."""
    params = OccupancyParams(p_hit=0.7, p_miss=0.3)
    world = MatchingMap(OccupancyGrid(params, *anchor, initial_capacity_cells=4))
    for x, y, half, repeats, read in scans:
        for _ in range(repeats):
            world.update(room_scan((x, y), half, beams=60), (x, y))
        if read & 1:
            world.maxpool_stack(2, 0)
        if read & 2:
            world.maxpool_stack(3, 1)
        if read & 4:
            world.ndt_cells(0.3)
            world.ndt_cells(0.5)
        if read & 8:
            world.overlapping_ndt_cells(0.3)
            world.overlapping_ndt_cells(1.0)
    assert_maxpool_matches_scratch(world, 2, 0)
    assert_maxpool_matches_scratch(world, 3, 1)
    assert_ndt_matches_scratch(world, 0.3)
    assert_ndt_matches_scratch(world, 0.5)
    assert_overlapping_matches_scratch(world, 0.3)
    assert_overlapping_matches_scratch(world, 1.0)


def test_ndt_cells_disappear_when_their_walls_are_cleared():
    world = MatchingMap(OccupancyGrid(initial_capacity_cells=8))
    for _ in range(2):
        world.update(room_scan((0.0, 0.0), 1.0, beams=360), (0.0, 0.0))
    old_wall = np.array([[1.0, 0.3]])
    cells = world.ndt_cells(0.5)
    assert cells.lookup(old_wall)[0] >= 0
    assert (world.overlapping_ndt_cells(0.5).lookup(old_wall) >= 0).all()
    before = len(cells)
    for _ in range(12):  # beams of a bigger room pass through the old walls: they turn free
        world.update(room_scan((0.0, 0.0), 4.0, beams=720), (0.0, 0.0))
    cells = world.ndt_cells(0.5)
    assert cells.lookup(old_wall)[0] == -1
    assert len(cells) > before  # the bigger room's walls, after the old ones were dropped
    assert (world.overlapping_ndt_cells(0.5).lookup(old_wall) == -1).all()
    assert_ndt_matches_scratch(world, 0.5)
    assert_overlapping_matches_scratch(world, 0.5)
    assert_maxpool_matches_scratch(world, 4, 0)


def test_stack_and_ndt_refresh_only_the_changed_neighbourhood(monkeypatch):
    world = corridor_map()
    world.maxpool_stack(4)
    world.ndt_cells(0.5)
    world.overlapping_ndt_cells(0.5)
    pooled, fetched = [], []
    real_pool, real_occupied_in = maxpool._pool, world.grid.occupied_in_boxes
    monkeypatch.setattr(
        maxpool,
        "_pool",
        lambda levels, boxes: (
            pooled.append([CellBox(*b).shape for b in boxes.tolist()]) or real_pool(levels, boxes)
        ),
    )
    monkeypatch.setattr(
        world.grid,
        "occupied_in_boxes",
        lambda boxes: (
            fetched.append([CellBox(*b).shape for b in boxes.tolist()]) or real_occupied_in(boxes)
        ),
    )
    result = world.update([[0.5, 0.0]], (0.0, 0.0))  # a new obstacle in a big map
    world.maxpool_stack(4)
    world.ndt_cells(0.5)
    world.overlapping_ndt_cells(0.5)
    margin = math.ceil(world.cutoff_sigmas * world.sigma_m / world.resolution_m) + 1
    (tile,) = tile_boxes(result.occupied_cells, TILE_CELLS).tolist()
    assert pooled == [[CellBox(*tile).expanded(margin).shape]]
    assert pooled[0][0][0] * pooled[0][0][1] < world.likelihood_field(0).values.size / 50
    # The NDT cells holding the changed cells' centres: one or two 0.5 m cells per axis (plus
    # a fine cell each side); the overlapping ones: one or two 0.25 m half-cells, plus one
    # half-cell each side (the blocks holding them reach that far).
    assert [len(f) for f in fetched] == [1, 1]
    assert max(fetched[0][0]) <= 2 * 10 + 2 and max(fetched[1][0]) <= 4 * 5 + 2
    assert_maxpool_matches_scratch(world, 4, 0)
    assert_ndt_matches_scratch(world, 0.5)
    assert_overlapping_matches_scratch(world, 0.5)
    # Two obstacles 30 m apart: a refresh per obstacle, each as small as the one above.
    pooled.clear()
    fetched.clear()
    world.update([[-15.0, 1.0], [15.0, -1.0]], (0.0, 0.0))
    world.maxpool_stack(4)
    world.ndt_cells(0.5)
    world.overlapping_ndt_cells(0.5)
    assert len(pooled) == 1 and len(pooled[0]) == 2
    assert all(rows * cols <= (TILE_CELLS + 2 * margin) ** 2 for rows, cols in pooled[0])
    assert [len(f) for f in fetched] == [2, 2]  # one box per obstacle, in one call per view
    assert max(max(shape) for f in fetched for shape in f) <= 2 * 10 + 2
    assert_maxpool_matches_scratch(world, 4, 0)
    assert_ndt_matches_scratch(world, 0.5)
    assert_overlapping_matches_scratch(world, 0.5)


class FieldOnly:
    """A map target without its own stack: csm pools the field from scratch."""

    def __init__(self, world: MatchingMap) -> None:
        self.world = world

    def likelihood_field(self, level: int = 0) -> LikelihoodField:
        return self.world.likelihood_field(level)


def test_csm_on_a_map_uses_its_stack_and_finds_what_a_rebuilt_stack_finds(monkeypatch):
    """The map grows scan by scan (half-room scans facing four ways); after each, csm against
    the map's incremental stack returns exactly what exhaustive search and a stack pooled from
    scratch return."""
    world = MatchingMap(OccupancyGrid(initial_capacity_cells=8))
    window = {"linear_m": 0.4, "angular_rad": math.radians(6)}
    used = []
    real = MatchingMap.maxpool_stack
    monkeypatch.setattr(
        MatchingMap, "maxpool_stack", lambda self, *a: used.append(a) or real(self, *a)
    )
    for i, heading in enumerate((0.0, 1.6, 3.1, -1.5)):
        pose = Pose2D(0.2 * i - 0.3, 0.1 * i - 0.2, heading)
        world.update(pose.transform_points(half_room_scan(pose)), (pose.x, pose.y))
        truth = Pose2D(pose.x + 0.1, pose.y - 0.15, heading + 0.05)
        source = half_room_scan(truth)
        fast = match(source, world, pose, method="csm", **window)
        full = match(source, world, pose, method="csm_exhaustive", **window)
        rebuilt = match(source, FieldOnly(world), pose, method="csm", **window)
        assert fast.ok and fast.pose == full.pose == rebuilt.pose
        assert fast.score == full.score == rebuilt.score
        assert math.hypot(fast.pose.x - truth.x, fast.pose.y - truth.y) < 0.05
    assert len(used) == 8  # csm and csm_exhaustive on the map, after each scan


def _all_hit_means_world(grid: OccupancyGrid) -> np.ndarray:
    """Every occupied cell's mean hit point, in world coordinates (the whole map at once)."""
    return grid.spec_of(grid.extent).cell_centers(grid.occupied_hit_means(grid.extent))


@settings(max_examples=25, deadline=None)
@given(st.floats(-2.0, 2.0), st.floats(-1.5, 1.5), st.floats(0.0, 0.5), st.integers(1, 40))
def test_hit_means_near_holds_every_mean_within_the_radius(x, y, radius_m, count):
    """The local target of a fine step: all of the map's mean hits within the radius of some
    query point, each one once, and nothing beyond the tiles around the points."""
    mm = MatchingMap(OccupancyGrid(anchor_x_m=0.013, anchor_y_m=-0.021))
    rng = np.random.default_rng(count)
    for center in ((0.0, 0.0), (0.7, -0.4)):
        mm.update(room_scan(center, rng=rng), center)
    everything = _all_hit_means_world(mm.grid)
    queries = np.array([x, y]) + rng.normal(0.0, 1.0, (count, 2))
    near = mm.hit_means_near(queries, radius_m)
    assert len(np.unique(near, axis=0)) == len(near)
    # Exactly the map's means, a subset of them.
    assert np.all(cKDTree(everything).query(near)[0] < 1e-9)
    wanted = everything[cKDTree(queries).query(everything)[0] <= radius_m]
    if len(wanted):
        assert np.all(cKDTree(near).query(wanted)[0] < 1e-9)
    # A query's tile of 8 cells, grown by ceil(radius / resolution) cells on every side: a
    # square around it, whose far corner lies sqrt(2) (radius + 9 cells) away at most.
    slack_m = math.sqrt(2) * (radius_m + 9 * mm.resolution_m)
    if len(near):
        assert np.all(cKDTree(queries).query(near)[0] <= slack_m)


def test_hit_means_near_of_nothing_is_empty():
    mm = MatchingMap(OccupancyGrid())
    assert mm.hit_means_near(np.zeros((3, 2)), 0.2).shape == (0, 2)
    mm.update(room_scan((0.0, 0.0)), (0.0, 0.0))
    assert mm.hit_means_near(np.zeros((0, 2)), 0.2).shape == (0, 2)
    with pytest.raises(ValueError, match="radius_m"):
        mm.hit_means_near(np.zeros((1, 2)), -1.0)


def test_levels_depths_and_radii_past_any_use_are_refused_by_name() -> None:
    """Unbounded, a level 24 field took 16 s (level 40: minutes), a max-pool stack 13 deep
    asked for 7 GiB, and an infinite radius overflowed (a fuzzing audit); a scalar sensor
    origin was an IndexError."""
    grid = OccupancyGrid(OccupancyParams(resolution_m=0.05))
    grid.insert_scan(room_scan(np.zeros(2)), np.zeros(2))
    m = MatchingMap(grid)
    assert m.likelihood_field(20).spec.resolution_m == pytest.approx(0.05 * 2**20)
    for call, named in (
        (lambda: m.likelihood_field(21), r"level must be in \[0, 20\]"),
        (lambda: m.likelihood_field(-1), r"level must be in \[0, 20\]"),
        (lambda: m.maxpool_stack(13), r"depth must be in \[0, 12\]"),
        (lambda: m.hit_means_near([[0.0, 0.0]], math.inf), "radius_m must be finite"),
        (lambda: grid.insert_scan([[1.0, 2.0]], 0), r"sensor_origin must have shape \(N, 2\)"),
    ):
        with pytest.raises(ValueError, match=named):
            call()
