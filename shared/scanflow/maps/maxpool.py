"""Max-pooled copies of a score grid for branch and bound (Cartographer's PrecomputationGrid).

Level h holds, at cell (r, c), the maximum of the level-0 grid over the 2**h x 2**h block
starting there: cells r..r+2**h-1, c..c+2**h-1. A search node covering 2**h x 2**h translation
offsets therefore scores at least as high at level h as any of its leaves at level 0: an upper
bound. Values are integers (probabilities quantised once) so sums are exact and the bound and
the leaf scores are compared without rounding.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit
from numpy.typing import NDArray

from scanflow.maps.grid import GridSpec

SCORE_SCALE = 1000  # probability 1.0 -> 1000 (int16 levels)


@njit(cache=True)
def _quantise_into(out, values):  # type: ignore[no-untyped-def]
    """out = rint(values * SCORE_SCALE) in one pass; False if a value is not in [0, 1]."""
    for r in range(values.shape[0]):
        for c in range(values.shape[1]):
            v = values[r, c]
            if not 0.0 <= v <= 1.0:  # NaN fails too
                return False
            out[r, c] = np.rint(v * SCORE_SCALE)
    return True


@dataclass(frozen=True, eq=False)
class MaxPoolStack:
    """Levels 0..depth of max-pooled integer scores, zero-padded so lookups may leave the grid."""

    spec: GridSpec
    levels: NDArray[np.int16]  # (depth + 1, rows + 2 pad, cols + 2 pad)
    pad_cells: int

    @staticmethod
    def from_values(spec: GridSpec, values: NDArray[np.floating], depth: int) -> MaxPoolStack:
        """Quantise probabilities in [0, 1] to integers and pool them up to 2**depth cells.

        float32 or float64 values (a map's field view) are read in place, not copied."""
        v = np.asarray(values)
        if v.dtype not in (np.float32, np.float64):
            v = v.astype(np.float64)
        if v.shape != spec.shape:
            raise ValueError(f"values shape {v.shape} != grid shape {spec.shape}")
        if depth < 0:
            raise ValueError(f"depth must be >= 0, got {depth}")
        pad = 2**depth
        levels = np.zeros((depth + 1, spec.rows + 2 * pad, spec.cols + 2 * pad), dtype=np.int16)
        if not _quantise_into(levels[0, pad : pad + spec.rows, pad : pad + spec.cols], v):
            raise ValueError("values must be probabilities in [0, 1]")
        for h in range(depth):
            prev, nxt, s = levels[h], levels[h + 1], 2**h
            # Block max doubles per level: max over the four blocks of size 2**h starting at
            # (r, c), (r + s, c), (r, c + s), (r + s, c + s). Rows past the end stay 0 (padding).
            np.maximum(prev[:-s, :], prev[s:, :], out=nxt[:-s, :])
            np.maximum(nxt[:, :-s], nxt[:, s:], out=nxt[:, :-s])
        return MaxPoolStack(spec, levels, pad)

    @property
    def depth(self) -> int:
        return len(self.levels) - 1

    def lookup(
        self, level: int, rows: NDArray[np.int64], cols: NDArray[np.int64]
    ) -> NDArray[np.int16]:
        """Pooled scores at grid cells (row, col), any shape; cells off the grid score 0."""
        grid = self.levels[level]
        r = np.clip(rows + self.pad_cells, 0, grid.shape[0] - 1)
        c = np.clip(cols + self.pad_cells, 0, grid.shape[1] - 1)
        return grid[r, c]
