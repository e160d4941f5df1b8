"""FieldLayer (one pyramid level) against a brute-force field of pooled mean hit points."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from numpy.typing import NDArray
from scanflow.maps.grid import CellBox
from scanflow.maps.occupancy import OccupancyGrid, OccupancyParams
from scanflow.maps.pyramid import FieldLayer

RES_M = 0.05
# Per level: sigma and cut-off in metres scale with the cell size; the cut-off is no whole
# number of cells, so no distance sits exactly on it.
SIGMA_CELLS, CUTOFF_CELLS = 1.87, 6.74


def _layer(grid: OccupancyGrid, factor: int, tile_cells: int = 4) -> FieldLayer:
    res = grid.resolution_m * factor
    return FieldLayer(grid, factor, SIGMA_CELLS * res, CUTOFF_CELLS * res, tile_cells)


def _pooled_means(grid: OccupancyGrid, factor: int) -> NDArray[np.float64]:
    """World (x, y) of the mean hit point of each coarse cell holding an occupied fine cell:
    hits summed over the fine cells it covers (an occupied cell without hits: one at its
    centre), coarse cell (R, C) covering fine rows [R f, R f + f) and cols likewise."""
    extent = grid.extent
    if extent is None:
        return np.zeros((0, 2))
    occupied = grid.observed & (grid.log_odds > grid.params.threshold_log_odds())
    sums = grid.hit_sums.astype(np.float64)
    res = grid.resolution_m
    pooled: dict[tuple[int, int], list[float]] = {}
    for r, c in zip(*np.nonzero(occupied), strict=True):
        sx, sy, n = sums[:, r, c]
        if n == 0:
            sx, sy, n = 0.5, 0.5, 1.0
        row, col = r + extent.row0, c + extent.col0
        x = n * (grid.anchor_x_m + col * res) + sx * res
        y = n * (grid.anchor_y_m + row * res) + sy * res
        acc = pooled.setdefault((math.floor(row / factor), math.floor(col / factor)), [0, 0, 0])
        acc[0] += x
        acc[1] += y
        acc[2] += n
    return np.array([(x / n, y / n) for x, y, n in pooled.values()]).reshape(-1, 2)


def _brute_force(
    grid: OccupancyGrid, factor: int
) -> tuple[float, float, NDArray[np.float64]]:
    """(origin x, origin y, values) of the level's field over the grid's extent on the coarse
    lattice padded by ceil(cut-off / cell) + 1 cells, every cell against every mean."""
    res = grid.resolution_m * factor
    sigma, cutoff = SIGMA_CELLS * res, CUTOFF_CELLS * res
    margin = math.ceil(CUTOFF_CELLS) + 1
    e = grid.extent
    row0, col0 = math.floor(e.row0 / factor) - margin, math.floor(e.col0 / factor) - margin
    row1, col1 = math.ceil(e.row1 / factor) + margin, math.ceil(e.col1 / factor) + margin
    rows, cols = np.mgrid[row0:row1, col0:col1]
    centres = np.stack(
        (grid.anchor_x_m + (cols + 0.5) * res, grid.anchor_y_m + (rows + 0.5) * res), axis=-1
    )
    means = _pooled_means(grid, factor)
    values = np.zeros(rows.shape)
    if len(means):
        d = np.linalg.norm(centres[:, :, None, :] - means[None, None], axis=-1).min(axis=-1)
        values = np.where(d <= cutoff, np.exp(-0.5 * (d / sigma) ** 2), 0.0)
    return grid.anchor_x_m + col0 * res, grid.anchor_y_m + row0 * res, values


def _imported_grid(seed: int, with_hits: bool) -> OccupancyGrid:
    """A grid imported over a box off the origin (negative rows: floor, not truncation), with
    scattered occupied cells, some observed free and some never observed."""
    rng = np.random.default_rng(seed)
    box = CellBox(-13, 5, 18, 34)
    log_odds = rng.choice([-1.0, 0.0, 2.0], size=box.shape, p=[0.5, 0.4, 0.1])
    observed = log_odds != 0.0
    hit_sums = None
    if with_hits:
        counts = rng.integers(0, 4, size=box.shape).astype(np.float64)
        hit_sums = np.stack((rng.uniform(0, 1, box.shape) * counts,
                             rng.uniform(0, 1, box.shape) * counts, counts))
    return OccupancyGrid.from_arrays(log_odds, observed, box, 0.37, -1.21,
                                     OccupancyParams(resolution_m=RES_M), hit_sums=hit_sums)


def _assert_matches_brute_force(layer: FieldLayer, factor: int) -> None:
    field = layer.field()
    x0, y0, want = _brute_force(layer.grid, factor)
    assert field.spec.resolution_m == pytest.approx(RES_M * factor)
    assert (field.spec.origin_x_m, field.spec.origin_y_m) == pytest.approx((x0, y0))
    assert field.values.shape == want.shape and field.values.dtype == np.float32
    np.testing.assert_allclose(field.values, want, rtol=2e-6, atol=2e-7)


@pytest.mark.parametrize("factor", [1, 2, 3, 4, 8])
@pytest.mark.parametrize("with_hits", [False, True])
def test_each_level_is_the_field_of_the_max_pooled_mean_hit_points(
    factor: int, with_hits: bool
) -> None:
    grid = _imported_grid(seed=factor, with_hits=with_hits)
    layer = _layer(grid, factor)
    _assert_matches_brute_force(layer, factor)
    assert layer.field().sigma_m == pytest.approx(SIGMA_CELLS * RES_M * factor)


@pytest.mark.parametrize("factor", [1, 2, 4])
def test_padded_extent_is_the_coarsened_extent_plus_the_cut_off_margin(factor: int) -> None:
    grid = _imported_grid(seed=0, with_hits=False)
    margin = math.ceil(CUTOFF_CELLS) + 1
    e = grid.extent
    want = CellBox(math.floor(e.row0 / factor) - margin, math.floor(e.col0 / factor) - margin,
                   math.ceil(e.row1 / factor) + margin, math.ceil(e.col1 / factor) + margin)
    layer = _layer(grid, factor)
    assert layer.padded_extent() == want
    assert layer.field().spec.shape == want.shape


def test_an_empty_grid_has_an_empty_field_at_the_anchor() -> None:
    grid = OccupancyGrid(OccupancyParams(resolution_m=RES_M), anchor_x_m=1.5, anchor_y_m=-2.0)
    layer = _layer(grid, 2)
    assert layer.padded_extent() is None
    box, values = layer.stored()
    assert box is None and values.shape == (0, 0) and layer.nbytes == 0
    field = layer.field()
    assert field.values.shape == (0, 0) and field.is_empty
    assert (field.spec.origin_x_m, field.spec.origin_y_m) == (1.5, -2.0)
    assert field.spec.resolution_m == pytest.approx(2 * RES_M)


def test_values_are_read_only_and_zero_outside_the_padded_extent() -> None:
    grid = OccupancyGrid(OccupancyParams(resolution_m=RES_M))
    layer = _layer(grid, 2)
    grid.insert_scan([[0.5, 0.2]], [0.0, 0.0])
    layer.field()
    result = grid.insert_scan([[-1.4, 1.1], [-1.3, 1.2]], [0.2, 0.1])  # the extent grows
    layer.mark_dirty(np.concatenate((result.occupied_cells, result.means_cells)))
    field = layer.field()
    assert not field.values.flags.writeable
    box, values = layer.stored()
    assert not values.flags.writeable
    assert layer.nbytes == values.nbytes == 4 * box.shape[0] * box.shape[1]
    padded = layer.padded_extent()
    outside = np.ones(box.shape, dtype=bool)
    outside[padded.slices_in(box)] = False
    assert not values[outside].any()
    np.testing.assert_array_equal(values[padded.slices_in(box)], field.values)


def _scan(rng: np.random.Generator, centre: NDArray[np.float64]) -> NDArray[np.float64]:
    """Endpoints on a ring of walls 0.5-1.5 m around `centre`."""
    angles = rng.uniform(-math.pi, math.pi, 40)
    ranges = rng.uniform(0.5, 1.5) + rng.normal(0.0, 0.02, 40)
    return centre + ranges[:, None] * np.column_stack((np.cos(angles), np.sin(angles)))


@settings(max_examples=12, deadline=None)
@given(
    seed=st.integers(0, 2**16),
    factor=st.sampled_from([1, 2, 4]),
    tile_cells=st.integers(1, 6),
    scans=st.integers(2, 5),
)
def test_refreshing_only_the_dirty_tiles_equals_the_field_from_scratch(
    seed: int, factor: int, tile_cells: int, scans: int
) -> None:
    rng = np.random.default_rng(seed)
    grid = OccupancyGrid(OccupancyParams(resolution_m=RES_M), anchor_x_m=0.013,
                         anchor_y_m=-0.021, initial_capacity_cells=8)
    layer = _layer(grid, factor, tile_cells)
    for _ in range(scans):
        centre = rng.uniform(-2.0, 2.0, 2)
        result = grid.insert_scan(_scan(rng, centre), centre)
        layer.mark_dirty(np.concatenate((result.occupied_cells, result.means_cells)))
        if rng.random() < 0.7:  # some updates are refreshed together, later
            _assert_matches_brute_force(layer, factor)
    _assert_matches_brute_force(layer, factor)
    np.testing.assert_array_equal(layer.field().values, _layer(grid, factor).field().values)


def test_take_changes_covers_every_changed_value_once() -> None:
    rng = np.random.default_rng(7)
    grid = OccupancyGrid(OccupancyParams(resolution_m=RES_M))
    layer = _layer(grid, 2)
    grid.insert_scan(_scan(rng, np.zeros(2)), np.zeros(2))
    layer.field()
    box, _ = layer.stored()
    first = layer.take_changes("pool")
    np.testing.assert_array_equal(first, [[box.row0, box.col0, box.row1, box.col1]])
    assert layer.take_changes("pool").shape == (0, 4)  # nothing changed since
    for step in range(4):
        before_box, before = layer.stored()
        before = before.copy()
        centre = np.array([0.3 * step, -0.2 * step])
        result = grid.insert_scan(_scan(rng, centre), centre)
        layer.mark_dirty(np.concatenate((result.occupied_cells, result.means_cells)))
        layer.field()
        box, after = layer.stored()
        was = np.zeros(box.shape, dtype=np.float32)
        was[before_box.slices_in(box)] = before  # growing changes no value
        changed = np.zeros(box.shape, dtype=np.int64)
        for r0, c0, r1, c1 in layer.take_changes("pool"):
            changed[CellBox(int(r0), int(c0), int(r1), int(c1)).slices_in(box)] += 1
        assert changed.max() <= 1  # disjoint boxes
        assert not (was != after)[changed == 0].any()  # every change inside a box
        assert (was != after).any()  # the scans did change the field
    late = layer.take_changes("late")  # a new consumer gets the whole stored box
    np.testing.assert_array_equal(late, [[box.row0, box.col0, box.row1, box.col1]])


def test_mark_dirty_takes_fine_cells_and_refreshes_their_coarse_tiles() -> None:
    """Changed cells are given on the grid's (fine) lattice, at negative rows and columns too:
    the layer refreshes the tiles of the coarse cells holding them, leaving no stale value."""
    grid = OccupancyGrid(OccupancyParams(resolution_m=RES_M))
    layer = _layer(grid, 4, tile_cells=1)
    grid.insert_scan([[0.6, 0.6], [-0.6, -0.6]], [0.0, 0.0])
    layer.field()
    result = grid.insert_scan([[-0.47, -0.53]], [0.0, 0.0])  # a new wall cell at negative rows
    assert (result.occupied_cells < 0).all()
    layer.mark_dirty(result.occupied_cells)
    _assert_matches_brute_force(layer, 4)


@pytest.mark.parametrize("field", ["factor", "tile_cells"])
def test_bad_factor_or_tile_size_is_refused_by_name(field: str) -> None:
    options = {"factor": 1, "sigma_m": 0.1, "cutoff_m": 0.4, "tile_cells": 4, field: 0}
    with pytest.raises(ValueError, match=f"{field} must be >= 1"):
        FieldLayer(OccupancyGrid(), **options)
