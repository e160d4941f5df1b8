"""Block moments and their distributions against plain numpy: grouping points by block, the
overlapping 2 x 2 blocks, and the eigenvalue floor of the inverse covariances."""

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st
from scanflow.maps.ndt_moments import (
    EIGEN_FLOOR_M2,
    EIGEN_FLOOR_RATIO,
    block_distributions,
    regularised_inverse,
    sparse_moments,
)


def numpy_blocks(points: np.ndarray, origin: tuple[float, float], size: float, rows: int,
                 cols: int, span: int, min_points: int) -> dict[int, np.ndarray]:
    """Flat block index -> its points: block (r, c) covers span x span cells from cell (r, c)."""
    cell = np.floor((points - origin) / size).astype(int)  # (col, row)
    out: dict[int, list] = {}
    for p, (col, row) in zip(points, cell, strict=True):
        for r in range(row - span + 1, row + 1):
            for c in range(col - span + 1, col + 1):
                if 0 <= r < rows and 0 <= c < cols:
                    out.setdefault(r * cols + c, []).append(p)
    return {k: np.array(v) for k, v in out.items() if len(v) >= min_points}


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), span=st.sampled_from([1, 2]),
       min_points=st.integers(1, 5))
def test_each_kept_block_has_the_mean_and_covariance_of_its_points(
    seed: int, span: int, min_points: int
) -> None:
    rng = np.random.default_rng(seed)
    origin, size, rows, cols = (100.0, -50.0), 0.5, 6, 7
    points = rng.uniform([99.0, -51.0], [104.5, -46.5], size=(int(rng.integers(0, 200)), 2))
    want = numpy_blocks(points, origin, size, rows, cols, span, min_points)

    kept = sparse_moments(points, *origin, size, rows, cols, span, min_points)
    index, means, inv_covs, counts = block_distributions(kept, origin, size, cols)

    assert sorted(np.flatnonzero(index >= 0).tolist()) == sorted(want)
    for flat, pts in want.items():
        k = index[flat]
        assert counts[k] == len(pts)
        np.testing.assert_allclose(means[k], pts.mean(axis=0), atol=1e-9)
        cov = np.cov(pts.T, ddof=1) if len(pts) > 1 else np.zeros((2, 2))
        np.testing.assert_allclose(inv_covs[k], regularised_inverse(cov[None])[0], rtol=1e-6,
                                   atol=1e-6)


@settings(max_examples=200, deadline=None)
@given(
    major=st.floats(1e-8, 10.0), ratio=st.floats(0.0, 1.0), angle=st.floats(-3.2, 3.2),
)
def test_the_inverse_floors_the_eigenvalues_and_keeps_the_axes(
    major: float, ratio: float, angle: float
) -> None:
    axes = np.array([[np.cos(angle), -np.sin(angle)], [np.sin(angle), np.cos(angle)]])
    cov = axes @ np.diag([major, major * ratio]) @ axes.T
    floor = max(EIGEN_FLOOR_RATIO * major, EIGEN_FLOOR_M2)
    want = axes @ np.diag([1 / max(major, floor), 1 / max(major * ratio, floor)]) @ axes.T
    got = regularised_inverse(cov[None])[0]
    np.testing.assert_allclose(got, want, rtol=1e-6, atol=1e-9 * np.abs(want).max())
    np.testing.assert_allclose(got, got.T)
