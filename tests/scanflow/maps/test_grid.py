"""Growth policy of growable arrays: holds what is needed, bounded spare, few reallocations;
box sets (tiles, disjoint covers, unions) that views track their changes with."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scanflow.maps.grid import (
    BoxUnion,
    CellBox,
    GridSpec,
    boxes_of,
    clipped,
    corner_below,
    disjoint_cover,
    grown_box,
    tile_boxes,
)

boxes = st.builds(
    lambda r, c, h, w: CellBox(r, c, r + h, c + w),
    st.integers(-500, 500),
    st.integers(-500, 500),
    st.integers(1, 400),
    st.integers(1, 400),
)


def test_first_box_is_centred_in_the_minimum():
    assert grown_box(None, CellBox(0, 0, 10, 4), minimum_cells=16) == CellBox(-3, -6, 13, 10)
    assert grown_box(None, CellBox(0, 0, 30, 30), minimum_cells=16) == CellBox(0, 0, 30, 30)


@given(old=boxes, need=boxes)
def test_grown_box_holds_need_with_bounded_spare(old, need):
    new = grown_box(old, need)
    assert new.contains_box(need)
    if old.contains_box(need):
        assert new == old
        return
    for lo, hi, n_lo, n_hi, o_lo, o_hi in (
        (new.row0, new.row1, need.row0, need.row1, old.row0, old.row1),
        (new.col0, new.col1, need.col0, need.col1, old.col0, old.col1),
    ):
        if o_lo <= n_lo and n_hi <= o_hi:
            assert (lo, hi) == (o_lo, o_hi)  # an axis that fits is left alone
        else:
            assert hi - lo <= 2 * (n_hi - n_lo) + 2  # at most 2x what is needed


def test_steady_growth_reallocates_logarithmically_often():
    box, used, reallocations = None, CellBox(0, 0, 10, 10), 0
    for step in range(1, 5001):
        used = used.union(CellBox(0, step, 10, step + 10))  # one more column every step
        new = grown_box(box, used, minimum_cells=16)
        reallocations += new != box
        box = new
    assert box.shape[1] <= 1.5 * used.shape[1] + 1
    assert reallocations <= 16  # log_1.5(5010 / 16) ~ 14, plus the first


def covered(boxes: np.ndarray, lo: int, hi: int) -> np.ndarray:
    """Boolean raster of the union of (n, 4) boxes over rows and cols [lo, hi)."""
    mask = np.zeros((hi - lo, hi - lo), dtype=bool)
    for r0, c0, r1, c1 in np.asarray(boxes).reshape(-1, 4).tolist():
        mask[max(r0, lo) - lo : max(r1, lo) - lo, max(c0, lo) - lo : max(c1, lo) - lo] = True
    return mask


small_boxes = st.lists(
    st.tuples(st.integers(-30, 30), st.integers(-30, 30), st.integers(0, 12), st.integers(0, 12)),
    max_size=25,
).map(
    lambda bs: np.array([(r, c, r + h, c + w) for r, c, h, w in bs], dtype=np.int64).reshape(-1, 4)
)


@settings(deadline=None)  # the first example compiles the kernel
@given(boxes=small_boxes)
def test_disjoint_cover_is_the_union_without_overlaps(boxes):
    cover = disjoint_cover(boxes)
    assert cover.shape[1:] == (4,)
    assert ((cover[:, 2] > cover[:, 0]) & (cover[:, 3] > cover[:, 1])).all()
    np.testing.assert_array_equal(covered(cover, -30, 45), covered(boxes, -30, 45))
    areas = (cover[:, 2] - cover[:, 0]) * (cover[:, 3] - cover[:, 1])
    assert areas.sum() == covered(boxes, -30, 45).sum()  # no cell twice


def test_disjoint_cover_merges_runs_and_stacks_of_equal_runs():
    # Two overlapping squares: three bands, the middle one a single run.
    cover = disjoint_cover(np.array([[0, 0, 4, 4], [2, 2, 6, 6]]))
    assert sorted(cover.tolist()) == [[0, 0, 2, 4], [2, 0, 4, 6], [4, 2, 6, 6]]
    # Side by side and stacked: one box each.
    assert disjoint_cover(np.array([[0, 0, 2, 3], [0, 3, 2, 5]])).tolist() == [[0, 0, 2, 5]]
    assert disjoint_cover(np.array([[0, 0, 2, 3], [2, 0, 5, 3]])).tolist() == [[0, 0, 5, 3]]
    assert disjoint_cover(np.array([[1, 1, 1, 5]])).shape == (0, 4)


@settings(deadline=None)  # the first example compiles the kernel
@given(
    cells=st.lists(st.tuples(st.integers(-40, 40), st.integers(-40, 40)), max_size=40),
    tile=st.integers(1, 9),
)
def test_tile_boxes_are_the_tiles_holding_the_cells(cells, tile):
    c = np.array(cells, dtype=np.int64).reshape(-1, 2)
    boxes = tile_boxes(c, tile)
    assert (boxes % tile == 0).all()
    areas = (boxes[:, 2] - boxes[:, 0]) * (boxes[:, 3] - boxes[:, 1])
    assert (boxes[:, 2] - boxes[:, 0] == tile).all()
    tiles = {tuple(t) for t in (c // tile).tolist()}
    assert areas.sum() == len(tiles) * tile * tile  # disjoint, and only the tiles holding cells
    mask = covered(boxes, -45, 50)
    assert mask[c[:, 0] + 45, c[:, 1] + 45].all()
    # Runs are maximal: no two boxes of a row of tiles touch.
    ends = {(r0, c1) for r0, _, _, c1 in boxes.tolist()}
    assert not any((r0, c0) in ends for r0, c0, _, _ in boxes.tolist())


@given(boxes=small_boxes, within=boxes)
def test_clipped_keeps_the_parts_inside(boxes, within):
    inside = clipped(boxes, within)
    assert all(within.contains_box(CellBox(*b)) and not CellBox(*b).is_empty for b in inside)
    lo, hi = -30, 45
    mask = np.zeros((hi - lo, hi - lo), dtype=bool)
    w = within.intersection(CellBox(lo, lo, hi, hi))
    mask[w.row0 - lo : w.row1 - lo, w.col0 - lo : w.col1 - lo] = True
    np.testing.assert_array_equal(covered(inside, lo, hi), covered(boxes, lo, hi) & mask)


@settings(deadline=None)
@given(parts=st.lists(small_boxes, max_size=8))
def test_box_union_takes_the_union_of_what_was_added(parts):
    union = BoxUnion()
    union.MERGE_AFTER = 3  # merge on the way
    for part in parts:
        union.add(part)
    everything = np.concatenate([np.zeros((0, 4), dtype=np.int64), *parts])
    assert bool(union) == bool(len(everything))  # something was added since the last take
    taken = union.take()
    np.testing.assert_array_equal(covered(taken, -30, 45), covered(everything, -30, 45))
    assert not union and union.take().shape == (0, 4)
    assert boxes_of(None).shape == (0, 4) and boxes_of(CellBox(1, 2, 1, 5)).shape == (0, 4)
    assert boxes_of(CellBox(1, 2, 3, 5)).tolist() == [[1, 2, 3, 5]]


def test_covering_holds_a_lowest_point_just_below_a_cell_border() -> None:
    """-127.70000000000002 / 0.1 rounds to -1277 exactly: with no margin the grid began at
    -127.7, just above the point, which fell in column -1 of its own covering grid (a
    likelihood field from that point was 0 everywhere)."""
    point = np.array([[-127.70000000000002, 0.05]])
    spec = GridSpec.covering(point, 0.1, 0.0)
    assert spec.contains(spec.world_to_cell(point)).all()
    rng = np.random.default_rng(2)
    for resolution_m in (0.05, 0.1, 0.3):
        x = np.nextafter(rng.integers(-3000, 3000, 300) * resolution_m, -np.inf)
        for row in np.column_stack((x, x[::-1])):
            spec = GridSpec.covering(row[None, :], resolution_m, 0.0)
            assert spec.contains(spec.world_to_cell(row)).all(), (resolution_m, row)


@pytest.mark.parametrize("bad", [np.nan, np.inf])
def test_covering_refuses_non_finite_points_by_name(bad: float) -> None:
    """It raised 'cannot convert float NaN to integer' (or infinity) from math.ceil."""
    with pytest.raises(ValueError, match=r"points has 1 non-finite row"):
        GridSpec.covering(np.array([[0.0, 0.0], [bad, 1.0]]), 0.05, 1.0)


@given(
    st.floats(-1e4, 1e4, allow_nan=False),
    st.sampled_from([0.01, 0.04, 0.05, 0.1, 0.3, 0.5, 2.0]),
    st.floats(-1.0, 1.0, allow_nan=False),
)
def test_corner_below_is_the_lattice_corner_at_or_below_the_point(
    x: float, step: float, offset: float
) -> None:
    corner = float(corner_below(np.array([x]), step, offset)[0])
    assert corner <= x  # never above, whatever floor's rounding does
    assert x - corner < step * (1 + 1e-9)  # and the highest such corner
    k = (corner - offset) / step
    assert abs(k - round(k)) < 1e-6  # on the lattice offset + k * step


def test_corner_below_steps_down_where_rounding_lands_above() -> None:
    x = -127.70000000000002
    assert np.floor(x / 0.1) * 0.1 > x  # the rounding this guards against
    assert corner_below(np.array([x]), 0.1)[0] <= x
