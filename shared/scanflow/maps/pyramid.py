"""Multi-resolution likelihood fields (Hector-style pyramid), each refreshed only where it changed.

Level k has cells 2**k times larger than the occupancy grid; a coarse cell is occupied when any
fine cell it covers is (max-pooling aligned to the world lattice, so coarse cells never straddle
a growth boundary). Each level's field has sigma and cut-off scaled with its cell size, so
coarse levels have a wide basin of attraction for the first, rough alignment.

Distances are measured to each occupied cell's mean hit point (the grid's hit sums pooled over
the fine cells it covers); an occupied fine cell without recorded hits (a map imported without
them) counts as one hit at its centre.

Because the field is cut off at `cutoff_m`, a change of the occupied mask or of a mean hit point
in a box moves field values only within the cut-off around it, and those values depend only on
obstacles within twice the cut-off: a refresh recomputes exactly that neighbourhood.
"""

from __future__ import annotations

import math
from collections.abc import Hashable

import numpy as np
from numpy.typing import NDArray

from scanflow.maps.field import LikelihoodField, field_from_means
from scanflow.maps.grid import CellBox, grown_box
from scanflow.maps.occupancy import OccupancyGrid


class FieldLayer:
    """One pyramid level's likelihood field over the grid's extent padded by the cut-off, kept
    current lazily.

    The padding lets obstacles on the outermost cells of the extent keep their whole field
    around them (cut at the border, a wall there read as ~0 and matchers saw no overlap). Values
    are float32 (plenty for a field in [0, 1]) in an array that grows like the grid's storage
    (`grown_box`) but follows the extent, not the grid's spare capacity. `mark_dirty` records
    where the grid's occupied mask or mean hit points changed; `field()` refreshes just the
    affected neighbourhood. Views derived from the values (max-pool stacks) follow them through
    `stored()` and `take_changes()`: where values changed since they last looked.
    """

    def __init__(self, grid: OccupancyGrid, factor: int, sigma_m: float, cutoff_m: float) -> None:
        if factor < 1:
            raise ValueError(f"factor must be >= 1, got {factor}")
        self.grid = grid
        self.factor = factor
        self.sigma_m = sigma_m
        self.cutoff_m = cutoff_m
        self.resolution_m = grid.resolution_m * factor
        self.margin_cells = math.ceil(cutoff_m / self.resolution_m) + 1
        self._values = np.zeros((0, 0), dtype=np.float32)
        self._box: CellBox | None = None
        self._pending: CellBox | None = None
        self._changes: dict[Hashable, CellBox | None] = {}

    @property
    def nbytes(self) -> int:
        return int(self._values.nbytes)

    def mark_dirty(self, fine_box: CellBox) -> None:
        """Note that the grid's occupied mask or mean hit points changed inside `fine_box`."""
        self._pending = fine_box.coarsened(self.factor).union(self._pending)

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

    def take_changes(self, consumer: Hashable) -> CellBox | None:
        """The box holding every stored value that `field()` changed since `consumer` last asked
        (None: none did); a consumer asking for the first time gets the whole stored box.

        Growing the storage changes no value (added cells are 0): consumers notice the new box
        through `stored()`.
        """
        if consumer not in self._changes:
            self._changes[consumer] = None
            return self._box
        changed, self._changes[consumer] = self._changes[consumer], None
        return changed

    def _changed(self, box: CellBox) -> None:
        if box.is_empty:
            return
        for consumer, changed in self._changes.items():
            self._changes[consumer] = box.union(changed)

    def _values_over(self, box: CellBox) -> NDArray[np.float32]:
        """This level's field over a box of its lattice, from the obstacles inside the box."""
        means = self.grid.occupied_hit_means(box, self.factor)
        return field_from_means(
            box.shape, means, self.resolution_m, self.sigma_m, self.cutoff_m, np.float32
        )

    def _hold(self, need: CellBox) -> CellBox:
        """Grow the values array to hold `need` and return the box it covers. Cells it adds are
        farther than the cut-off from every obstacle the old values saw, so they start at 0;
        new obstacles are pending."""
        if self._box is None:
            self._box = grown_box(None, need)
            self._values = self._values_over(self._box)
            self._pending = None
            self._changed(self._box)
        elif not self._box.contains_box(need):
            new = grown_box(self._box, need)
            values = np.zeros(new.shape, dtype=np.float32)
            kept = self._box.intersection(new)
            values[kept.slices_in(new)] = self._values[kept.slices_in(self._box)]
            self._box, self._values = new, values
        return self._box

    def _refresh(self, dirty: CellBox, box: CellBox) -> None:
        source = dirty.expanded(2 * self.margin_cells).intersection(box)
        target = dirty.expanded(self.margin_cells).intersection(box)
        values = self._values_over(source)
        self._values[target.slices_in(box)] = values[target.slices_in(source)]
        self._changed(target)

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
        if self._pending is not None:
            self._refresh(self._pending, box)
            self._pending = None
        view = self._values[padded.slices_in(box)]
        view.flags.writeable = False
        return LikelihoodField(self.grid.spec_of(padded, self.factor), view, self.sigma_m)
