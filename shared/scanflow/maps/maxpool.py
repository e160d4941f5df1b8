"""Max-pooled copies of a score grid for branch and bound (Cartographer's PrecomputationGrid).

Level h holds, at cell (r, c), the maximum of the level-0 grid over the 2**h x 2**h block
starting there: cells r..r+2**h-1, c..c+2**h-1. A search node covering 2**h x 2**h translation
offsets therefore scores at least as high at level h as any of its leaves at level 0: an upper
bound. Values are integers (probabilities quantised once) so sums are exact and the bound and
the leaf scores are compared without rounding.

A change of level 0 inside a box changes level h only inside that box grown by 2**h - 1 cells
towards lower rows and columns, which is what lets `MaxPoolStore` follow a changing grid (a
map's likelihood field) by re-pooling just that neighbourhood of each box that changed.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit
from numpy.typing import NDArray

from scanflow.maps.grid import CellBox, GridSpec, clipped

SCORE_SCALE = 1000  # probability 1.0 -> 1000 (int16 levels)


@njit(cache=True, nogil=True)
def _quantise_into(out, values, boxes, pad):  # type: ignore[no-untyped-def]
    """out[r + pad, c + pad] = rint(values[r, c] * SCORE_SCALE) over each box (n, 4) of values'
    indices, in one pass; False if a value is not in [0, 1]."""
    for k in range(boxes.shape[0]):
        for r in range(boxes[k, 0], boxes[k, 2]):
            row, to = values[r], out[r + pad]
            for c in range(boxes[k, 1], boxes[k, 3]):
                v = row[c]
                if not 0.0 <= v <= 1.0:  # NaN fails too
                    return False
                to[c + pad] = np.rint(v * SCORE_SCALE)
    return True


@njit(cache=True, nogil=True)
def _pool(levels, changed):  # type: ignore[no-untyped-def]
    """Recompute levels 1.. of `levels` where level 0 changed inside the `changed` boxes ((n, 4)
    rows of [row0, col0, row1, col1), array indices).

    Block max doubles per level: level h + 1 at (r, c) is the max of level h at (r, c),
    (r + s, c), (r, c + s), (r + s, c + s) with s = 2**h, so a box changed at level 0 changes
    level h + 1 in the box grown by 2**(h + 1) - 1 towards lower indices. Each level is done
    for every box before the next (where grown boxes overlap, cells are recomputed to the same
    value). The boxes must keep 2**depth - 1 cells from the low edges of the array and
    2**(depth - 1) from the high ones (the zero padding does).
    """
    for h in range(levels.shape[0] - 1):
        s = 2**h
        shift = np.uint64(s)
        prev, out = levels[h], levels[h + 1]
        for k in range(changed.shape[0]):
            # Unsigned columns: no negative-index wrap-around check, so the loop vectorises
            # (as fast as numpy's whole-array maximum on one big box).
            c0, c1 = np.uint64(changed[k, 1] - (2 * s - 1)), np.uint64(changed[k, 3])
            for r in range(changed[k, 0] - (2 * s - 1), changed[k, 2]):
                here, below, row = prev[r], prev[r + s], out[r]
                for c in range(c0, c1):
                    pair = max(here[c], below[c])
                    row[c] = max(pair, max(here[c + shift], below[c + shift]))


def _check_depth(depth: int) -> None:
    if depth < 0:
        raise ValueError(f"depth must be >= 0, got {depth}")


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
        _check_depth(depth)
        pad = 2**depth
        levels = np.zeros((depth + 1, spec.rows + 2 * pad, spec.cols + 2 * pad), dtype=np.int16)
        whole = np.array([[0, 0, spec.rows, spec.cols]])
        _quantised(levels[0], v, whole, pad)
        _pool(levels, whole + pad)
        # Read-only like a followed map's stack: the search kernels then see one array type
        # (numba compiles each type apart, seconds each, at a service's first search).
        levels.flags.writeable = False
        return MaxPoolStack(spec, levels, pad)

    @property
    def depth(self) -> int:
        """The highest level: it holds maxima over 2**depth x 2**depth blocks."""
        return len(self.levels) - 1

    def lookup(
        self, level: int, rows: NDArray[np.int64], cols: NDArray[np.int64]
    ) -> NDArray[np.int16]:
        """Pooled scores at grid cells (row, col), any shape; cells off the grid score 0."""
        grid = self.levels[level]
        r = np.clip(rows + self.pad_cells, 0, grid.shape[0] - 1)
        c = np.clip(cols + self.pad_cells, 0, grid.shape[1] - 1)
        return grid[r, c]


def _quantised(
    out: NDArray[np.int16], values: NDArray[np.floating], boxes: NDArray[np.int64], pad: int
) -> None:
    if not _quantise_into(out, values, boxes, pad):
        raise ValueError("values must be probabilities in [0, 1]")


class MaxPoolStore:
    """The levels of a grid that changes in places, re-pooled only where it changed.

    `follow` tracks probabilities stored over a box of a lattice (a map's field level, whose box
    grows amortised): it re-lays the levels out when that box moves, which copies the kept cells
    (a growth adds zeros, whose pooled values are zero too), and re-pools the boxes of values
    changed since the previous call. `stack` then serves any box inside as a view equal to
    `MaxPoolStack.from_values` over it, when the values around that box are 0.
    """

    def __init__(self, depth: int) -> None:
        _check_depth(depth)
        self.depth = depth
        self.pad = 2**depth
        self._box: CellBox | None = None  # the box of values followed; levels hold it + pad
        self._levels = np.zeros((depth + 1, 0, 0), dtype=np.int16)
        self._stack: MaxPoolStack | None = None

    @property
    def nbytes(self) -> int:
        """Bytes of the stored levels (padding included)."""
        return int(self._levels.nbytes)

    def _storage(self, box: CellBox) -> CellBox:
        return box.expanded(self.pad)

    def follow(
        self, box: CellBox, values: NDArray[np.floating], changed: NDArray[np.int64]
    ) -> None:
        """Track `values` (probabilities in [0, 1] over `box`) that changed only inside the
        `changed` boxes ((n, 4) rows of [row0, col0, row1, col1) of the lattice; none: no row;
        pass `box` the first time) since the previous call. Cells that `box` no longer holds
        must have been 0."""
        if values.shape != box.shape:
            raise ValueError(f"values shape {values.shape} != box shape {box.shape}")
        if box != self._box:
            self._relayout(box)
        inside = clipped(changed, box)
        if len(inside) == 0:
            return
        at = inside - np.array([box.row0, box.col0, box.row0, box.col0])  # indices of values
        _quantised(self._levels[0], values, at, self.pad)  # levels hold the box plus the pad
        _pool(self._levels, at + self.pad)
        self._stack = None

    def _relayout(self, box: CellBox) -> None:
        new = self._storage(box)
        levels = np.zeros((self.depth + 1, *new.shape), dtype=np.int16)
        if self._box is not None:
            old = self._storage(self._box)
            kept = old.intersection(new)
            levels[(slice(None), *kept.slices_in(new))] = self._levels[
                (slice(None), *kept.slices_in(old))
            ]
        self._box, self._levels, self._stack = box, levels, None

    def stack(self, spec: GridSpec, box: CellBox) -> MaxPoolStack:
        """The stack of the values over `box` (inside the followed box; `spec` its geometry): a
        read-only view, the same object while nothing changed, valid until the next `follow`."""
        if self._box is None or not self._box.contains_box(box):
            raise ValueError(f"{box} is not inside the followed box {self._box}")
        if spec.shape != box.shape:
            raise ValueError(f"spec shape {spec.shape} != box shape {box.shape}")
        if self._stack is None or self._stack.spec != spec:
            outer = self._storage(box).slices_in(self._storage(self._box))
            view = self._levels[(slice(None), *outer)]
            view.flags.writeable = False
            self._stack = MaxPoolStack(spec, view, self.pad)
        return self._stack
