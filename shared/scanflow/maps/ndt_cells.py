"""Normal-distribution cells (Biber & Strasser 2003): per-cell mean and regularised covariance.

Points are binned into square cells; each cell with enough points keeps its mean and the
inverse of its covariance, whose eigenvalues are floored (a wall's points are nearly collinear,
so the raw covariance is close to singular). The paper's four overlapping grids are the same
construction shifted by half a cell in x, y and both (`OverlappingCells`, all four at once).

`GridNDTCells` and `GridOverlappingCells` keep the cells of a growing occupancy grid's
occupied cell centres current, on lattices anchored at the grid's anchor: after a scan they
recompute only the cells (the 2 x 2 blocks of half-cells) holding a cell that flipped between
free and occupied, from the occupied centres inside them.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Generic, NamedTuple, TypeVar

import numpy as np
from numpy.typing import NDArray

from scanflow.maps.grid import (
    BoxUnion,
    CellBox,
    GridSpec,
    boxes_of,
    corner_below,
    disjoint_cover,
    finite_rows,
    grown_box,
    tile_boxes,
)
from scanflow.maps.ndt_moments import (
    block_distributions,
    boxes_moments,
    cell_distributions,
    sparse_moments,
)
from scanflow.maps.occupancy import OccupancyGrid

MIN_CELL_POINTS = 3


def _check_cell_size(cell_size_m: float) -> None:
    if not (math.isfinite(cell_size_m) and cell_size_m > 0):
        raise ValueError(f"cell_size_m must be positive, got {cell_size_m}")


def _checked_points(points: NDArray[np.float64], cell_size_m: float) -> NDArray[np.float64]:
    _check_cell_size(cell_size_m)
    return finite_rows("points", np.asarray(points, dtype=np.float64).reshape(-1, 2))


def _read_only(*arrays: NDArray) -> None:
    """Cells never change once made (a map's are views of its live arrays): every holder of
    them reads the same read-only arrays, which the compiled scorer then takes in one type."""
    for a in arrays:
        a.flags.writeable = False


@dataclass(frozen=True, eq=False)
class NDTCells:
    """Cell grid `spec` (resolution = cell size), `index[row, col]` = cell number or -1."""

    spec: GridSpec
    index: NDArray[np.int64]
    means: NDArray[np.float64]  # (K, 2)
    inv_covs: NDArray[np.float64]  # (K, 2, 2)
    counts: NDArray[np.int64]  # (K,)

    def __post_init__(self) -> None:
        _read_only(self.index, self.means, self.inv_covs, self.counts)

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
            lo = corner_below(p.min(axis=0), cell_size_m, (ox, oy))
            hi = p.max(axis=0)
        else:
            lo = hi = np.array([ox, oy])
        cols = math.floor((hi[0] - lo[0]) / cell_size_m) + 1
        rows = math.floor((hi[1] - lo[1]) / cell_size_m) + 1
        spec = GridSpec(float(lo[0]), float(lo[1]), cell_size_m, rows, cols)
        origin = (spec.origin_x_m, spec.origin_y_m)
        index, means, inv_covs, counts = block_distributions(
            sparse_moments(p, *origin, cell_size_m, rows, cols, 1, min_points),
            origin,
            cell_size_m,
            cols,
        )
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


V = TypeVar("V")


class BlockArrays(NamedTuple):
    """Read-only views of a block store: index by block start, and per-block distributions."""

    block_index: NDArray[np.int64]  # not `index`: that would shadow tuple.index
    means: NDArray[np.float64]
    inv_covs: NDArray[np.float64]
    counts: NDArray[np.int64]


class _LatticeBlocks(Generic[V]):
    """Distributions of an OccupancyGrid's occupied cell centres in span x span blocks of a
    lattice anchored at the grid's anchor, kept current block by block.

    A fine cell belongs to the lattice cell holding its centre, so a block's distribution
    depends only on the occupied fine cells inside it. `mark_dirty(cells)` notes the fine cells
    whose occupied mask changed; the next `cells()` recomputes every block holding the lattice
    cell of one of them (the blocks of a scan's changes along its walls: a few disjoint boxes,
    not their bounding box, which would often be the map), from the occupied fine cells inside
    (moments about each block's corner: small sums), adds or drops blocks as they reach or fall
    below `min_points`, and keeps the distributions packed (a dropped block's slot takes the
    last one's). The index grid, by block start, grows like the grid's storage (`grown_box`).
    """

    def __init__(self, grid: OccupancyGrid, lattice_m: float, span: int, min_points: int) -> None:
        _check_cell_size(lattice_m)
        self.grid = grid
        self.lattice_m = lattice_m
        self.span = span
        self.min_points = min_points
        self._box: CellBox | None = None  # the block starts `_index` covers
        self._index = np.zeros((0, 0), dtype=np.int64)
        self._means = np.zeros((0, 2))
        self._inv_covs = np.zeros((0, 2, 2))
        self._counts = np.zeros(0, dtype=np.int64)
        self._cell_of = np.zeros((0, 2), dtype=np.int64)  # (row, col) of each slot's block
        self._used = 0
        self._pending = BoxUnion()  # lattice cells; everything to start with
        if grid.extent is not None:
            self._pending.add(boxes_of(self._cells_over(grid.extent)))
        self._view: V | None = None

    @property
    def nbytes(self) -> int:
        """Bytes of the block index and the packed per-block arrays, spare slots included."""
        return int(self._index.nbytes + sum(a.nbytes for a in self._slot_arrays()))

    def mark_dirty(self, fine_cells: NDArray[np.int64]) -> None:
        """Note that the grid's occupied mask changed at the (K, 2) cells (grid cells)."""
        self._pending.add(tile_boxes(self._bins(fine_cells), 1))

    def _bins(self, fine: NDArray[np.int64]) -> NDArray[np.int64]:
        """The lattice cell (row or col) holding the centre of each fine row or col."""
        scale = self.grid.resolution_m / self.lattice_m
        return np.floor((np.asarray(fine) + 0.5) * scale).astype(np.int64)

    def _cells_over(self, fine: CellBox) -> CellBox:
        """The lattice cells holding the centres of a (non-empty) box of fine cells."""
        lo = self._bins(np.array([fine.row0, fine.col0]))
        hi = self._bins(np.array([fine.row1 - 1, fine.col1 - 1])) + 1
        return CellBox(int(lo[0]), int(lo[1]), int(hi[0]), int(hi[1]))

    def _blocks_over(self, cells: CellBox) -> CellBox:
        """The blocks holding some lattice cell of `cells` (by first cell)."""
        lead = self.span - 1
        return CellBox(cells.row0 - lead, cells.col0 - lead, cells.row1, cells.col1)

    def cells(self) -> V:
        """The current blocks: read-only views, the same object while the occupied cells did
        not change, valid until the next grid update."""
        extent = self.grid.extent
        if self._pending and extent is not None:
            self._hold(self._blocks_over(self._cells_over(extent)))
            lead = self.span - 1
            self._refresh(disjoint_cover(self._pending.take() - np.array([lead, lead, 0, 0])))
            self._view = None
        if self._view is None:
            arrays = BlockArrays(
                self._index[:, :],
                self._means[: self._used],
                self._inv_covs[: self._used],
                self._counts[: self._used],
            )
            self._view = self._make_view(self._box or CellBox(0, 0, 0, 0), arrays)
        return self._view

    def _make_view(self, box: CellBox, arrays: BlockArrays) -> V:
        """The public cells object of the blocks `arrays` hold, numbered over `box` (by block
        start)."""
        raise NotImplementedError

    def _hold(self, need: CellBox) -> None:
        """Grow the index grid to hold `need` (every block with occupied centres)."""
        if self._box is not None and self._box.contains_box(need):
            return
        new = grown_box(self._box, need)
        index = np.full(new.shape, -1, dtype=np.int64)
        if self._box is not None:
            kept = self._box.intersection(new)
            index[kept.slices_in(new)] = self._index[kept.slices_in(self._box)]
        self._box, self._index = new, index

    def _refresh(self, blocks: NDArray[np.int64]) -> None:
        """Recompute the blocks of the disjoint (n, 4) boxes of blocks (by first cell), from
        the occupied fine cells whose centres lie in them (coordinates from each block's corner:
        small sums), all boxes in one compiled pass."""
        res, size = self.grid.resolution_m, self.lattice_m
        scale = size / res
        fine = np.column_stack(  # the fine cells over each box of blocks, and one more each side
            (
                np.floor(blocks[:, 0] * scale) - 1,
                np.floor(blocks[:, 1] * scale) - 1,
                np.ceil((blocks[:, 2] + self.span - 1) * scale) + 1,
                np.ceil((blocks[:, 3] + self.span - 1) * scale) + 1,
            )
        ).astype(np.int64)
        masks, starts = self.grid.occupied_in_boxes(fine)
        block_rc, live, moments, corners = boxes_moments(
            masks, starts, fine, blocks, res, size, self.span, self.min_points
        )
        means, inv_covs, counts = cell_distributions(moments, corners)
        means += (self.grid.anchor_x_m, self.grid.anchor_y_m)
        self._apply(block_rc, live, (means, inv_covs, counts, block_rc[live]))

    def _apply(
        self,
        block_rc: NDArray[np.int64],
        live: NDArray[np.bool_],
        new: tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.int64], NDArray[np.int64]],
    ) -> None:
        """Store the recomputed blocks at (row, col) `block_rc` (distinct; `new` holds the live
        ones, in that order)."""
        assert self._box is not None
        at = (block_rc[:, 0] - self._box.row0, block_rc[:, 1] - self._box.col0)
        index = self._index[at]
        was = index >= 0
        order = np.cumsum(live) - 1  # row of `new` for each live block
        added = live & ~was
        slots = self._used + np.arange(np.count_nonzero(added))
        self._reserve(self._used + len(slots))
        kept = was & live
        for array, values in zip(self._slot_arrays(), new, strict=True):
            array[index[kept]] = values[order[kept]]
            array[slots] = values[order[added]]
        dropped = index[was & ~live]
        index[added] = slots
        index[was & ~live] = -1
        self._index[at] = index
        self._used += len(slots)
        self._drop(dropped)

    def _slot_arrays(self) -> tuple[NDArray, NDArray, NDArray, NDArray]:
        return self._means, self._inv_covs, self._counts, self._cell_of

    def _reserve(self, slots: int) -> None:
        if slots <= len(self._counts):
            return
        capacity = max(slots, 2 * len(self._counts), 64)
        grown = []
        for array in self._slot_arrays():
            bigger = np.zeros((capacity, *array.shape[1:]), dtype=array.dtype)
            bigger[: self._used] = array[: self._used]
            grown.append(bigger)
        self._means, self._inv_covs, self._counts, self._cell_of = grown

    def _drop(self, slots: NDArray[np.int64]) -> None:
        """Free `slots`, moving the last used slots into the ones below the new end."""
        if len(slots) == 0:
            return
        assert self._box is not None
        end = self._used - len(slots)
        holes = np.sort(slots[slots < end])
        tail_dropped = np.zeros(self._used - end, dtype=bool)
        tail_dropped[slots[slots >= end] - end] = True
        movers = end + np.flatnonzero(~tail_dropped)
        for array in self._slot_arrays():
            array[holes] = array[movers]
        moved = self._cell_of[holes]
        self._index[moved[:, 0] - self._box.row0, moved[:, 1] - self._box.col0] = holes
        self._used = end


class GridNDTCells(_LatticeBlocks[NDTCells]):
    """NDTCells of an OccupancyGrid's occupied cell centres, kept current cell by cell.

    Cells of `cell_size_m` sit on the lattice anchored at the grid's anchor (blocks of one
    lattice cell, see _LatticeBlocks). Per cell location the result equals
    `NDTCells.from_points` of the occupied centres with the same size and anchor, up to
    summation order; the numbering of the cells differs.
    """

    def __init__(
        self, grid: OccupancyGrid, cell_size_m: float, min_points: int = MIN_CELL_POINTS
    ) -> None:
        super().__init__(grid, cell_size_m, 1, min_points)
        self.cell_size_m = cell_size_m

    def _make_view(self, box: CellBox, arrays: BlockArrays) -> NDTCells:
        spec = box.spec(self.grid.anchor_x_m, self.grid.anchor_y_m, self.cell_size_m)
        return NDTCells(spec, *arrays)


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

    def __post_init__(self) -> None:
        _read_only(self.index, self.means, self.inv_covs, self.counts)

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
        ox, oy = float(origin[0]), float(origin[1])
        index, means, inv_covs, counts = block_distributions(
            sparse_moments(p, ox, oy, half, rows - 1, cols - 1, 2, min_points),
            (ox, oy),
            half,
            cols - 1,
        )
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


class GridOverlappingCells(_LatticeBlocks[OverlappingCells]):
    """OverlappingCells of an OccupancyGrid's occupied cell centres, kept current block by block.

    The half-size lattice is anchored at the grid's anchor, so the four grids do not shift as
    the map grows; a change recomputes the 2 x 2 blocks holding a half-cell it touched (see
    _LatticeBlocks). Per block location the
    result equals `OverlappingCells.from_points` of the occupied centres with the same size and
    anchor, up to summation order; the numbering of the blocks differs.
    """

    def __init__(
        self, grid: OccupancyGrid, cell_size_m: float, min_points: int = MIN_CELL_POINTS
    ) -> None:
        _check_cell_size(cell_size_m)
        super().__init__(grid, 0.5 * cell_size_m, 2, min_points)
        self.cell_size_m = cell_size_m

    def _make_view(self, box: CellBox, arrays: BlockArrays) -> OverlappingCells:
        half = self.lattice_m
        return OverlappingCells(
            self.grid.anchor_x_m + box.col0 * half,
            self.grid.anchor_y_m + box.row0 * half,
            half,
            (box.row0 % 2, box.col0 % 2),
            *arrays,
        )
