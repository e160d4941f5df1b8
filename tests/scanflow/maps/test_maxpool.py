"""MaxPoolStack: every level is the block maximum it claims to be, on and off the grid."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scanflow.maps.grid import GridSpec
from scanflow.maps.maxpool import SCORE_SCALE, MaxPoolStack


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
