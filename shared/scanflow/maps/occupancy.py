"""A growable log-odds occupancy grid: free along each beam, occupied at its end, clamped.

Growth is amortised reallocation of one contiguous array (not tiles): cells are indexed on a
lattice fixed in the world (cell (0, 0) has its corner at the anchor), and when a scan reaches
beyond the stored box, each axis that must grow gets the used extent plus 50 % spare on the side
it grew (`grid.grown_box`), so the map is copied O(log size) times and the storage stays within
~2x of the extent per axis. One contiguous array lets every derived view (distance fields,
pyramids, exports) slice any region directly, with no tile stitching; the spare capacity is
reported by `nbytes` and measured in bench/maps.py.

A cell is updated at most once per scan; a cell hit by some beam of the scan is not also
cleared by another beam of the same scan.

Each cell also keeps the sums of where endpoints fell inside it (x and y offsets in 1/256 of a
cell, a unit u standing for (u + 0.5) / 256, uint16; and their count, uint8: 5 more bytes per
cell), so matching fields can measure
distances to the mean hit point of an occupied cell instead of its centre: walls stay at
sub-cell accuracy. Sums and count are halved when the count would pass 255, which bounds them
(and lets old hits fade) without moving the mean.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np
from numpy.typing import ArrayLike, NDArray

from scanflow.maps.grid import CellBox, GridSpec, boxes_of, finite_rows, grown_box
from scanflow.maps.occupancy_kernels import (
    HIT_COUNT_MAX,
    HIT_UNITS_PER_CELL,
    accumulate_hits,
    insert_many,
    occupied_windows,
    pooled_hit_means,
    update_cells,
)

# A map's lattice anchor and cell indices stay where int64 cell arithmetic cannot overflow (a
# map anchored at 1e300 m, as a forged file could say, failed deep inside a compiled kernel).
MAX_ANCHOR_M = 1e7
MAX_CELL_INDEX = 2**40
MIN_RESOLUTION_M, MAX_RESOLUTION_M = 1e-3, 100.0


def _logit(p: float) -> float:
    return math.log(p / (1.0 - p))


def _is_int(value: object) -> bool:
    """An integer (Python's or numpy's), not a bool or a float."""
    return isinstance(value, int | np.integer) and not isinstance(value, bool)


@dataclass(frozen=True, slots=True)
class OccupancyParams:
    """Sensor model and bookkeeping for an OccupancyGrid (probabilities, metres)."""

    resolution_m: float = 0.05
    p_hit: float = 0.85
    p_miss: float = 0.4
    log_odds_min: float = -2.0
    log_odds_max: float = 3.5
    occupied_threshold: float = 0.65
    no_return_clear_m: float = 5.0
    max_range_m: float = 100.0

    def __post_init__(self) -> None:
        # A cell of 1e-6 m asked for TiB at the first insert, one of 1e300 m overflowed a search.
        if not MIN_RESOLUTION_M <= self.resolution_m <= MAX_RESOLUTION_M:
            raise ValueError(
                f"resolution_m must be in [{MIN_RESOLUTION_M:g}, {MAX_RESOLUTION_M:g}] m, got "
                f"{self.resolution_m}"
            )
        if not 0.5 < self.p_hit < 1.0:
            raise ValueError(f"p_hit must be in (0.5, 1), got {self.p_hit}")
        if not 0.0 < self.p_miss < 0.5:
            raise ValueError(f"p_miss must be in (0, 0.5), got {self.p_miss}")
        if not self.log_odds_min < 0.0 < self.log_odds_max:
            raise ValueError(
                f"need log_odds_min < 0 < log_odds_max, got "
                f"[{self.log_odds_min}, {self.log_odds_max}]"
            )
        if not 0.0 < self.occupied_threshold < 1.0:
            raise ValueError(f"occupied_threshold must be in (0, 1), got {self.occupied_threshold}")
        if not self.no_return_clear_m >= 0.0:
            raise ValueError(f"no_return_clear_m must be >= 0, got {self.no_return_clear_m}")
        if not self.max_range_m > 0.0:
            raise ValueError(f"max_range_m must be positive, got {self.max_range_m}")

    @property
    def hit_log_odds(self) -> float:
        """logit(p_hit) (> 0): what a scan adds to the log-odds of each cell it hits."""
        return _logit(self.p_hit)

    @property
    def miss_log_odds(self) -> float:
        """logit(p_miss) (< 0): what a scan adds to each cell its beams pass through."""
        return _logit(self.p_miss)

    def threshold_log_odds(self, probability: float | None = None) -> float:
        """Log-odds above which a cell counts as occupied (default: occupied_threshold)."""
        p = self.occupied_threshold if probability is None else probability
        if not 0.0 < p < 1.0:
            raise ValueError(f"threshold probability must be in (0, 1), got {p}")
        return _logit(p)


def _no_cells() -> NDArray[np.int64]:
    return np.zeros((0, 2), dtype=np.int64)


@dataclass(frozen=True, slots=True, eq=False)
class InsertResult:
    """What one scan changed: the box of every cell it updated, the (K, 2) lattice (row, col)
    of the cells whose occupied mask flipped, and those of the cells occupied after the scan
    that got new hits (their mean hit point moved; a cell hit twice is listed twice).

    The changed cells, not their bounding boxes, are what views refresh around: a 360-degree
    scan changes cells along the walls all around the sensor, a thin set whose box is often
    most of the map.
    """

    touched: CellBox | None
    occupied_cells: NDArray[np.int64] = field(default_factory=_no_cells)
    means_cells: NDArray[np.int64] = field(default_factory=_no_cells)

    @property
    def occupied_changed(self) -> CellBox | None:
        """Bounding box of the cells whose occupied mask flipped (None: none did)."""
        return CellBox.around(self.occupied_cells) if len(self.occupied_cells) else None


class ScanRays(NamedTuple):
    """One scan's beams in world coordinates: the sensor's position (2,), the (N, 2) points
    its beams hit and the (M, 2) ends of beams that saw nothing (None: no such beams)."""

    origin: ArrayLike
    hits: ArrayLike
    misses: ArrayLike | None = None


@dataclass(frozen=True, eq=False)
class RayBatch:
    """Many scans' beams, for `OccupancyGrid.insert_scans`: scan s has `origins[s]`, the hits
    `hits[hit_starts[s]:hit_starts[s + 1]]` and the no-return ends `misses[miss_starts[s]:
    miss_starts[s + 1]]` (world coordinates)."""

    origins: NDArray[np.float64]  # (S, 2)
    hits: NDArray[np.float64]  # (H, 2)
    hit_starts: NDArray[np.int64]  # (S + 1,)
    misses: NDArray[np.float64]  # (M, 2)
    miss_starts: NDArray[np.int64]  # (S + 1,)

    def __post_init__(self) -> None:
        for name in ("origins", "hits", "misses"):
            object.__setattr__(self, name, np.ascontiguousarray(_shaped(name, getattr(self, name))))
        scans = self.origins.shape[0]
        for name, rows in (("hit_starts", self.hits.shape[0]),
                           ("miss_starts", self.misses.shape[0])):
            s = np.ascontiguousarray(getattr(self, name), dtype=np.int64)
            object.__setattr__(self, name, s)
            if (s.shape != (scans + 1,) or s[0] != 0 or s[-1] != rows
                    or (np.diff(s) < 0).any()):
                raise ValueError(
                    f"{name} must rise from 0 to {rows} in {scans + 1} steps, got "
                    f"{s.tolist()[:8]}"
                )

    @staticmethod
    def of(scans: Sequence[ScanRays]) -> RayBatch:
        """The batch of `scans` (shapes checked, naming the scan)."""
        origins, hits, misses = [], [], []
        for i, scan in enumerate(scans):
            origin = np.asarray(scan.origin, dtype=np.float64)
            if origin.shape != (2,):
                raise ValueError(f"scans[{i}].origin must have shape (2,), got {origin.shape}")
            origins.append(origin)
            hits.append(_shaped(f"scans[{i}].hits", scan.hits))
            misses.append(_shaped(f"scans[{i}].misses", np.zeros((0, 2)) if scan.misses is None
                                  else scan.misses))
        return RayBatch(
            np.array(origins, dtype=np.float64).reshape(-1, 2),
            np.concatenate([np.zeros((0, 2)), *hits]),
            np.cumsum([0] + [len(h) for h in hits]),
            np.concatenate([np.zeros((0, 2)), *misses]),
            np.cumsum([0] + [len(m) for m in misses]),
        )

    def first_bad(self, name: str, rows: NDArray[np.bool_]) -> str:
        """Where the first flagged row of `name` ("origins", "hits" or "misses") is, as
        `scans[s].<name> row r <value>`, for an error message."""
        row = int(np.flatnonzero(rows)[0])
        if name == "origins":
            return f"scans[{row}].origin {getattr(self, name)[row]}"
        starts = self.hit_starts if name == "hits" else self.miss_starts
        scan = int(np.searchsorted(starts, row, side="right")) - 1
        return f"scans[{scan}].{name} row {row - starts[scan]} {getattr(self, name)[row]}"


def _shaped(name: str, value: ArrayLike) -> NDArray[np.float64]:
    p = np.asarray(value, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 2:
        raise ValueError(f"{name} must have shape (N, 2), got {p.shape}")
    return p


def _as_points(name: str, value: ArrayLike) -> NDArray[np.float64]:
    return finite_rows(name, _shaped(name, value))


def _quantised_hit_sums(
    hit_sums: NDArray[np.floating], shape: tuple[int, int]
) -> tuple[NDArray[np.uint16], NDArray[np.uint8]]:
    """Storage form of (3, rows, cols) hit sums (offsets in cells, counts): counts above the
    maximum are scaled down with their sums, which keeps the means."""
    h = np.asarray(hit_sums, dtype=np.float64)
    if h.shape != (3, *shape):
        raise ValueError(f"hit_sums must have shape {(3, *shape)}, got {h.shape}")
    if not np.isfinite(h).all():
        raise ValueError("hit_sums has non-finite values")
    if (h < 0).any():
        raise ValueError(f"hit_sums must be >= 0, got {float(h.min())}")
    scale = np.maximum(h[2] / HIT_COUNT_MAX, 1.0)
    count = np.rint(h[2] / scale)
    most = count * (HIT_UNITS_PER_CELL - 1)
    xy = np.clip(np.rint((h[:2] * HIT_UNITS_PER_CELL - 0.5 * h[2]) / scale), 0, most)
    return xy.astype(np.uint16), count.astype(np.uint8)


class OccupancyGrid:
    """Log-odds occupancy on a world-fixed lattice that grows as scans reach new ground."""

    def __init__(
        self,
        params: OccupancyParams | None = None,
        anchor_x_m: float = 0.0,
        anchor_y_m: float = 0.0,
        initial_capacity_cells: int = 64,
    ) -> None:
        if initial_capacity_cells < 1:
            raise ValueError(f"initial_capacity_cells must be >= 1, got {initial_capacity_cells}")
        if not (abs(anchor_x_m) <= MAX_ANCHOR_M and abs(anchor_y_m) <= MAX_ANCHOR_M):
            raise ValueError(
                f"anchor must be finite and within +-{MAX_ANCHOR_M:g} m, got "
                f"({anchor_x_m}, {anchor_y_m})"
            )
        self.params = params or OccupancyParams()
        self.anchor_x_m = float(anchor_x_m)
        self.anchor_y_m = float(anchor_y_m)
        self._initial_capacity = initial_capacity_cells
        self._log_odds = np.zeros((0, 0), dtype=np.float32)
        self._observed = np.zeros((0, 0), dtype=bool)
        self._hit_xy = np.zeros((2, 0, 0), dtype=np.uint16)  # sums of x, y offsets in cells/256
        self._hit_n = np.zeros((0, 0), dtype=np.uint8)
        self._storage: CellBox | None = None
        self._extent: CellBox | None = None
        self.revision = 0
        self.storage_generation = 0

    @classmethod
    def from_arrays(
        cls,
        log_odds: NDArray[np.floating],
        observed: NDArray[np.bool_],
        box: CellBox,
        anchor_x_m: float,
        anchor_y_m: float,
        params: OccupancyParams | None = None,
        revision: int = 0,
        hit_sums: NDArray[np.floating] | None = None,
    ) -> OccupancyGrid:
        """A grid holding `log_odds` (clamped to the params) over `box`: used by map import.

        Without `hit_sums` (3, rows, cols) every cell has no recorded hits, so matching fields
        fall back to the occupied cells' centres.
        """
        bounds = (box.row0, box.col0, box.row1, box.col1)
        if not all(_is_int(v) and abs(v) <= MAX_CELL_INDEX for v in bounds):
            raise ValueError(f"box must hold integers within +-{MAX_CELL_INDEX}, got {bounds}")
        if not (_is_int(revision) and revision >= 0):
            raise ValueError(f"revision must be an integer >= 0, got {revision!r}")
        lo = np.asarray(log_odds, dtype=np.float32)
        obs = np.asarray(observed, dtype=bool)
        if lo.shape != box.shape or obs.shape != box.shape:
            raise ValueError(
                f"log_odds {lo.shape} and observed {obs.shape} must both have box shape {box.shape}"
            )
        if not np.isfinite(lo).all():
            raise ValueError("log_odds has non-finite values")
        hit_xy, hit_n = _quantised_hit_sums(
            np.zeros((3, *box.shape)) if hit_sums is None else hit_sums, box.shape
        )
        grid = cls(params, anchor_x_m, anchor_y_m)
        p = grid.params
        grid._log_odds = np.clip(lo, p.log_odds_min, p.log_odds_max).astype(np.float32)
        grid._observed = obs.copy()
        grid._hit_xy, grid._hit_n = hit_xy, hit_n
        if not box.is_empty:
            grid._storage = grid._extent = box
        grid.revision = revision
        return grid

    @classmethod
    def from_int8(
        cls,
        data: NDArray[np.integer],
        origin_x_m: float,
        origin_y_m: float,
        params: OccupancyParams | None = None,
    ) -> OccupancyGrid:
        """A grid from ROS OccupancyGrid data (rows grow with y): -1 unknown, 0..100 percent."""
        d = np.asarray(data)
        if d.ndim != 2:
            raise ValueError(f"data must be 2-D, got shape {d.shape}")
        bad = (d < -1) | (d > 100)
        if bad.any():
            raise ValueError(f"data values must be -1 or 0..100, got {int(d[bad][0])}")
        p_occ = np.clip(d.astype(np.float64) / 100.0, 1e-9, 1.0 - 1e-9)
        log_odds = np.where(d >= 0, np.log(p_occ / (1.0 - p_occ)), 0.0)
        box = CellBox(0, 0, d.shape[0], d.shape[1])
        return cls.from_arrays(log_odds, d >= 0, box, origin_x_m, origin_y_m, params)

    # ---- geometry -------------------------------------------------------------------------

    @property
    def resolution_m(self) -> float:
        """Cell size (m), from `params`."""
        return self.params.resolution_m

    @property
    def extent(self) -> CellBox | None:
        """Bounding box of every cell ever updated (None while empty)."""
        return self._extent

    @property
    def storage_box(self) -> CellBox | None:
        """The box the backing array covers (>= extent; changes only when the grid grows)."""
        return self._storage

    @property
    def is_empty(self) -> bool:
        """True until some cell has been updated (no `extent` yet)."""
        return self._extent is None

    @property
    def spec(self) -> GridSpec:
        """GridSpec of the current extent (0 x 0 at the anchor while empty)."""
        box = self._extent or CellBox(0, 0, 0, 0)
        return self.spec_of(box)

    def spec_of(self, box: CellBox, factor: int = 1) -> GridSpec:
        """GridSpec of a box on this lattice, or on the lattice `factor` times coarser."""
        return box.spec(self.anchor_x_m, self.anchor_y_m, self.resolution_m * factor)

    @property
    def nbytes(self) -> int:
        """Memory held by the backing arrays (spare capacity included)."""
        arrays = (self._log_odds, self._observed, self._hit_xy, self._hit_n)
        return int(sum(a.nbytes for a in arrays))

    def world_to_cells(self, points: NDArray[np.float64]) -> NDArray[np.int64]:
        """Lattice (row, col) of each world point, valid however the grid grows."""
        p = np.asarray(points, dtype=np.float64).reshape(-1, 2)
        col = np.floor((p[:, 0] - self.anchor_x_m) / self.resolution_m).astype(np.int64)
        row = np.floor((p[:, 1] - self.anchor_y_m) / self.resolution_m).astype(np.int64)
        return np.column_stack((row, col))

    # ---- reading --------------------------------------------------------------------------

    def _extent_view(self, array: NDArray) -> NDArray:
        if self._extent is None or self._storage is None:
            return array[:0, :0]
        view = array[self._extent.slices_in(self._storage)]
        view.flags.writeable = False
        return view

    @property
    def log_odds(self) -> NDArray[np.float32]:
        """Read-only log-odds over the extent (0 where never observed)."""
        return self._extent_view(self._log_odds)

    @property
    def observed(self) -> NDArray[np.bool_]:
        """Read-only mask of cells updated at least once, over the extent."""
        return self._extent_view(self._observed)

    @property
    def hit_sums(self) -> NDArray[np.float32]:
        """(3, rows, cols) over the extent: per cell the sums of the endpoints' x and y offsets
        inside the cell (in cells, each in [0, 1)) and their count (a copy)."""
        if self._extent is None or self._storage is None:
            return np.zeros((3, 0, 0), dtype=np.float32)
        rows, cols = self._extent.slices_in(self._storage)
        out = np.empty((3, *self._extent.shape), dtype=np.float32)
        out[2] = self._hit_n[rows, cols]
        out[:2] = (self._hit_xy[:, rows, cols] + 0.5 * out[2]) / np.float32(HIT_UNITS_PER_CELL)
        return out

    def occupied_hit_means(
        self, box: CellBox, factor: int = 1, frame: CellBox | None = None
    ) -> NDArray[np.float64]:
        """(K, 2) mean hit points of the occupied cells of the `factor`-times-coarser lattice
        over `box` (a box of that lattice), as fractional (row, col) with cell centres at
        integers, counted from the first cell of `frame` (default: `box`).

        A coarse cell pools the hits of the occupied fine cells it covers; an occupied fine cell
        without recorded hits (a map imported without them) counts as one hit at its centre.
        """
        return self.occupied_hit_means_in(boxes_of(box), factor, frame or box)

    def occupied_hit_means_in(
        self, boxes: NDArray[np.int64], factor: int, frame: CellBox
    ) -> NDArray[np.float64]:
        """`occupied_hit_means` of every box of the disjoint (n, 4) boxes [row0, col0, row1,
        col1) of the coarser lattice, box after box, counted from the first cell of `frame`: a
        field refreshed over some boxes reads the obstacles of larger ones around them, in one
        pass."""
        if factor < 1:
            raise ValueError(f"factor must be >= 1, got {factor}")
        if self._storage is None:
            return np.zeros((0, 2))
        corner = np.array([frame.row0, frame.col0, frame.row0, frame.col0])
        return pooled_hit_means(
            self._log_odds,
            self._observed,
            self._hit_xy,
            self._hit_n,
            np.float32(self.params.threshold_log_odds()),
            np.ascontiguousarray(boxes, dtype=np.int64).reshape(-1, 4) - corner,
            factor,
            frame.row0 * factor - self._storage.row0,
            frame.col0 * factor - self._storage.col0,
        )

    def probability(self) -> NDArray[np.float64]:
        """Occupancy probability over the extent (0.5 where never observed)."""
        return 1.0 / (1.0 + np.exp(-self.log_odds.astype(np.float64)))

    def to_int8(self) -> NDArray[np.int8]:
        """ROS OccupancyGrid data over the extent: -1 unknown, 0..100 percent occupied."""
        percent = np.rint(100.0 * self.probability())
        return np.where(self.observed, percent, -1).astype(np.int8)

    def occupied_mask(self, threshold: float | None = None) -> NDArray[np.bool_]:
        """Observed cells with occupancy probability above `threshold` (default: params)."""
        return self.observed & (self.log_odds > self.params.threshold_log_odds(threshold))

    def free_mask(self, threshold: float) -> NDArray[np.bool_]:
        """Observed cells with occupancy probability below `threshold`."""
        return self.observed & (self.log_odds < self.params.threshold_log_odds(threshold))

    def occupied_in(self, box: CellBox, threshold: float | None = None) -> NDArray[np.bool_]:
        """Occupied mask over any lattice box (False outside the stored area)."""
        out = np.zeros(box.shape, dtype=bool)
        if self._storage is None:
            return out
        inner = box.intersection(self._storage)
        if inner.is_empty:
            return out
        src = inner.slices_in(self._storage)
        lo = self._log_odds[src]
        out[inner.slices_in(box)] = self._observed[src] & (
            lo > self.params.threshold_log_odds(threshold)
        )
        return out

    def occupied_in_boxes(
        self, boxes: NDArray[np.int64]
    ) -> tuple[NDArray[np.bool_], NDArray[np.int64]]:
        """The occupied masks (default threshold) of the (n, 4) lattice boxes [row0, col0, row1,
        col1), each row-major and False outside the stored area, concatenated: box k's is
        `flat[starts[k]:starts[k + 1]]`. One pass for many small boxes (the blocks a scan's
        changes dirty), where `occupied_in` per box would cost more in calls than in cells."""
        b = np.ascontiguousarray(boxes, dtype=np.int64).reshape(-1, 4)
        storage = self._storage or CellBox(0, 0, 0, 0)
        return occupied_windows(
            self._log_odds,
            self._observed,
            np.float32(self.params.threshold_log_odds()),
            b,
            storage.row0,
            storage.col0,
        )

    # ---- writing --------------------------------------------------------------------------

    def _reserve(self, box: CellBox) -> CellBox:
        """Make the backing arrays hold `box`, growing as `grown_box` says (amortised copies of
        the used extent only). Returns the (possibly new) storage box."""
        old = self._storage
        if old is not None and old.contains_box(box):
            return old
        new = grown_box(old, box.union(self._extent), self._initial_capacity)
        log_odds = np.zeros(new.shape, dtype=np.float32)
        observed = np.zeros(new.shape, dtype=bool)
        hit_xy = np.zeros((2, *new.shape), dtype=np.uint16)
        hit_n = np.zeros(new.shape, dtype=np.uint8)
        if old is not None and self._extent is not None:
            # Cells outside the extent were never written: only the extent moves.
            src, dst = self._extent.slices_in(old), self._extent.slices_in(new)
            log_odds[dst] = self._log_odds[src]
            observed[dst] = self._observed[src]
            hit_xy[(slice(None), *dst)] = self._hit_xy[(slice(None), *src)]
            hit_n[dst] = self._hit_n[src]
        self._log_odds, self._observed, self._storage = log_odds, observed, new
        self._hit_xy, self._hit_n = hit_xy, hit_n
        self.storage_generation += 1
        return new

    def _clipped_no_return(
        self, origin: NDArray[np.float64], ends: NDArray[np.float64]
    ) -> NDArray[np.float64]:
        """No-return beam ends pulled in to at most no_return_clear_m from the sensor."""
        delta = ends - origin
        length = np.hypot(delta[:, 0], delta[:, 1])
        scale = np.minimum(1.0, self.params.no_return_clear_m / np.maximum(length, 1e-12))
        return origin + delta * scale[:, None]

    def _sensor_model(self) -> tuple[np.float32, ...]:
        """The kernels' float32 constants: miss and hit log-odds, clamps, occupied threshold."""
        p = self.params
        return tuple(
            np.float32(v)
            for v in (p.miss_log_odds, p.hit_log_odds, p.log_odds_min, p.log_odds_max,
                      p.threshold_log_odds())
        )

    def insert_scan(
        self,
        points_world: ArrayLike,
        sensor_origin: ArrayLike,
        no_return_endpoints: ArrayLike | None = None,
    ) -> InsertResult:
        """Clear cells along each beam (end excluded), mark each end occupied, clamp.

        `no_return_endpoints` are points along beams that saw nothing (e.g. at max range): they
        clear free space up to `params.no_return_clear_m` only (that last cell included).
        Invalid input raises before the grid changes.
        """
        hits = _as_points("points_world", points_world)
        origin = np.asarray(sensor_origin, dtype=np.float64).reshape(1, -1)
        origin = _as_points("sensor_origin", origin)
        misses = (
            np.empty((0, 2))
            if no_return_endpoints is None
            else _as_points("no_return_endpoints", no_return_endpoints)
        )
        ranges_m = np.hypot(*(hits - origin).T)
        too_far = ranges_m > self.params.max_range_m
        if too_far.any():
            raise ValueError(
                f"points_world range {ranges_m[too_far][0]:.3f} m exceeds "
                f"max_range_m {self.params.max_range_m} m"
            )
        if hits.shape[0] == 0 and misses.shape[0] == 0:
            return InsertResult(None)

        origin_cell = self.world_to_cells(origin)
        hit_cells = self.world_to_cells(hits)
        miss_ends = self.world_to_cells(self._clipped_no_return(origin[0], misses))
        # A Bresenham ray stays inside the bounding box of its two end cells.
        box = CellBox.around(np.concatenate((origin_cell, hit_cells, miss_ends)))
        storage = self._reserve(box)

        corner = np.array([storage.row0, storage.col0])
        stored_hits = hit_cells - corner
        model = self._sensor_model()
        flipped = update_cells(
            self._log_odds,
            self._observed,
            np.array([box.row0, box.col0, box.row1, box.col1]) - np.tile(corner, 2),
            origin_cell[0] - corner,
            stored_hits,
            miss_ends - corner,
            *model,
        )
        accumulate_hits(self._hit_xy, self._hit_n, stored_hits, self._hit_units(hits, hit_cells))
        rows, cols = stored_hits[:, 0], stored_hits[:, 1]

        self._extent = box.union(self._extent)
        self.revision += 1
        moved = self._observed[rows, cols] & (self._log_odds[rows, cols] > model[-1])
        return InsertResult(box, flipped + corner, hit_cells[moved])

    def insert_scans(self, batch: RayBatch) -> CellBox | None:
        """`insert_scan` of each scan of `batch` in turn, to the same map bit for bit, in one
        compiled pass: a redraw of many keyframes pays numpy's per-call costs once, not per
        scan. Returns the box of every cell updated (None: none). Invalid input raises, naming
        the scan, before the grid changes."""
        b = batch
        for name in ("origins", "hits", "misses"):
            bad = ~np.isfinite(getattr(b, name)).all(axis=1)
            if bad.any():
                raise ValueError(f"{b.first_bad(name, bad)} is not finite")
        hit_counts, miss_counts = np.diff(b.hit_starts), np.diff(b.miss_starts)
        ranges_m = np.hypot(*(b.hits - np.repeat(b.origins, hit_counts, axis=0)).T)
        too_far = ranges_m > self.params.max_range_m
        if too_far.any():
            raise ValueError(
                f"{b.first_bad('hits', too_far)}: range {ranges_m[too_far][0]:.3f} m exceeds "
                f"max_range_m {self.params.max_range_m} m"
            )
        used = (hit_counts > 0) | (miss_counts > 0)
        if not used.any():
            return None
        misses = self._clipped_no_return(np.repeat(b.origins, miss_counts, axis=0), b.misses)
        origin_cells = self.world_to_cells(b.origins)
        hit_cells = self.world_to_cells(b.hits)
        miss_ends = self.world_to_cells(misses)
        box = CellBox.around(np.concatenate((origin_cells[used], hit_cells, miss_ends)))
        storage = self._reserve(box)
        corner = np.array([storage.row0, storage.col0])
        insert_many(
            self._log_odds, self._observed, self._hit_xy, self._hit_n,
            origin_cells - corner, hit_cells - corner, b.hit_starts, miss_ends - corner,
            b.miss_starts, self._hit_units(b.hits, hit_cells), *self._sensor_model(),
        )
        self._extent = box.union(self._extent)
        self.revision += int(np.count_nonzero(used))
        return box

    def _hit_units(
        self, hits: NDArray[np.float64], hit_cells: NDArray[np.int64]
    ) -> NDArray[np.uint16]:
        """Each endpoint's (x, y) offset inside its cell in 1/256 (see the module docstring)."""
        offset = np.column_stack(
            (
                (hits[:, 0] - self.anchor_x_m) / self.resolution_m - hit_cells[:, 1],
                (hits[:, 1] - self.anchor_y_m) / self.resolution_m - hit_cells[:, 0],
            )
        )
        units = np.clip(np.floor(offset * HIT_UNITS_PER_CELL), 0, HIT_UNITS_PER_CELL - 1)
        return units.astype(np.uint16)
