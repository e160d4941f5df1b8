"""Matching views: incremental refresh must equal a rebuild from scratch, and stay local."""

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scanflow.maps import pyramid
from scanflow.maps.field import LikelihoodField
from scanflow.maps.grid import CellBox
from scanflow.maps.matching_map import MatchingMap
from scanflow.maps.occupancy import OccupancyGrid, OccupancyParams


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


def reference_field(grid: OccupancyGrid, level: int, sigma_m: float, cutoff_sigmas: float):
    """The level's field computed from scratch from the grid's occupied mask."""
    factor = 2**level
    extent = grid.extent
    coarse = extent.coarsened(factor)
    fine = coarse.refined(factor)
    occupied = np.zeros(fine.shape, dtype=bool)
    occupied[extent.slices_in(fine)] = grid.occupied_mask()
    pooled = occupied.reshape(coarse.shape[0], factor, coarse.shape[1], factor).any(axis=(1, 3))
    sigma = sigma_m * factor
    return LikelihoodField.from_occupied(
        grid.spec_of(coarse, factor), pooled, sigma, cutoff_sigmas * sigma
    )


def assert_views_match_scratch(world: MatchingMap, levels=3):
    for level in range(levels):
        got = world.likelihood_field(level)
        want = reference_field(world.grid, level, world.sigma_m, world.cutoff_sigmas)
        assert got.spec == want.spec
        np.testing.assert_allclose(got.values, want.values, rtol=0, atol=1e-12)


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
    assert_views_match_scratch(world)


def test_refresh_touches_only_the_neighbourhood_of_the_change(monkeypatch):
    world = MatchingMap(OccupancyGrid(initial_capacity_cells=1200))
    for x in np.arange(-20.0, 21.0, 2.0):
        world.update(room_scan((x, 0.0), 3.0, beams=90), (x, 0.0))
    world.likelihood_field(0)
    shapes = []
    real = pyramid.field_values
    monkeypatch.setattr(
        pyramid, "field_values", lambda occ, *a: shapes.append(occ.shape) or real(occ, *a)
    )
    # A new obstacle 0.5 m in front of the sensor: a small change in a big map.
    result = world.update([[0.5, 0.0]], (0.0, 0.0))
    world.likelihood_field(0)
    margin = math.ceil(world.cutoff_sigmas * world.sigma_m / world.resolution_m) + 1
    assert result.occupied_changed is not None
    rows, cols = result.occupied_changed.expanded(2 * margin).shape
    assert shapes == [(rows, cols)]
    assert rows * cols < world.grid.spec.rows * world.grid.spec.cols / 50
    assert_views_match_scratch(world, levels=1)


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
    world.update([[1.0, 1.0], [1.02, 1.0], [1.0, 1.02]], (0.0, 0.0))
    assert world.ndt_cells(0.5) is not cells
    assert world.nbytes > world.grid.nbytes
