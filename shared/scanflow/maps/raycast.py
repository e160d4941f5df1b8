"""Bresenham ray marking: flag in a boolean mask every cell that many rays pass through.

A ray from cell a to cell b with n = max(|dr|, |dc|) steps visits, for k = 0..n,
a + round(k * (b - a) / n) with halves rounded away from zero: exactly the cells of the classic
integer all-octant Bresenham line. Compiled with numba because it is the hot spot of a scan
insert: a vectorised numpy version (all cells of all rays as index arrays) measured 7-12 ms for
360 rays of 200 cells, against 0.4 ms here, since it materialises a dozen 72k-element arrays.
"""

from __future__ import annotations

import numba
import numpy as np
from numpy.typing import NDArray

from scanflow.maps.grid import CellBox


@numba.njit(cache=True, nogil=True)
def _mark(
    mask: NDArray[np.bool_],
    row0: int,
    col0: int,
    start: NDArray[np.int64],
    end: NDArray[np.int64],
    include_end: bool,
) -> None:
    for i in range(start.shape[0]):
        dr = end[i, 0] - start[i, 0]
        dc = end[i, 1] - start[i, 1]
        n = max(abs(dr), abs(dc))
        den = 2 * max(n, 1)
        for k in range(n + 1 if include_end else n):
            a = k * dr
            b = k * dc
            step_r = (2 * abs(a) + n) // den
            step_c = (2 * abs(b) + n) // den
            r = start[i, 0] + (-step_r if a < 0 else step_r)
            c = start[i, 1] + (-step_c if b < 0 else step_c)
            mask[r - row0, c - col0] = True


def mark_rays(
    mask: NDArray[np.bool_],
    box: CellBox,
    start_cells: NDArray[np.int64],
    end_cells: NDArray[np.int64],
    include_end: bool = False,
) -> None:
    """Set True in `mask` (which stores `box`) every cell of each Bresenham ray start -> end.

    The start cell is always marked, the end cell only with `include_end`. Every start and end
    cell must lie inside `box` (then so does every cell between them).
    """
    # Contiguous and writable, always: a one-row broadcast (one ray) is already contiguous but
    # read-only, and numba compiles each array type apart (seconds, on a service's hot path).
    start = np.require(start_cells, np.int64, ["C", "W"]).reshape(-1, 2)
    end = np.require(end_cells, np.int64, ["C", "W"]).reshape(-1, 2)
    if start.shape != end.shape:
        raise ValueError(f"start_cells shape {start.shape} != end_cells shape {end.shape}")
    if mask.shape != box.shape or mask.dtype != np.bool_:
        raise ValueError(
            f"mask must be bool with box shape {box.shape}, got {mask.dtype} {mask.shape}"
        )
    if start.shape[0] == 0:
        return
    for name, cells in (("start_cells", start), ("end_cells", end)):
        lo, hi = cells.min(axis=0), cells.max(axis=0)
        if lo[0] < box.row0 or lo[1] < box.col0 or hi[0] >= box.row1 or hi[1] >= box.col1:
            raise ValueError(
                f"{name} span rows [{lo[0]}, {hi[0]}] cols [{lo[1]}, {hi[1]}] leave {box}"
            )
    _mark(mask, box.row0, box.col0, start, end, include_end)
