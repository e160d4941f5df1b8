"""Normal-distribution cells (Biber & Strasser 2003): per-cell mean and regularised covariance.

Points are binned into square cells; each cell with enough points keeps its mean and the
inverse of its covariance, whose eigenvalues are floored (a wall's points are nearly collinear,
so the raw covariance is close to singular). The paper's four overlapping grids are the same
construction shifted by half a cell in x, y and both (`overlapping_cells`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from scanflow.maps.grid import GridSpec

MIN_CELL_POINTS = 3
EIGEN_FLOOR_RATIO = 0.1  # smallest eigenvalue >= this fraction of the largest
EIGEN_FLOOR_M2 = 1e-4  # and >= (1 cm)^2


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
        if not (math.isfinite(cell_size_m) and cell_size_m > 0):
            raise ValueError(f"cell_size_m must be positive, got {cell_size_m}")
        p = np.asarray(points, dtype=np.float64).reshape(-1, 2)
        ox, oy = offset_m
        if len(p):
            lo = np.floor((p.min(axis=0) - (ox, oy)) / cell_size_m) * cell_size_m + (ox, oy)
            hi = p.max(axis=0)
        else:
            lo = hi = np.array([ox, oy])
        cols = math.floor((hi[0] - lo[0]) / cell_size_m) + 1
        rows = math.floor((hi[1] - lo[1]) / cell_size_m) + 1
        spec = GridSpec(float(lo[0]), float(lo[1]), cell_size_m, rows, cols)
        cells = spec.world_to_cell(p)
        flat = cells[:, 0] * cols + cells[:, 1]
        n = np.bincount(flat, minlength=rows * cols)
        kept = np.flatnonzero(n >= min_points)
        counts = n[kept]
        # Moments about the first point keep the sums small (no cancellation far from 0).
        c = p - p[0] if len(p) else p
        sx, sy, sxx, sxy, syy = (
            np.bincount(flat, w, rows * cols)[kept]
            for w in (c[:, 0], c[:, 1], c[:, 0] ** 2, c[:, 0] * c[:, 1], c[:, 1] ** 2)
        )
        mx, my = sx / counts, sy / counts
        dof = np.maximum(counts - 1, 1)
        cov = np.empty((len(kept), 2, 2))
        cov[:, 0, 0] = (sxx - counts * mx * mx) / dof
        cov[:, 0, 1] = cov[:, 1, 0] = (sxy - counts * mx * my) / dof
        cov[:, 1, 1] = (syy - counts * my * my) / dof
        means = np.column_stack((mx, my)) + (p[0] if len(p) else 0.0)
        index = np.full(rows * cols, -1, dtype=np.int64)
        index[kept] = np.arange(len(kept))
        return NDTCells(spec, index.reshape(rows, cols), means, regularised_inverse(cov), counts)

    def __len__(self) -> int:
        return len(self.means)

    def lookup(self, points: NDArray[np.float64]) -> NDArray[np.int64]:
        """Cell number holding each point, -1 when the point's cell has no distribution."""
        cells = self.spec.world_to_cell(points)
        inside = self.spec.contains(cells)
        out = np.full(len(cells), -1, dtype=np.int64)
        out[inside] = self.index[cells[inside, 0], cells[inside, 1]]
        return out


def regularised_inverse(cov: NDArray[np.float64]) -> NDArray[np.float64]:
    """Inverse of (K, 2, 2) covariances after flooring their eigenvalues."""
    vals, vecs = np.linalg.eigh(cov)
    floor = np.maximum(EIGEN_FLOOR_RATIO * vals[:, 1:], EIGEN_FLOOR_M2)
    vals = np.maximum(vals, floor)
    return np.einsum("kij,kj,klj->kil", vecs, 1.0 / vals, vecs)


def overlapping_cells(points: NDArray[np.float64], cell_size_m: float) -> tuple[NDTCells, ...]:
    """The four grids of the paper: unshifted and shifted by half a cell in x, y and xy."""
    h = 0.5 * cell_size_m
    return tuple(
        NDTCells.from_points(points, cell_size_m, off)
        for off in ((0.0, 0.0), (h, 0.0), (0.0, h), (h, h))
    )
