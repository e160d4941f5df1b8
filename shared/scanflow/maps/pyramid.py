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

import numpy as np
from numpy.typing import NDArray

from scanflow.maps.field import LikelihoodField, field_from_means
from scanflow.maps.grid import CellBox
from scanflow.maps.occupancy import OccupancyGrid


class FieldLayer:
    """One pyramid level's likelihood field over the grid's storage, kept current lazily.

    `mark_dirty` records where the grid's occupied mask changed; `field()` refreshes just the
    affected neighbourhood, or everything after the grid's storage was reallocated (which
    happens O(log size) times as the grid doubles).
    """

    def __init__(self, grid: OccupancyGrid, factor: int, sigma_m: float, cutoff_m: float) -> None:
        if factor < 1:
            raise ValueError(f"factor must be >= 1, got {factor}")
        self.grid = grid
        self.factor = factor
        self.sigma_m = sigma_m
        self.cutoff_m = cutoff_m
        self.resolution_m = grid.resolution_m * factor
        self._margin = math.ceil(cutoff_m / self.resolution_m) + 1
        self._values = np.zeros((0, 0))
        self._box: CellBox | None = None
        self._generation = -1
        self._pending: CellBox | None = None

    @property
    def nbytes(self) -> int:
        return int(self._values.nbytes)

    def mark_dirty(self, fine_box: CellBox) -> None:
        """Note that the grid's occupied mask or mean hit points changed inside `fine_box`."""
        self._pending = fine_box.coarsened(self.factor).union(self._pending)

    def _rebuild(self) -> None:
        storage = self.grid.storage_box
        self._box = None if storage is None else storage.coarsened(self.factor)
        self._generation = self.grid.storage_generation
        self._pending = None
        if self._box is None:
            self._values = np.zeros((0, 0))
            return
        self._values = self._values_over(self._box)

    def _values_over(self, box: CellBox) -> NDArray[np.float64]:
        """This level's field over a box of its lattice, from the obstacles inside the box."""
        means = self.grid.occupied_hit_means(box, self.factor)
        return field_from_means(box.shape, means, self.resolution_m, self.sigma_m, self.cutoff_m)

    def _refresh(self, dirty: CellBox, box: CellBox) -> None:
        source = dirty.expanded(2 * self._margin).intersection(box)
        target = dirty.expanded(self._margin).intersection(box)
        values = self._values_over(source)
        self._values[target.slices_in(box)] = values[target.slices_in(source)]

    def field(self) -> LikelihoodField:
        """The field over the grid's extent at this level; a read-only view valid until the
        next grid update (copy `values` to keep a snapshot)."""
        if self._generation != self.grid.storage_generation:
            self._rebuild()
        elif self._pending is not None and self._box is not None:
            self._refresh(self._pending, self._box)
            self._pending = None
        extent = self.grid.extent
        if extent is None or self._box is None:
            return LikelihoodField(
                self.grid.spec_of(CellBox(0, 0, 0, 0), self.factor), np.zeros((0, 0)), self.sigma_m
            )
        coarse = extent.coarsened(self.factor)
        view = self._values[coarse.slices_in(self._box)]
        view.flags.writeable = False
        return LikelihoodField(self.grid.spec_of(coarse, self.factor), view, self.sigma_m)
