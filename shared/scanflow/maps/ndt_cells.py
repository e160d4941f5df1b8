"""Normal-distribution cells (Biber & Strasser 2003): per-cell mean and regularised covariance.

Points are binned into square cells; each cell with enough points keeps its mean and the
inverse of its covariance, whose eigenvalues are floored (a wall's points are nearly collinear,
so the raw covariance is close to singular). The paper's four overlapping grids are the same
construction shifted by half a cell in x, y and both (`OverlappingCells`, all four at once).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numba import njit
from numpy.typing import NDArray

from scanflow.maps.grid import GridSpec

MIN_CELL_POINTS = 3
EIGEN_FLOOR_RATIO = 0.1  # smallest eigenvalue >= this fraction of the largest
EIGEN_FLOOR_M2 = 1e-4  # and >= (1 cm)^2


def _checked_points(points: NDArray[np.float64], cell_size_m: float) -> NDArray[np.float64]:
    if not (math.isfinite(cell_size_m) and cell_size_m > 0):
        raise ValueError(f"cell_size_m must be positive, got {cell_size_m}")
    return np.asarray(points, dtype=np.float64).reshape(-1, 2)


@dataclass(frozen=True, eq=False)
class NDTCells:
    """Cell grid `spec` (resolution = cell size), `index[row, col]` = cell number or -1."""

    spec: GridSpec
    index: NDArray[np.int64]
    means: NDArray[np.float64]  # (K, 2)
    inv_covs: NDArray[np.float64]  # (K, 2, 2)
    counts: NDArray[np.int64]  # (K,)

    @staticmethod
    def from_points(
        points: NDArray[np.float64],
        cell_size_m: float,
        offset_m: tuple[float, float] = (0.0, 0.0),
        min_points: int = MIN_CELL_POINTS,
    ) -> NDTCells:
        """Bin `points` into cells of `cell_size_m` whose corners sit at offset + k * size."""
        p = _checked_points(points, cell_size_m)
        ox, oy = offset_m
        if len(p):
            lo = np.floor((p.min(axis=0) - (ox, oy)) / cell_size_m) * cell_size_m + (ox, oy)
            hi = p.max(axis=0)
        else:
            lo = hi = np.array([ox, oy])
        cols = math.floor((hi[0] - lo[0]) / cell_size_m) + 1
        rows = math.floor((hi[1] - lo[1]) / cell_size_m) + 1
        spec = GridSpec(float(lo[0]), float(lo[1]), cell_size_m, rows, cols)
        index, moments = _sparse_moments(
            p, spec.origin_x_m, spec.origin_y_m, cell_size_m, rows, cols, 1, min_points
        )
        means, inv_covs, counts = cell_distributions(moments, p[0] if len(p) else np.zeros(2))
        return NDTCells(spec, index.reshape(rows, cols), means, inv_covs, counts)

    def __len__(self) -> int:
        return len(self.means)

    def lookup(self, points: NDArray[np.float64]) -> NDArray[np.int64]:
        """Cell number holding each point, -1 when the point's cell has no distribution."""
        cells = self.spec.world_to_cell(points)
        inside = self.spec.contains(cells)
        out = np.full(len(cells), -1, dtype=np.int64)
        out[inside] = self.index[cells[inside, 0], cells[inside, 1]]
        return out


@njit(cache=True)
def _sparse_moments(points, origin_x, origin_y, size, rows, cols, span, min_points):  # type: ignore[no-untyped-def]
    """(flat index of kept cell numbers or -1, (K, 6) moments of the kept cells).

    Block (r, c) covers span x span cells of `size` from cell (r, c): span 1 gives plain
    cells; span 2 the 2 x 2 blocks of OverlappingCells, each point added to the four blocks
    holding it. Moments (count, sum x, sum y, sum xx, sum xy, sum yy) are accumulated only
    for blocks holding points, about the first point (small sums, no cancellation far from
    the origin); blocks with fewer than `min_points` points are dropped.
    """
    index = np.full(rows * cols, -1, dtype=np.int64)
    moments = np.zeros((points.shape[0] * span * span, 6))
    touched = np.empty(points.shape[0] * span * span, dtype=np.int64)
    n = 0
    x0, y0 = (points[0, 0], points[0, 1]) if points.shape[0] else (0.0, 0.0)
    for i in range(points.shape[0]):
        col = math.floor((points[i, 0] - origin_x) / size)
        row = math.floor((points[i, 1] - origin_y) / size)
        x, y = points[i, 0] - x0, points[i, 1] - y0
        for r in range(max(row - span + 1, 0), min(row, rows - 1) + 1):
            for c in range(max(col - span + 1, 0), min(col, cols - 1) + 1):
                flat = r * cols + c
                k = index[flat]
                if k < 0:
                    k = index[flat] = n
                    touched[n] = flat
                    n += 1
                m = moments[k]
                m[0] += 1.0
                m[1] += x
                m[2] += y
                m[3] += x * x
                m[4] += x * y
                m[5] += y * y
    kept = 0
    for k in range(n):
        if moments[k, 0] >= min_points:
            moments[kept] = moments[k]
            index[touched[k]] = kept
            kept += 1
        else:
            index[touched[k]] = -1
    return index, moments[:kept]


def cell_distributions(
    moments: NDArray[np.float64], about: NDArray[np.float64]
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.int64]]:
    """(means, regularised inverse covariances, counts) from `_sparse_moments`' moments."""
    n, sx, sy, sxx, sxy, syy = moments.T
    mx, my = sx / n, sy / n
    dof = np.maximum(n - 1, 1)
    cov = np.empty((len(n), 2, 2))
    cov[:, 0, 0] = (sxx - n * mx * mx) / dof
    cov[:, 0, 1] = cov[:, 1, 0] = (sxy - n * mx * my) / dof
    cov[:, 1, 1] = (syy - n * my * my) / dof
    means = np.column_stack((mx, my)) + about
    return means, regularised_inverse(cov), n.astype(np.int64)


def regularised_inverse(cov: NDArray[np.float64]) -> NDArray[np.float64]:
    """Inverse of (K, 2, 2) symmetric covariances after flooring their eigenvalues.

    Closed form for 2 x 2: eigenvalues mid -+ radius, major axis at half the angle of
    (a - c, 2 b).
    """
    a, b, c = cov[:, 0, 0], cov[:, 0, 1], cov[:, 1, 1]
    mid = 0.5 * (a + c)
    radius = np.hypot(0.5 * (a - c), b)
    small, large = mid - radius, mid + radius
    floor = np.maximum(EIGEN_FLOOR_RATIO * large, EIGEN_FLOOR_M2)
    inv_small = 1.0 / np.maximum(small, floor)
    inv_large = 1.0 / np.maximum(large, floor)
    phi = 0.5 * np.arctan2(2.0 * b, a - c)
    cos2, sin2, cs = np.cos(phi) ** 2, np.sin(phi) ** 2, np.cos(phi) * np.sin(phi)
    out = np.empty_like(cov)
    out[:, 0, 0] = cos2 * inv_large + sin2 * inv_small
    out[:, 0, 1] = out[:, 1, 0] = cs * (inv_large - inv_small)
    out[:, 1, 1] = sin2 * inv_large + cos2 * inv_small
    return out


@dataclass(frozen=True, eq=False)
class OverlappingCells:
    """The paper's four grids (unshifted and shifted by half a cell in x, y and xy) in one array.

    Each grid's cells are 2 x 2 blocks of a lattice of half-size cells; `index[i, j]` numbers
    the block whose first half-cell is (i, j) (every block is a cell of exactly one grid), so
    the moments are accumulated once on the half lattice and summed over blocks, and a point
    lies in the four blocks starting at its half-cell minus 0 or 1 in each axis.
    """

    origin_x_m: float  # corner of half-cell (0, 0)
    origin_y_m: float
    half_size_m: float
    parity: tuple[int, int]  # (row, col) parity of half-cell (0, 0) on the anchored lattice
    index: NDArray[np.int64]  # (R, C) block number or -1
    means: NDArray[np.float64]  # (K, 2)
    inv_covs: NDArray[np.float64]  # (K, 2, 2)
    counts: NDArray[np.int64]  # (K,)

    @staticmethod
    def from_points(
        points: NDArray[np.float64],
        cell_size_m: float,
        anchor_m: tuple[float, float] = (0.0, 0.0),
        min_points: int = MIN_CELL_POINTS,
    ) -> OverlappingCells:
        """Cells of `cell_size_m` with corners at anchor + k * size (+ size / 2 when shifted)."""
        p = _checked_points(points, cell_size_m)
        half = 0.5 * cell_size_m
        anchor = np.asarray(anchor_m, dtype=np.float64)
        if len(p):
            # One spare half-cell each side: every block holding a point starts inside.
            lo = np.floor((p.min(axis=0) - anchor) / half).astype(np.int64) - 1
            hi = np.floor((p.max(axis=0) - anchor) / half).astype(np.int64) + 1
        else:
            lo = hi = np.zeros(2, dtype=np.int64)
        cols, rows = (hi - lo + 1).tolist()
        origin = anchor + lo * half
        index, moments = _sparse_moments(
            p, origin[0], origin[1], half, rows - 1, cols - 1, 2, min_points
        )
        means, inv_covs, counts = cell_distributions(moments, p[0] if len(p) else np.zeros(2))
        return OverlappingCells(
            float(origin[0]),
            float(origin[1]),
            half,
            (int(lo[1] % 2), int(lo[0] % 2)),
            index.reshape(rows - 1, cols - 1),
            means,
            inv_covs,
            counts,
        )

    def __len__(self) -> int:
        return len(self.means)

    def lookup(self, points: NDArray[np.float64]) -> NDArray[np.int64]:
        """(N, 4) cell numbers of each point in the unshifted, x-, y- and xy-shifted grids."""
        p = np.asarray(points, dtype=np.float64).reshape(-1, 2)
        hc = np.floor((p[:, 0] - self.origin_x_m) / self.half_size_m).astype(np.int64)
        hr = np.floor((p[:, 1] - self.origin_y_m) / self.half_size_m).astype(np.int64)
        rows, cols = self.index.shape
        out = np.full((len(p), 4), -1, dtype=np.int64)
        for g, (shift_r, shift_c) in enumerate(((0, 0), (0, 1), (1, 0), (1, 1))):
            r = hr - (hr + self.parity[0] - shift_r) % 2
            c = hc - (hc + self.parity[1] - shift_c) % 2
            inside = (r >= 0) & (c >= 0) & (r < rows) & (c < cols)
            out[inside, g] = self.index[r[inside], c[inside]]
        return out
