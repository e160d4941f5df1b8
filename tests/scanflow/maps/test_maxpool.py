"""MaxPoolStack: every level is the block maximum it claims to be, on and off the grid;
MaxPoolStore: followed incrementally, it equals a rebuild."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scanflow.maps import maxpool
from scanflow.maps.grid import CellBox, GridSpec, boxes_of
from scanflow.maps.maxpool import SCORE_SCALE, MaxPoolStack, MaxPoolStore


def brute_block_max(q: np.ndarray, r: int, c: int, size: int) -> int:
    rows, cols = q.shape
    r0, r1 = max(r, 0), min(r + size, rows)
    c0, c1 = max(c, 0), min(c + size, cols)
    return int(q[r0:r1, c0:c1].max()) if r0 < r1 and c0 < c1 else 0


@settings(max_examples=40, deadline=None)
@given(
    rows=st.integers(1, 12),
    cols=st.integers(1, 12),
    depth=st.integers(0, 4),
    seed=st.integers(0, 2**31 - 1),
)
def test_levels_are_block_maxima(rows: int, cols: int, depth: int, seed: int) -> None:
    rng = np.random.default_rng(seed)
    values = rng.random((rows, cols)) * (rng.random((rows, cols)) < 0.4)
    stack = MaxPoolStack.from_values(GridSpec(0.0, 0.0, 0.1, rows, cols), values, depth)
    q = np.rint(values * SCORE_SCALE).astype(np.int64)
    assert stack.depth == depth
    r = np.arange(-(2**depth) - 3, rows + 3)
    c = np.arange(-(2**depth) - 3, cols + 3)
    rr, cc = np.meshgrid(r, c, indexing="ij")
    for h in range(depth + 1):
        got = stack.lookup(h, rr, cc)
        want = np.vectorize(lambda a, b, h=h: brute_block_max(q, a, b, 2**h))(rr, cc)
        np.testing.assert_array_equal(got, want)


def test_far_off_grid_lookups_score_zero() -> None:
    stack = MaxPoolStack.from_values(GridSpec(0.0, 0.0, 0.1, 3, 3), np.ones((3, 3)), 2)
    far = np.array([-1000, 1000, -5, 7])
    assert not stack.lookup(2, far, far).any()
    assert stack.lookup(2, np.array([-3]), np.array([-3]))[0] == SCORE_SCALE


@pytest.mark.parametrize(
    ("values", "depth", "match"),
    [
        (np.ones((2, 2)), 1, "shape"),
        (np.full((3, 3), 1.5), 1, "probabilities"),
        (np.full((3, 3), np.nan), 1, "probabilities"),
        (np.ones((3, 3)), -1, "depth"),
    ],
)
def test_bad_input_names_the_problem(values: np.ndarray, depth: int, match: str) -> None:
    with pytest.raises(ValueError, match=match):
        MaxPoolStack.from_values(GridSpec(0.0, 0.0, 0.1, 3, 3), values, depth)


def test_float32_views_pool_like_float64() -> None:
    """A map's field is a float32 view into a larger array: pooled without a float64 copy, to
    the same integers (the probabilities are not near a quantisation boundary here)."""
    rng = np.random.default_rng(3)
    big = (np.rint(rng.random((20, 24)) * SCORE_SCALE) / SCORE_SCALE).astype(np.float32)
    view = big[3:15, 2:21]
    spec = GridSpec(0.0, 0.0, 0.05, *view.shape)
    got = MaxPoolStack.from_values(spec, view, 3)
    want = MaxPoolStack.from_values(spec, view.astype(np.float64), 3)
    np.testing.assert_array_equal(got.levels, want.levels)


def _stack_of(store: MaxPoolStore, box: CellBox) -> MaxPoolStack:
    return store.stack(GridSpec(0.1 * box.col0, 0.1 * box.row0, 0.1, *box.shape), box)


@settings(max_examples=60, deadline=None)
@given(
    depth=st.integers(0, 3),
    steps=st.lists(
        st.tuples(
            st.lists(  # the boxes that change in this step (may overlap or touch)
                st.tuples(
                    st.integers(-6, 6),  # low corner
                    st.integers(-6, 6),
                    st.integers(1, 9),  # shape
                    st.integers(1, 9),
                ),
                min_size=1,
                max_size=3,
            ),
            st.integers(0, 4),  # spare cells around the support in the followed box
            st.integers(0, 2**31 - 1),
        ),
        min_size=1,
        max_size=6,
    ),
)
def test_store_follows_changes_like_a_rebuild(depth: int, steps: list) -> None:
    """Values change in a few random boxes per step while the followed box grows, moves and
    shrinks (keeping every non-zero value): the store's stack equals a rebuild over the
    followed box and over the support inside it."""
    store = MaxPoolStore(depth)
    values: dict[tuple[int, int], float] = {}  # lattice cell -> non-zero value
    support = None
    for changes, spare, seed in steps:
        rng = np.random.default_rng(seed)
        changed = [CellBox(r, c, r + rows, c + cols) for r, c, rows, cols in changes]
        for part in changed:
            new = rng.random(part.shape) * (rng.random(part.shape) < 0.5)
            for (r, c), v in np.ndenumerate(new):
                values[(part.row0 + r, part.col0 + c)] = v
            support = part.union(support)
        box = support.expanded(spare)
        dense = np.zeros(box.shape)
        for (r, c), v in values.items():
            dense[r - box.row0, c - box.col0] = v
        store.follow(box, dense, np.concatenate([boxes_of(part) for part in changed]))
        for inner, inner_values in ((box, dense), (support, dense[support.slices_in(box)])):
            spec = GridSpec(0.1 * inner.col0, 0.1 * inner.row0, 0.1, *inner.shape)
            got = store.stack(spec, inner)
            want = MaxPoolStack.from_values(spec, inner_values, depth)
            np.testing.assert_array_equal(got.levels, want.levels)
            assert got.pad_cells == want.pad_cells and got.spec == spec
    assert not _stack_of(store, support).levels.flags.writeable


def test_store_repools_only_around_the_changes(monkeypatch) -> None:
    """Two changes far apart: level 0 is re-quantised in the two boxes only, and each level
    above re-pooled in the two boxes grown towards lower indices, not in the box spanning
    both."""
    store = MaxPoolStore(3)
    big = CellBox(0, 0, 200, 300)
    values = np.zeros(big.shape)
    store.follow(big, values, boxes_of(big))
    stack = _stack_of(store, big)
    assert _stack_of(store, big) is stack
    store.follow(big, values, boxes_of(None))
    assert _stack_of(store, big) is stack
    pooled = []
    real = maxpool._pool
    monkeypatch.setattr(
        maxpool, "_pool", lambda levels, boxes: pooled.append(boxes.tolist()) or real(levels, boxes)
    )
    values[50:53, 60:62] = 0.5
    values[150:151, 250:254] = 0.7
    store.follow(big, values, np.array([[50, 60, 53, 62], [150, 250, 151, 254]]))
    pad = 2**3
    assert pooled == [
        [[50 + pad, 60 + pad, 53 + pad, 62 + pad], [150 + pad, 250 + pad, 151 + pad, 254 + pad]]
    ]
    assert _stack_of(store, big) is not stack
    np.testing.assert_array_equal(
        _stack_of(store, big).levels,
        MaxPoolStack.from_values(_stack_of(store, big).spec, values, 3).levels,
    )


def test_store_rejects_boxes_it_does_not_hold() -> None:
    store = MaxPoolStore(1)
    with pytest.raises(ValueError, match="followed box"):
        _stack_of(store, CellBox(0, 0, 2, 2))
    store.follow(CellBox(0, 0, 4, 4), np.zeros((4, 4)), boxes_of(CellBox(0, 0, 4, 4)))
    with pytest.raises(ValueError, match="followed box"):
        _stack_of(store, CellBox(0, 0, 5, 4))
    with pytest.raises(ValueError, match="box shape"):
        store.follow(CellBox(0, 0, 4, 4), np.zeros((3, 4)), boxes_of(None))
    with pytest.raises(ValueError, match="probabilities"):
        store.follow(CellBox(0, 0, 4, 4), np.full((4, 4), 2.0), boxes_of(CellBox(1, 1, 2, 2)))
