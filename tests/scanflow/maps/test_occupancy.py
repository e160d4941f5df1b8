"""Occupancy grid: beam updates (bit for bit the bounding-box masks they replaced), clamping,
growth that keeps content in place, bad input."""

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scanflow.maps.grid import CellBox
from scanflow.maps.occupancy import (
    OccupancyGrid,
    OccupancyParams,
    RayBatch,
    ScanRays,
)


def log_odds_at(grid: OccupancyGrid, xy) -> np.ndarray:
    """Log-odds at world points (0 outside the extent)."""
    cells = grid.spec.world_to_cell(np.asarray(xy, dtype=float))
    inside = grid.spec.contains(cells)
    out = np.zeros(len(cells))
    out[inside] = grid.log_odds[cells[inside, 0], cells[inside, 1]]
    return out


def ring(center, radius_m, beams=90):
    a = np.linspace(-math.pi, math.pi, beams, endpoint=False)
    return np.column_stack((center[0] + radius_m * np.cos(a), center[1] + radius_m * np.sin(a)))


def test_beam_clears_free_space_and_marks_its_end():
    params = OccupancyParams()
    grid = OccupancyGrid(params)
    result = grid.insert_scan([[1.025, 0.025]], (0.025, 0.025))
    assert result.touched == CellBox(0, 0, 1, 21)
    assert result.occupied_changed == CellBox(0, 20, 1, 21)
    assert result.occupied_cells.tolist() == result.means_cells.tolist() == [[0, 20]]
    assert grid.spec.shape == (1, 21)
    np.testing.assert_allclose(grid.log_odds[0, :20], params.miss_log_odds, rtol=1e-6)
    assert grid.log_odds[0, 20] == pytest.approx(params.hit_log_odds, rel=1e-6)
    assert grid.occupied_mask().sum() == 1 and grid.occupied_mask()[0, 20]
    assert grid.to_int8()[0, 20] == round(100 * params.p_hit)
    assert grid.to_int8()[0, 0] == round(100 * params.p_miss)
    assert grid.revision == 1


def test_unobserved_cells_are_unknown():
    grid = OccupancyGrid()
    grid.insert_scan([[1.0, 1.0]], (0.0, 0.0))
    data = grid.to_int8()
    probability = grid.probability()
    assert (data == -1).sum() == (~grid.observed).sum() > 0
    np.testing.assert_array_equal(probability[~grid.observed], 0.5)


def test_log_odds_clamp_at_both_ends():
    params = OccupancyParams(log_odds_min=-1.0, log_odds_max=2.0)
    grid = OccupancyGrid(params)
    for _ in range(20):
        grid.insert_scan([[2.0, 0.01]], (0.01, 0.01))
    assert grid.log_odds.max() == pytest.approx(2.0)
    assert grid.log_odds.min() == pytest.approx(-1.0)


def test_a_cell_hit_in_a_scan_is_not_also_cleared_by_it():
    grid = OccupancyGrid()
    # The first beam ends in a cell that the second beam passes through.
    grid.insert_scan([[0.525, 0.025], [2.025, 0.025]], (0.025, 0.025))
    assert grid.log_odds[0, 10] == pytest.approx(grid.params.hit_log_odds, rel=1e-6)


def test_no_return_beams_clear_only_up_to_the_configured_distance():
    grid = OccupancyGrid(OccupancyParams(no_return_clear_m=2.0))
    grid.insert_scan(np.empty((0, 2)), (0.025, 0.025), no_return_endpoints=[[20.025, 0.025]])
    assert not grid.occupied_mask().any()
    assert grid.spec.shape == (1, 41)  # cells 0..40: the last one holds the point at 2 m
    assert (grid.log_odds < 0).all()


def test_repeated_scan_changes_no_occupancy():
    grid = OccupancyGrid()
    scan = ring((0.0, 0.0), 3.0)
    grid.insert_scan(scan, (0.0, 0.0))
    second = grid.insert_scan(scan, (0.0, 0.0))
    assert second.touched is not None
    assert second.occupied_changed is None


def test_growth_in_all_four_directions_keeps_content_in_place():
    grid = OccupancyGrid(initial_capacity_cells=8)
    first = ring((0.0, 0.0), 2.0)
    grid.insert_scan(first, (0.0, 0.0))
    probe = grid.spec.cell_centers(np.argwhere(grid.observed))
    before = log_odds_at(grid, probe)
    assert np.count_nonzero(before) == len(probe) > 100
    for far in ((40.0, 0.0), (-40.0, 0.0), (0.0, 40.0), (0.0, -40.0)):
        generation = grid.storage_generation
        grid.insert_scan(ring(far, 1.0), far)
        assert grid.storage_generation > generation
        np.testing.assert_array_equal(log_odds_at(grid, probe), before)
    assert grid.spec.width_m > 80 and grid.spec.height_m > 80


def test_growth_is_amortised():
    grid = OccupancyGrid(initial_capacity_cells=16)
    for i in range(200):
        x = 0.25 * i
        grid.insert_scan(ring((x, 0.0), 1.0, beams=16), (x, 0.0))
    # ~50 m of travel at 5 cm is 1000 columns: growing by half reallocates ~log1.5(1000/16)
    # times, and the storage stays within 1.5x of the extent along the axis that grew.
    assert grid.storage_generation <= 12
    assert grid.storage_box.shape[1] <= 1.5 * grid.extent.shape[1] + 1
    assert grid.storage_box.shape[0] == grid.extent.shape[0]  # the other axis did not grow


@settings(max_examples=25, deadline=None)
@given(
    scans=st.lists(
        st.tuples(
            st.floats(-5, 5), st.floats(-5, 5), st.floats(0.2, 4.0), st.integers(1, 40)
        ),
        min_size=1,
        max_size=6,
    )
)
def test_small_initial_capacity_gives_the_same_map_as_a_large_one(scans):
    """Growth (many reallocations) must be invisible in the content."""
    small = OccupancyGrid(initial_capacity_cells=1)
    large = OccupancyGrid(initial_capacity_cells=1000)
    for x, y, radius, beams in scans:
        for grid in (small, large):
            grid.insert_scan(ring((x, y), radius, beams), (x, y))
    assert small.extent == large.extent
    np.testing.assert_array_equal(small.log_odds, large.log_odds)
    np.testing.assert_array_equal(small.observed, large.observed)


def occupancy_and_sums(grid: OccupancyGrid, box: CellBox) -> tuple[np.ndarray, np.ndarray]:
    """Occupied mask and hit sums over a lattice box (empty outside the extent)."""
    occupied = grid.occupied_in(box)
    sums = np.zeros((3, *box.shape), dtype=np.float32)
    if grid.extent is not None:
        inner = box.intersection(grid.extent)
        sums[(slice(None), *inner.slices_in(box))] = grid.hit_sums[
            (slice(None), *inner.slices_in(grid.extent))
        ]
    return occupied, sums


@settings(max_examples=25, deadline=None)
@given(
    scans=st.lists(
        st.tuples(st.floats(-3, 3), st.floats(-3, 3), st.floats(0.2, 3.0), st.integers(1, 60)),
        min_size=1,
        max_size=6,
    )
)
def test_insert_reports_exactly_the_cells_that_changed(scans):
    """`occupied_cells` are the cells whose occupied mask flipped (both ways), `means_cells`
    the cells occupied after the scan whose hit sums changed; the boxes are theirs."""
    grid = OccupancyGrid(OccupancyParams(p_hit=0.7, p_miss=0.3), initial_capacity_cells=4)
    area = CellBox(-200, -200, 200, 200)
    for x, y, radius, beams in scans:
        occupied_before, sums_before = occupancy_and_sums(grid, area)
        result = grid.insert_scan(ring((x, y), radius, beams), (x, y))
        occupied_after, sums_after = occupancy_and_sums(grid, area)
        corner = np.array([area.row0, area.col0])
        flipped = np.argwhere(occupied_before != occupied_after) + corner
        np.testing.assert_array_equal(np.unique(result.occupied_cells, axis=0), flipped)
        moved = occupied_after & (sums_before != sums_after).any(axis=0)
        np.testing.assert_array_equal(
            np.unique(result.means_cells, axis=0), np.argwhere(moved) + corner
        )
        cells = result.occupied_cells
        assert result.occupied_changed == (CellBox.around(cells) if len(cells) else None)


@settings(max_examples=30, deadline=None)
@given(
    boxes=st.lists(
        st.tuples(
            st.integers(-80, 80), st.integers(-80, 80), st.integers(0, 50), st.integers(0, 50)
        ),
        max_size=6,
    ),
    factor=st.sampled_from([1, 2, 4]),
    shift=st.tuples(st.integers(-5, 5), st.integers(-5, 5)),
)
def test_many_boxes_read_like_one_at_a_time(boxes, factor, shift):
    """occupied_in_boxes: each box's window is occupied_in of that box (also past the storage);
    occupied_hit_means in another box's frame: the same points, shifted by the corners;
    occupied_hit_means_in: those of each box, one after the other."""
    grid = OccupancyGrid(initial_capacity_cells=4)
    grid.insert_scan(ring((0.3, -0.2), 2.0, beams=120), (0.3, -0.2))
    grid.insert_scan(ring((1.0, 0.5), 1.2, beams=60), (1.0, 0.5))
    b = np.array([(r, c, r + h, c + w) for r, c, h, w in boxes], dtype=np.int64).reshape(-1, 4)
    flat, starts = grid.occupied_in_boxes(b)
    assert len(starts) == len(b) + 1 and starts[-1] == len(flat)
    frame = CellBox(*shift, *shift)
    coarse = [CellBox(*row).coarsened(factor) for row in b.tolist()]
    np.testing.assert_array_equal(
        grid.occupied_hit_means_in(
            np.array([[c.row0, c.col0, c.row1, c.col1] for c in coarse]).reshape(-1, 4),
            factor,
            frame,
        ),
        np.concatenate(
            [np.zeros((0, 2))] + [grid.occupied_hit_means(c, factor, frame) for c in coarse]
        ),
    )
    for k, row in enumerate(b.tolist()):
        box = CellBox(*row)
        window = flat[starts[k] : starts[k + 1]].reshape(box.shape)
        np.testing.assert_array_equal(window, grid.occupied_in(box))
        coarse = box.coarsened(factor)
        frame = coarse.shifted(*shift)
        np.testing.assert_allclose(
            grid.occupied_hit_means(coarse, factor, frame=frame),
            grid.occupied_hit_means(coarse, factor) - np.array(shift),
            rtol=0,
            atol=1e-12,
        )


def test_bad_input_raises_and_leaves_the_grid_unchanged():
    grid = OccupancyGrid()
    grid.insert_scan(ring((0.0, 0.0), 2.0), (0.0, 0.0))
    before = grid.log_odds.copy()
    with pytest.raises(ValueError, match="points_world"):
        grid.insert_scan([[1.0, np.nan]], (0.0, 0.0))
    with pytest.raises(ValueError, match="max_range_m"):
        grid.insert_scan([[1e6, 0.0]], (0.0, 0.0))
    with pytest.raises(ValueError, match="sensor_origin"):
        grid.insert_scan([[1.0, 0.0]], (np.inf, 0.0))
    with pytest.raises(ValueError, match=r"shape \(N, 2\)"):
        grid.insert_scan(np.zeros((3, 3)), (0.0, 0.0))
    assert grid.revision == 1
    np.testing.assert_array_equal(grid.log_odds, before)


def grid_state(grid: OccupancyGrid) -> tuple:
    """Everything a map holds: extent, revision, log-odds bits, observed cells, hit sums."""
    return (grid.extent, grid.revision, grid.log_odds.tobytes(), grid.observed.tobytes(),
            grid.hit_sums.tobytes())


@settings(max_examples=60, deadline=None)
@given(
    scans=st.lists(
        st.tuples(
            st.floats(-4, 4), st.floats(-4, 4), st.floats(0.05, 3.0), st.integers(0, 50),
            st.integers(0, 8), st.floats(0.1, 12.0),
        ),
        max_size=8,
    ),
    p_hit=st.floats(0.55, 0.95),
)
def test_scans_inserted_together_give_the_map_of_one_at_a_time_bit_for_bit(scans, p_hit):
    """Rings of hits (repeated, so cells saturate their clamps and hit counts), no-return
    beams of any length (clipped or not), empty scans, on a grid that already holds a map."""
    params = OccupancyParams(p_hit=p_hit, log_odds_max=1.0, no_return_clear_m=2.0)
    one, batch = OccupancyGrid(params, initial_capacity_cells=2), OccupancyGrid(params)
    first = ring((0.3, -0.2), 1.5, 30)
    for grid in (one, batch):
        grid.insert_scan(first, (0.3, -0.2))
    rays = []
    for x, y, radius, beams, n_misses, miss_m in scans:
        angles = np.linspace(0.0, 2.0 * math.pi, n_misses, endpoint=False) + 0.3
        misses = np.column_stack((x + miss_m * np.cos(angles), y + miss_m * np.sin(angles)))
        hits = np.repeat(ring((x, y), radius, beams), 3, axis=0) if beams else np.zeros((0, 2))
        rays.append(ScanRays((x, y), hits, misses if n_misses else None))
        one.insert_scan(hits, (x, y), misses if n_misses else None)
    box = batch.insert_scans(RayBatch.of(rays))
    assert grid_state(batch) == grid_state(one)
    touched = [r for r in rays if len(r.hits) or r.misses is not None]
    assert (box is None) == (not touched)


def test_scans_inserted_together_raise_naming_the_scan_and_change_nothing():
    grid = OccupancyGrid()
    grid.insert_scan(ring((0.0, 0.0), 2.0), (0.0, 0.0))
    before = grid_state(grid)
    good = ScanRays((0.0, 0.0), ring((0.0, 0.0), 1.0))
    cases = [
        ([good, ScanRays((0.0, 0.0), [[1.0, 2.0], [1.0, np.nan]])],
         r"scans\[1\].hits row 1 \[ 1. nan\] is not finite"),
        ([good, good, ScanRays((0.0, 0.0), [[1e6, 0.0]])],
         r"scans\[2\].hits row 0 .*: range 1000000.000 m exceeds max_range_m"),
        ([good, ScanRays((0.0, 0.0), np.zeros((0, 2)), [[1.0, 0.0], [np.inf, 0.0]])],
         r"scans\[1\].misses row 1 \[inf  0.\] is not finite"),
        ([ScanRays((np.inf, 0.0), [[1.0, 0.0]])], r"scans\[0\].origin \[inf  0.\] is not"),
    ]
    for scans, message in cases:
        with pytest.raises(ValueError, match=message):
            grid.insert_scans(RayBatch.of(scans))
    with pytest.raises(ValueError, match=r"scans\[1\].misses must have shape \(N, 2\)"):
        RayBatch.of([good, ScanRays((0.0, 0.0), [[1.0, 0.0]], np.zeros((2, 3)))])
    with pytest.raises(ValueError, match=r"scans\[0\].origin must have shape \(2,\)"):
        RayBatch.of([ScanRays((0.0, 0.0, 1.0), [[1.0, 0.0]])])
    with pytest.raises(ValueError, match=r"hit_starts must rise from 0 to 2 in 2 steps"):
        RayBatch(np.zeros((1, 2)), np.ones((2, 2)), [0, 1], np.zeros((0, 2)), [0, 0])
    assert grid_state(grid) == before
    assert grid.insert_scans(RayBatch.of([])) is None
    assert grid.insert_scans(RayBatch.of([ScanRays((5.0, 5.0), np.zeros((0, 2)))])) is None
    assert grid_state(grid) == before


def test_views_are_read_only():
    grid = OccupancyGrid()
    grid.insert_scan([[1.0, 0.0]], (0.0, 0.0))
    with pytest.raises(ValueError):
        grid.log_odds[0, 0] = 1.0


def test_empty_grid():
    grid = OccupancyGrid()
    assert grid.is_empty and grid.spec.shape == (0, 0)
    assert grid.insert_scan(np.empty((0, 2)), (0.0, 0.0)).touched is None
    assert grid.to_int8().shape == (0, 0)


@pytest.mark.parametrize(
    ("field", "kwargs"),
    [
        ("p_hit", {"p_hit": 0.4}),
        ("p_miss", {"p_miss": 0.6}),
        ("log_odds_min", {"log_odds_min": 1.0}),
        ("resolution_m", {"resolution_m": 0.0}),
        ("no_return_clear_m", {"no_return_clear_m": -1.0}),
    ],
)
def test_params_validation_names_the_field(field, kwargs):
    with pytest.raises(ValueError, match=field):
        OccupancyParams(**kwargs)


def test_from_int8_reads_ros_convention():
    data = np.array([[-1, 0, 100], [50, 65, 66]], dtype=np.int8)
    grid = OccupancyGrid.from_int8(data, -1.0, 2.0)
    assert grid.spec.origin_x_m == -1.0 and grid.spec.origin_y_m == 2.0
    np.testing.assert_array_equal(grid.observed, data >= 0)
    np.testing.assert_array_equal(grid.occupied_mask(), data > 65)
    with pytest.raises(ValueError, match=r"-1 or 0\.\.100"):
        OccupancyGrid.from_int8(np.array([[101]]), 0.0, 0.0)


def test_hit_sums_hold_the_mean_endpoint_inside_each_cell():
    grid = OccupancyGrid(OccupancyParams(resolution_m=0.1))
    hits = np.array([[1.02, 0.53], [1.04, 0.57], [2.55, 0.55]])
    grid.insert_scan(hits, (0.05, 0.55))
    cells = grid.world_to_cells(hits) - [grid.extent.row0, grid.extent.col0]
    sums = grid.hit_sums
    r, c = cells[0]
    assert sums[2, r, c] == 2
    np.testing.assert_allclose(sums[:2, r, c] / 2, [0.3, 0.5], atol=2e-3)  # 1/512 cell
    r, c = cells[2]
    np.testing.assert_allclose(sums[:, r, c], [0.5, 0.5, 1.0], atol=2e-3)
    assert sums[2].sum() == 3


def test_hit_sums_survive_growth_and_stay_bounded():
    grid = OccupancyGrid(initial_capacity_cells=4)
    for _ in range(130):
        grid.insert_scan([[0.512, 0.033], [0.512, 0.033]], (0.0, 0.0))
    result = grid.insert_scan([[-3.0, 4.0]], (0.0, 0.0))  # grows the storage
    assert len(result.means_cells)
    cell = grid.world_to_cells(np.array([[0.512, 0.033]]))[0]
    r, c = cell - [grid.extent.row0, grid.extent.col0]
    x, y, n = grid.hit_sums[:, r, c]
    assert 127 <= n <= 255  # 260 hits: halved once on the way
    np.testing.assert_allclose([x / n, y / n], [0.24, 0.66], atol=2e-3)


def test_from_arrays_checks_hit_sums():
    box = CellBox(0, 0, 2, 3)
    lo, obs = np.zeros((2, 3)), np.ones((2, 3), dtype=bool)
    assert not OccupancyGrid.from_arrays(lo, obs, box, 0.0, 0.0).hit_sums.any()
    with pytest.raises(ValueError, match="hit_sums must have shape"):
        OccupancyGrid.from_arrays(lo, obs, box, 0.0, 0.0, hit_sums=np.zeros((3, 3, 2)))
    with pytest.raises(ValueError, match="hit_sums must be >= 0"):
        OccupancyGrid.from_arrays(lo, obs, box, 0.0, 0.0, hit_sums=-np.ones((3, 2, 3)))
