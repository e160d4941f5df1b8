"""The grid's compiled loops: on hand-sized arrays, one update per cell per scan, a hit never
also cleared, the flipped cells reported, hit sums that fade without moving their mean; on
random ones, the update equal bit for bit to the bounding-box masks it replaced."""

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st
from scanflow.maps.occupancy import OccupancyParams
from scanflow.maps.occupancy_kernels import (
    HIT_COUNT_MAX,
    accumulate_hits,
    insert_many,
    occupied_windows,
    update_cells,
)
from scanflow.maps.raycast import ray_length, trace_ray

MISS, HIT, LO_MIN, LO_MAX, THRESHOLD = -0.4, 0.85, -2.0, 3.5, 0.0


def empty(rows: int, cols: int) -> tuple[np.ndarray, np.ndarray]:
    """A never-observed storage of log-odds and observed flags."""
    return np.zeros((rows, cols), dtype=np.float32), np.zeros((rows, cols), dtype=np.bool_)


def cells(*pairs: tuple[int, int]) -> np.ndarray:
    """(n, 2) int64 cell indices."""
    return np.array(pairs, dtype=np.int64).reshape(-1, 2)


def box_of(origin: np.ndarray, *ends: np.ndarray) -> np.ndarray:
    """The scratch box (row0, col0, row1, col1) the kernel expects: origin and ends, exclusive."""
    every = np.vstack([origin[None, :], *ends])
    return np.r_[every.min(axis=0), every.max(axis=0) + 1].astype(np.int64)


def test_a_beam_clears_up_to_its_hit_and_the_hit_alone_is_reported_as_flipped() -> None:
    log_odds, observed = empty(1, 8)
    origin, hits, misses = np.array([0, 0], dtype=np.int64), cells((0, 5)), cells()
    flipped = update_cells(log_odds, observed, box_of(origin, hits), origin, hits, misses,
                           MISS, HIT, LO_MIN, LO_MAX, THRESHOLD)
    np.testing.assert_array_equal(flipped, cells((0, 5)))
    np.testing.assert_allclose(log_odds[0], [MISS] * 5 + [HIT, 0.0, 0.0])
    np.testing.assert_array_equal(observed[0], [True] * 6 + [False] * 2)


def test_a_cell_hit_by_one_beam_is_not_cleared_by_another_passing_through_it() -> None:
    log_odds, observed = empty(1, 8)
    origin, hits = np.array([0, 0], dtype=np.int64), cells((0, 6), (0, 3))
    flipped = update_cells(log_odds, observed, box_of(origin, hits), origin, hits, cells(),
                           MISS, HIT, LO_MIN, LO_MAX, THRESHOLD)
    np.testing.assert_array_equal(flipped, cells((0, 3), (0, 6)))  # sorted, row-major
    assert log_odds[0, 3] == np.float32(HIT)
    assert log_odds[0, 2] == np.float32(MISS)  # two beams cross it: updated once


def test_a_no_return_beam_clears_its_end_cell_too_and_values_stay_clamped() -> None:
    log_odds, observed = empty(1, 4)
    origin, misses = np.array([0, 0], dtype=np.int64), cells((0, 3))
    for _ in range(20):
        flipped = update_cells(log_odds, observed, box_of(origin, misses), origin, cells(),
                               misses, MISS, HIT, LO_MIN, LO_MAX, THRESHOLD)
        assert len(flipped) == 0  # free cells never become occupied
    np.testing.assert_allclose(log_odds[0], [LO_MIN] * 4)


def test_an_occupied_cell_seen_free_again_is_reported_when_it_flips_back() -> None:
    log_odds, observed = empty(1, 6)
    origin = np.array([0, 0], dtype=np.int64)
    update_cells(log_odds, observed, box_of(origin, cells((0, 2))), origin, cells((0, 2)),
                 cells(), MISS, HIT, LO_MIN, LO_MAX, THRESHOLD)
    flips = []
    for _ in range(3):  # 0.85 - 0.4 - 0.4 > 0, then - 0.4 < 0
        far = cells((0, 5))
        flips.append(update_cells(log_odds, observed, box_of(origin, far), origin, far,
                                  cells(), MISS, HIT, LO_MIN, LO_MAX, THRESHOLD))
    assert [f.tolist() for f in flips] == [[[0, 5]], [], [[0, 2]]]


@settings(max_examples=60, deadline=None)
@given(unit=st.integers(0, 255), extra=st.integers(1, 300))
def test_hit_sums_fade_past_the_count_limit_keeping_their_mean(unit: int, extra: int) -> None:
    hit_xy = np.zeros((2, 1, 1), dtype=np.uint16)
    hit_n = np.zeros((1, 1), dtype=np.uint8)
    cells = np.zeros((1, 2), dtype=np.int64)
    units = np.array([[unit, 255 - unit]], dtype=np.uint16)
    for _ in range(HIT_COUNT_MAX + extra):
        accumulate_hits(hit_xy, hit_n, cells, units)
    count = int(hit_n[0, 0])
    assert 0 < count <= HIT_COUNT_MAX
    mean = hit_xy[:, 0, 0] / count
    np.testing.assert_allclose(mean, [unit, 255 - unit], atol=0.01)


def test_inserting_many_scans_equals_inserting_them_one_by_one() -> None:
    rng = np.random.default_rng(3)
    origins = rng.integers(8, 12, size=(4, 2)).astype(np.int64)
    hits = [rng.integers(0, 20, size=(n, 2)).astype(np.int64) for n in (5, 0, 7, 3)]
    misses = [rng.integers(0, 20, size=(n, 2)).astype(np.int64) for n in (2, 4, 0, 1)]
    units = [rng.integers(0, 256, size=(len(h), 2)).astype(np.uint16) for h in hits]

    one = empty(20, 20)
    one_xy, one_n = np.zeros((2, 20, 20), np.uint16), np.zeros((20, 20), np.uint8)
    for o, h, m, u in zip(origins, hits, misses, units, strict=True):
        if len(h) or len(m):
            update_cells(*one, box_of(o, h, m), o, h, m, MISS, HIT, LO_MIN, LO_MAX, THRESHOLD)
            accumulate_hits(one_xy, one_n, h, u)

    many = empty(20, 20)
    many_xy, many_n = np.zeros((2, 20, 20), np.uint16), np.zeros((20, 20), np.uint8)
    starts = lambda parts: np.r_[0, np.cumsum([len(p) for p in parts])].astype(np.int64)  # noqa: E731
    insert_many(*many, many_xy, many_n, origins, np.vstack(hits), starts(hits), np.vstack(misses),
                starts(misses), np.vstack(units), MISS, HIT, LO_MIN, LO_MAX, THRESHOLD)

    for a, b in zip((*one, one_xy, one_n), (*many, many_xy, many_n), strict=True):
        np.testing.assert_array_equal(a, b)


def test_occupied_windows_read_outside_the_storage_as_empty() -> None:
    log_odds, observed = empty(3, 3)
    log_odds[1, 1], observed[1, 1] = 1.0, True
    log_odds[0, 0], observed[0, 0] = 1.0, False  # never observed: not occupied
    boxes = np.array([[0, 0, 3, 3], [10, 10, 12, 12]], dtype=np.int64)  # storage starts at (0, 0)
    out, starts = occupied_windows(log_odds, observed, THRESHOLD, boxes, 0, 0)
    assert starts.tolist() == [0, 9, 13]
    assert np.flatnonzero(out).tolist() == [4]


def masked_update(log_odds, observed, origin, hits, misses, params: OccupancyParams):
    """The update as the grid made it before it touched only the beams' cells (until 2d18b1b):
    boolean masks over the scan's whole bounding box, numpy arithmetic with the params as
    Python floats. Storage cells; returns the flipped cells, row-major."""
    r0, c0, r1, c1 = box_of(origin, hits, misses)
    free_mask = np.zeros((r1 - r0, c1 - c0), dtype=bool)
    for ends, include_end in ((hits, False), (misses, True)):
        for end in ends.tolist():
            ray = np.empty((ray_length(*origin.tolist(), *end), 2), dtype=np.int64)
            passed = ray[: trace_ray(ray, *origin.tolist(), *end)]  # test_raycast checks these
            for r, c in passed if include_end else passed[:-1]:
                free_mask[r - r0, c - c0] = True
    hit_mask = np.zeros_like(free_mask)
    hit_mask[hits[:, 0] - r0, hits[:, 1] - c0] = True
    free_mask &= ~hit_mask
    lo, ob = log_odds[r0:r1, c0:c1], observed[r0:r1, c0:c1]
    threshold = params.threshold_log_odds()
    before = ob & (lo > threshold)
    lo[free_mask] += np.float32(params.miss_log_odds)
    lo[hit_mask] += np.float32(params.hit_log_odds)
    np.clip(lo, params.log_odds_min, params.log_odds_max, out=lo)
    ob |= hit_mask | free_mask
    rows, cols = np.nonzero(before != (ob & (lo > threshold)))
    return np.column_stack((rows + r0, cols + c0))


SIDE = 24
cells_in = st.tuples(st.integers(0, SIDE - 1), st.integers(0, SIDE - 1))


@settings(max_examples=300, deadline=None)
@given(
    seed=st.integers(0, 2**32 - 1),
    origin=cells_in,
    hits=st.lists(cells_in, max_size=40),
    misses=st.lists(cells_in, max_size=10),
    p_hit=st.floats(0.51, 0.99),
    p_miss=st.floats(0.01, 0.49),
    threshold=st.floats(0.05, 0.95),
)
def test_the_beams_cells_update_equals_the_bounding_box_masks_bit_for_bit(
    seed, origin, hits, misses, p_hit, p_miss, threshold
):
    """Same log-odds bits, observed cells and flipped cells, on a grid whose values sit at the
    clamps, at the threshold itself and a float32 step either side of it."""
    params = OccupancyParams(p_hit=p_hit, p_miss=p_miss, occupied_threshold=threshold,
                             log_odds_min=-1.5, log_odds_max=2.0)
    at = np.float32(params.threshold_log_odds())
    values = np.array([-1.5, 2.0, 0.0, at, np.nextafter(at, np.float32(9)),
                       np.nextafter(at, np.float32(-9)), at - np.float32(params.hit_log_odds),
                       at - np.float32(params.miss_log_odds)], dtype=np.float32)
    rng = np.random.default_rng(seed)
    log_odds = np.clip(rng.choice(values, (SIDE, SIDE)), -1.5, 2.0).astype(np.float32)
    observed = rng.random((SIDE, SIDE)) < 0.7
    o, h = np.array(origin, np.int64), np.array(hits, np.int64).reshape(-1, 2)
    m = np.array(misses, np.int64).reshape(-1, 2)
    want_lo, want_ob = log_odds.copy(), observed.copy()
    want = masked_update(want_lo, want_ob, o, h, m, params)
    got = update_cells(
        log_odds, observed, box_of(o, h, m), o, h, m, *(np.float32(v) for v in (
            params.miss_log_odds, params.hit_log_odds, params.log_odds_min,
            params.log_odds_max, params.threshold_log_odds(),
        )),
    )
    assert log_odds.tobytes() == want_lo.tobytes()
    np.testing.assert_array_equal(observed, want_ob)
    np.testing.assert_array_equal(got, want)
