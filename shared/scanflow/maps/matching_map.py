"""A map that scan-to-map matchers take as their target: an occupancy grid plus derived views.

The likelihood fields (one per pyramid level) measure distances to each occupied cell's mean
hit point (sub-cell accurate walls; cell centres for maps imported without hit sums). They are
refreshed lazily, on first access after an update, and only around the tiles where the scan
flipped cells between free/unknown and occupied or added hits to occupied cells (a 360-degree
scan changes cells along every wall it sees: a thin set, whose one bounding box would often be
the whole map). The views derived from them follow the same way: a max-pool stack re-pools
only the boxes where its level's field values changed (`FieldLayer.take_changes`), and NDT
cells (plain, and the four overlapping grids the `ndt` matcher reads) recompute only the cells
holding cells that flipped. So keeping every view current costs in proportion to the region a
scan touched, not to the map; their arrays grow amortised with the map (O(log size)
re-layouts). Only the occupied points are rebuilt whole (on first access after the occupied
cells changed).

The default field sigma is 2 cells of the grid (0.10 m at 5 cm): wide enough for a smooth
gradient across a wall and a basin of a few cells, narrow enough to keep walls distinct; level k
of the pyramid scales it by 2**k with its cells. Fields are cut off at `cutoff_sigmas` sigmas
(default 4, where the field is exp(-8) ~ 3e-4), which bounds the refresh neighbourhood.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike, NDArray

from scanflow.maps.field import LikelihoodField
from scanflow.maps.grid import CellBox, disjoint_cover, tile_boxes
from scanflow.maps.maxpool import MaxPoolStack, MaxPoolStore
from scanflow.maps.ndt_cells import GridNDTCells, GridOverlappingCells, NDTCells, OverlappingCells
from scanflow.maps.occupancy import InsertResult, OccupancyGrid
from scanflow.maps.pyramid import TILE_CELLS, FieldLayer

# Side of the tiles `hit_means_near` reads around a scan's points (0.4 m at 5 cm cells).
NEAR_TILE_CELLS = 8
# Pyramid levels and max-pool depths its users reach (gn's 16 levels; csm's capped windows);
# past them the work grows without end (level 24: 16 s, a stack 13 deep: 7 GiB).
MAX_LEVEL = 20
MAX_POOL_DEPTH = 12


class MatchingMap:
    """An OccupancyGrid with incrementally maintained matching views."""

    def __init__(
        self,
        grid: OccupancyGrid | None = None,
        *,
        sigma_cells: float = 2.0,
        cutoff_sigmas: float = 4.0,
        tile_cells: int = TILE_CELLS,
    ) -> None:
        """`tile_cells`: side of the tiles the fields track changes by (see FieldLayer)."""
        if not sigma_cells > 0:
            raise ValueError(f"sigma_cells must be positive, got {sigma_cells}")
        if not cutoff_sigmas > 0:
            raise ValueError(f"cutoff_sigmas must be positive, got {cutoff_sigmas}")
        self.grid = grid if grid is not None else OccupancyGrid()
        self.sigma_m = sigma_cells * self.grid.resolution_m
        self.cutoff_sigmas = cutoff_sigmas
        self.tile_cells = tile_cells
        self._layers: dict[int, FieldLayer] = {}
        self._occupied_points: NDArray[np.float64] | None = None
        self._pools: dict[tuple[int, int], MaxPoolStore] = {}
        self._ndt: dict[float, GridNDTCells] = {}
        self._overlapping: dict[float, GridOverlappingCells] = {}
        self._seen_revision = self.grid.revision

    @property
    def resolution_m(self) -> float:
        """The grid's cell size (m)."""
        return self.grid.resolution_m

    @property
    def revision(self) -> int:
        """The grid's `revision`: it goes up as scans are inserted."""
        return self.grid.revision

    @property
    def nbytes(self) -> int:
        """Memory held by the grid and every view built so far."""
        views = sum(layer.nbytes for layer in self._layers.values())
        views += sum(pool.nbytes for pool in self._pools.values())
        views += sum(cells.nbytes for cells in self._ndt.values())
        views += sum(cells.nbytes for cells in self._overlapping.values())
        if self._occupied_points is not None:
            views += self._occupied_points.nbytes
        return self.grid.nbytes + views

    @property
    def is_empty(self) -> bool:
        """True while no cell of the map counts as occupied (nothing to match against)."""
        return self.occupied_points().shape[0] == 0

    def _sync(self) -> None:
        """Drop every view if the grid was written to other than through `update`."""
        if self.grid.revision != self._seen_revision:
            self._layers.clear()
            self._pools.clear()
            self._ndt.clear()
            self._overlapping.clear()
            self._occupied_points = None
            self._seen_revision = self.grid.revision

    def update(
        self,
        points_world: ArrayLike,
        sensor_origin: ArrayLike,
        no_return_endpoints: ArrayLike | None = None,
    ) -> InsertResult:
        """Insert a scan (see OccupancyGrid.insert_scan) and mark the views dirty where needed."""
        self._sync()
        result = self.grid.insert_scan(points_world, sensor_origin, no_return_endpoints)
        self._seen_revision = self.grid.revision
        flipped = result.occupied_cells
        if len(flipped) or len(result.means_cells):
            dirty = np.concatenate((flipped, result.means_cells))
            for layer in self._layers.values():
                layer.mark_dirty(dirty)
        if len(flipped):
            self._occupied_points = None
            stores: list[GridNDTCells | GridOverlappingCells] = [
                *self._ndt.values(), *self._overlapping.values()
            ]
            for cells in stores:
                cells.mark_dirty(flipped)
        return result

    def _layer(self, level: int) -> FieldLayer:
        if not 0 <= level <= MAX_LEVEL:
            raise ValueError(f"level must be in [0, {MAX_LEVEL}], got {level}")
        self._sync()
        layer = self._layers.get(level)
        if layer is None:
            sigma_m = self.sigma_m * 2**level
            layer = FieldLayer(
                self.grid, 2**level, sigma_m, self.cutoff_sigmas * sigma_m, self.tile_cells
            )
            self._layers[level] = layer
        return layer

    def likelihood_field(self, level: int = 0) -> LikelihoodField:
        """The likelihood field at pyramid level `level` (cells 2**level times the grid's).

        A read-only view valid until the next update.
        """
        return self._layer(level).field()

    def likelihood_pyramid(self, levels: int) -> list[LikelihoodField]:
        """Fields of levels levels-1 .. 0: coarse to fine, the order a multi-resolution
        matcher refines its estimate in."""
        if levels < 1:
            raise ValueError(f"levels must be >= 1, got {levels}")
        return [self.likelihood_field(level) for level in reversed(range(levels))]

    def occupied_points(self) -> NDArray[np.float64]:
        """(M, 2) world centres of the occupied cells (read-only; cached until they change)."""
        self._sync()
        if self._occupied_points is None:
            cells = np.argwhere(self.grid.occupied_mask())
            points = self.grid.spec.cell_centers(cells)
            points.flags.writeable = False
            self._occupied_points = points
        return self._occupied_points

    def hit_means_near(self, points_world: ArrayLike, radius_m: float) -> NDArray[np.float64]:
        """(K, 2) world mean hit points of the occupied cells within `radius_m` of the points
        (and some a little farther: whole tiles of NEAR_TILE_CELLS around them): a point-to-line
        matcher's target around a scan, read in proportion to the scan, not to the map."""
        if not 0.0 <= radius_m < math.inf:
            raise ValueError(f"radius_m must be finite and >= 0, got {radius_m}")
        points = np.asarray(points_world, dtype=np.float64).reshape(-1, 2)
        if len(points) == 0 or self.grid.is_empty:
            return np.zeros((0, 2))
        reach = math.ceil(radius_m / self.resolution_m)
        boxes = tile_boxes(self.grid.world_to_cells(points), NEAR_TILE_CELLS)
        boxes = disjoint_cover(boxes + np.array([-reach, -reach, reach, reach]))
        lattice = CellBox(0, 0, 0, 0)  # means counted from lattice cell (0, 0)
        rc = self.grid.occupied_hit_means_in(boxes, 1, lattice)
        return self.grid.spec_of(lattice).cell_centers(rc)

    def maxpool_stack(self, depth: int, level: int = 0) -> MaxPoolStack:
        """Branch-and-bound max-pooled scores of the level's likelihood field, 2**depth deep:
        equal to `MaxPoolStack.from_values` of `likelihood_field(level)`, re-pooled only where
        the field changed. A read-only view valid until the next update."""
        if not 0 <= depth <= MAX_POOL_DEPTH:
            raise ValueError(f"depth must be in [0, {MAX_POOL_DEPTH}], got {depth}")
        layer = self._layer(level)
        field = layer.field()
        pool = self._pools.get((depth, level))
        if pool is None:
            pool = self._pools[(depth, level)] = MaxPoolStore(depth)
        changed = layer.take_changes(pool)
        held, values = layer.stored()
        padded = layer.padded_extent()
        if held is None or padded is None:
            return MaxPoolStack.from_values(field.spec, field.values, depth)
        pool.follow(held, values, changed)
        return pool.stack(field.spec, padded)

    def ndt_cells(self, cell_size_m: float) -> NDTCells:
        """NDT distributions of the occupied cell centres, cells aligned to the map lattice
        anchor so they do not shift as the map grows; refreshed where occupied cells changed
        (see GridNDTCells). A read-only view valid until the next update."""
        self._sync()
        cells = self._ndt.get(cell_size_m)
        if cells is None:
            cells = self._ndt[cell_size_m] = GridNDTCells(self.grid, cell_size_m)
        return cells.cells()

    def overlapping_ndt_cells(self, cell_size_m: float) -> OverlappingCells:
        """The `ndt` matcher's four overlapping grids of the occupied cell centres, on the half-
        cell lattice anchored at the map lattice anchor (cells do not shift as the map grows);
        refreshed where occupied cells changed (see GridOverlappingCells). Equal, per block,
        to `OverlappingCells.from_points(occupied_points(), cell_size_m, anchor)`. A read-only
        view valid until the next update."""
        self._sync()
        cells = self._overlapping.get(cell_size_m)
        if cells is None:
            cells = self._overlapping[cell_size_m] = GridOverlappingCells(self.grid, cell_size_m)
        return cells.cells()
