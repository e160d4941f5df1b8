"""Multi-resolution likelihood fields (Hector-style pyramid), each refreshed only where it changed.

Level k has cells 2**k times larger than the occupancy grid; a coarse cell is occupied when any
fine cell it covers is (max-pooling aligned to the world lattice, so coarse cells never straddle
a growth boundary). Each level's field has sigma and cut-off scaled with its cell size, so
coarse levels have a wide basin of attraction for the first, rough alignment.

Distances are measured to each occupied cell's mean hit point (the grid's hit sums pooled over
the fine cells it covers); an occupied fine cell without recorded hits (a map imported without
them) counts as one hit at its centre.

Because the field is cut off at `cutoff_m`, a change of the occupied mask or of a mean hit point
in a cell moves field values only within the cut-off around it, and those values depend only on
obstacles within twice the cut-off. Changes are tracked by tile (TILE_CELLS square on each
level's lattice), not by one bounding box: a 360-degree scan in a building changes cells along
the walls all around the robot, whose box is most of the map. A refresh recomputes the union of
the dirty tiles grown by the cut-off (as disjoint boxes) from the obstacles within twice the
cut-off of those tiles, each splatted once, so it costs in proportion to the walls near what a
scan changed, not to the map.
"""

from __future__ import annotations

import math
from collections.abc import Hashable

import numpy as np
from numba import njit
from numpy.typing import NDArray

from scanflow.maps.field import LikelihoodField, field_from_means
from scanflow.maps.grid import (
    BoxUnion,
    CellBox,
    boxes_of,
    clipped,
    disjoint_cover,
    grown_box,
    tile_boxes,
)
from scanflow.maps.occupancy import OccupancyGrid

TILE_CELLS = 4  # dirty-tile side on each level's lattice (`bench.maps --tile-cells` compares)


@njit(cache=True)
def _copy_boxes(dst, dst_row0, dst_col0, src, src_row0, src_col0, boxes):  # type: ignore[no-untyped-def]
    """dst[box] = src[box] for each lattice box (n, 4); (row0, col0) of each array: the lattice
    cell its [0, 0] holds."""
    for k in range(boxes.shape[0]):
        for r in range(boxes[k, 0], boxes[k, 2]):
            to, frm = dst[r - dst_row0], src[r - src_row0]
            for c in range(boxes[k, 1], boxes[k, 3]):
                to[c - dst_col0] = frm[c - src_col0]


class FieldLayer:
    """One pyramid level's likelihood field over the grid's extent padded by the cut-off, kept
    current lazily.

    The padding lets obstacles on the outermost cells of the extent keep their whole field
    around them (cut at the border, a wall there read as ~0 and matchers saw no overlap). Values
    are float32 (plenty for a field in [0, 1]) in an array that grows like the grid's storage
    (`grown_box`) but follows the extent, not the grid's spare capacity. `mark_dirty` records
    the tiles where the grid's occupied mask or mean hit points changed; `field()` refreshes
    just their neighbourhood. Views derived from the values (max-pool stacks) follow them
    through `stored()` and `take_changes()`: where values changed since they last looked.
    """

    def __init__(
        self,
        grid: OccupancyGrid,
        factor: int,
        sigma_m: float,
        cutoff_m: float,
        tile_cells: int = TILE_CELLS,
    ) -> None:
        if factor < 1:
            raise ValueError(f"factor must be >= 1, got {factor}")
        if tile_cells < 1:
            raise ValueError(f"tile_cells must be >= 1, got {tile_cells}")
        self.grid = grid
        self.factor = factor
        self.sigma_m = sigma_m
        self.cutoff_m = cutoff_m
        self.tile_cells = tile_cells
        self.resolution_m = grid.resolution_m * factor
        self.margin_cells = math.ceil(cutoff_m / self.resolution_m) + 1
        self._values = np.zeros((0, 0), dtype=np.float32)
        self._box: CellBox | None = None
        self._pending = BoxUnion()  # dirty tiles, as boxes of this lattice
        self._changes: dict[Hashable, BoxUnion] = {}

    @property
    def nbytes(self) -> int:
        """Bytes of the stored field values (the padded extent's float32 array)."""
        return int(self._values.nbytes)

    def mark_dirty(self, fine_cells: NDArray[np.int64]) -> None:
        """Note that the grid's occupied mask or mean hit points changed at the (K, 2) cells
        (of the grid's lattice)."""
        cells = np.asarray(fine_cells, dtype=np.int64).reshape(-1, 2) // self.factor
        self._pending.add(tile_boxes(cells, self.tile_cells))

    def padded_extent(self) -> CellBox | None:
        """The box this level's field covers: the grid's extent on this level's lattice plus the
        cut-off margin (None while the grid is empty)."""
        extent = self.grid.extent
        return None if extent is None else extent.coarsened(self.factor).expanded(self.margin_cells)

    def stored(self) -> tuple[CellBox | None, NDArray[np.float32]]:
        """The box the values array holds (None before the first `field()`) and a read-only view
        of it: 0 outside the padded extent. Valid until the next update."""
        view = self._values[:, :]
        view.flags.writeable = False
        return self._box, view

    def take_changes(self, consumer: Hashable) -> NDArray[np.int64]:
        """Disjoint boxes ((n, 4) rows of [row0, col0, row1, col1)) holding every stored value
        that `field()` changed since `consumer` last asked (none: no row); a consumer asking for
        the first time gets the whole stored box.

        Growing the storage changes no value (added cells are 0): consumers notice the new box
        through `stored()`.
        """
        if consumer not in self._changes:
            self._changes[consumer] = BoxUnion()
            return boxes_of(self._box)
        return self._changes[consumer].take()

    def _changed(self, boxes: NDArray[np.int64]) -> None:
        for changed in self._changes.values():
            changed.add(boxes)

    def _values_over(self, box: CellBox, sources: NDArray[np.int64]) -> NDArray[np.float32]:
        """This level's field over a box of its lattice, from the obstacles inside the disjoint
        `sources` boxes ((n, 4): all obstacles within the cut-off of the cells that matter)."""
        means = self.grid.occupied_hit_means_in(sources, self.factor, box)
        return field_from_means(
            box.shape, means, self.resolution_m, self.sigma_m, self.cutoff_m, np.float32
        )

    def _hold(self, need: CellBox) -> CellBox:
        """Grow the values array to hold `need` and return the box it covers. Cells it adds are
        farther than the cut-off from every obstacle the old values saw, so they start at 0;
        new obstacles are pending."""
        if self._box is None:
            self._box = grown_box(None, need)
            self._values = self._values_over(self._box, boxes_of(self._box))
            self._pending = BoxUnion()
            self._changed(boxes_of(self._box))
        elif not self._box.contains_box(need):
            new = grown_box(self._box, need)
            values = np.zeros(new.shape, dtype=np.float32)
            kept = self._box.intersection(new)
            values[kept.slices_in(new)] = self._values[kept.slices_in(self._box)]
            self._box, self._values = new, values
        return self._box

    def _refresh(self, box: CellBox) -> None:
        """Recompute the values within the cut-off of the pending tiles (their union grown by
        the margin, as disjoint boxes) in one pass: every obstacle within the margin of those
        boxes is splatted once into their bounding box, and the boxes are copied from it (a
        field per box would splat an obstacle near several boxes once for each)."""
        m = self.margin_cells
        tiles = self._pending.take()
        targets = disjoint_cover(clipped(tiles + np.array([-m, -m, m, m]), box))
        if len(targets) == 0:
            return
        sources = disjoint_cover(clipped(tiles + np.array([-2 * m, -2 * m, 2 * m, 2 * m]), box))
        frame = CellBox(*targets[:, :2].min(axis=0).tolist(), *targets[:, 2:].max(axis=0).tolist())
        values = self._values_over(frame, sources)
        _copy_boxes(self._values, box.row0, box.col0, values, frame.row0, frame.col0, targets)
        self._changed(targets)

    def field(self) -> LikelihoodField:
        """The field over the padded extent at this level; a read-only view valid until the next
        grid update (copy `values` to keep a snapshot)."""
        padded = self.padded_extent()
        if padded is None:
            return LikelihoodField(
                self.grid.spec_of(CellBox(0, 0, 0, 0), self.factor),
                np.zeros((0, 0), dtype=np.float32),
                self.sigma_m,
            )
        box = self._hold(padded)
        if self._pending:
            self._refresh(box)
        view = self._values[padded.slices_in(box)]
        view.flags.writeable = False
        return LikelihoodField(self.grid.spec_of(padded, self.factor), view, self.sigma_m)
