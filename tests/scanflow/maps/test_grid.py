"""Growth policy of growable arrays: holds what is needed, bounded spare, few reallocations."""

from hypothesis import given
from hypothesis import strategies as st
from scanflow.maps.grid import CellBox, grown_box

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
