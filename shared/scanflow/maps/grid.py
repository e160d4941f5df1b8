"""Where a 2D grid sits in the world: origin, resolution and size, and world <-> cell maps.

Cell (row, col) covers world x in [origin_x + col*res, origin_x + (col+1)*res) and y likewise
with rows; its value is taken to sit at the cell centre. Row index grows with y (as in ROS
map_server data before the image is flipped for display).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numba import njit
from numpy.typing import NDArray


def finite_rows(name: str, points: NDArray[np.float64]) -> NDArray[np.float64]:
    """`points` (N, 2) when every row is finite; else ValueError naming `name` and a bad row."""
    bad = ~np.isfinite(points).all(axis=1)
    if bad.any():
        raise ValueError(f"{name} has {int(bad.sum())} non-finite rows, first {points[bad][0]}")
    return points


def corner_below(
    lowest: NDArray[np.float64], step_m: float, offset_m: float | tuple[float, float] = 0.0
) -> NDArray[np.float64]:
    """The highest lattice corner offset + k * step at or below `lowest`, per axis. floor(x /
    step) * step can round to just above x (x = -127.70000000000002, step 0.1): one step lower
    then, so that x never falls in the cell before a grid's first."""
    corner = np.floor((lowest - offset_m) / step_m) * step_m + offset_m
    return corner - step_m * (lowest < corner)


@dataclass(frozen=True, slots=True)
class GridSpec:
    """Geometry of a grid: origin is the world position of the corner of cell (0, 0)."""

    origin_x_m: float
    origin_y_m: float
    resolution_m: float
    rows: int
    cols: int

    def __post_init__(self) -> None:
        if not (math.isfinite(self.resolution_m) and self.resolution_m > 0):
            raise ValueError(f"resolution_m must be positive and finite, got {self.resolution_m}")
        if self.rows < 0 or self.cols < 0:
            raise ValueError(f"grid size must be non-negative, got {self.rows}x{self.cols}")
        if not (math.isfinite(self.origin_x_m) and math.isfinite(self.origin_y_m)):
            raise ValueError("grid origin must be finite")

    @property
    def shape(self) -> tuple[int, int]:
        """(rows, cols), the numpy shape of the grid's arrays."""
        return (self.rows, self.cols)

    @property
    def width_m(self) -> float:
        """Extent along x: cols times the resolution."""
        return self.cols * self.resolution_m

    @property
    def height_m(self) -> float:
        """Extent along y: rows times the resolution."""
        return self.rows * self.resolution_m

    @staticmethod
    def covering(points: NDArray[np.float64], resolution_m: float, margin_m: float) -> GridSpec:
        """The smallest resolution-aligned grid holding the points plus a margin."""
        p = finite_rows("points", np.asarray(points, dtype=np.float64).reshape(-1, 2))
        if p.size == 0:
            lo = np.array([-margin_m, -margin_m])
            hi = np.array([margin_m, margin_m])
        else:
            lo = p.min(axis=0) - margin_m
            hi = p.max(axis=0) + margin_m
        lo = corner_below(lo, resolution_m)
        cols = math.ceil((hi[0] - lo[0]) / resolution_m) + 1
        rows = math.ceil((hi[1] - lo[1]) / resolution_m) + 1
        return GridSpec(float(lo[0]), float(lo[1]), resolution_m, rows, cols)

    def world_to_cell(self, points: NDArray[np.float64]) -> NDArray[np.int64]:
        """Integer (row, col) of the cell holding each (x, y) point; may fall outside the grid."""
        p = np.asarray(points, dtype=np.float64).reshape(-1, 2)
        col = np.floor((p[:, 0] - self.origin_x_m) / self.resolution_m).astype(np.int64)
        row = np.floor((p[:, 1] - self.origin_y_m) / self.resolution_m).astype(np.int64)
        return np.column_stack((row, col))

    def world_to_continuous(self, points: NDArray[np.float64]) -> NDArray[np.float64]:
        """Fractional (row, col) with cell centres at integers: the frame bilinear sampling uses."""
        p = np.asarray(points, dtype=np.float64).reshape(-1, 2)
        col = (p[:, 0] - self.origin_x_m) / self.resolution_m - 0.5
        row = (p[:, 1] - self.origin_y_m) / self.resolution_m - 0.5
        return np.column_stack((row, col))

    def cell_centers(self, cells: NDArray[np.int64] | NDArray[np.float64]) -> NDArray[np.float64]:
        """World (x, y) of the centres of (row, col) cells; of fractional (row, col) too, cell
        centres at integers (e.g. `OccupancyGrid.occupied_hit_means`)."""
        c = np.asarray(cells).reshape(-1, 2)
        x = self.origin_x_m + (c[:, 1] + 0.5) * self.resolution_m
        y = self.origin_y_m + (c[:, 0] + 0.5) * self.resolution_m
        return np.column_stack((x, y))

    def contains(self, cells: NDArray[np.int64]) -> NDArray[np.bool_]:
        """True for each (row, col) cell that lies inside the grid."""
        c = np.asarray(cells).reshape(-1, 2)
        return (c[:, 0] >= 0) & (c[:, 0] < self.rows) & (c[:, 1] >= 0) & (c[:, 1] < self.cols)

    def coarsened(self, factor: int) -> GridSpec:
        """The same area at `factor` times the cell size (rounded up to whole cells)."""
        if factor < 1:
            raise ValueError(f"factor must be >= 1, got {factor}")
        return GridSpec(
            self.origin_x_m,
            self.origin_y_m,
            self.resolution_m * factor,
            -(-self.rows // factor),
            -(-self.cols // factor),
        )


@dataclass(frozen=True, slots=True)
class CellBox:
    """A half-open box of integer cells [row0, row1) x [col0, col1) on a fixed world lattice.

    Growable maps index cells from a fixed lattice anchor, so boxes stay valid when the stored
    array grows; they describe storage, extents and the dirty regions of incremental updates.
    """

    row0: int
    col0: int
    row1: int
    col1: int

    def __post_init__(self) -> None:
        if self.row1 < self.row0 or self.col1 < self.col0:
            raise ValueError(
                f"CellBox bounds inverted: rows [{self.row0}, {self.row1}), "
                f"cols [{self.col0}, {self.col1})"
            )

    @staticmethod
    def around(cells: NDArray[np.int64]) -> CellBox:
        """The smallest box holding every (row, col) cell given (at least one)."""
        c = np.asarray(cells).reshape(-1, 2)
        if c.shape[0] == 0:
            raise ValueError("CellBox.around needs at least one cell, got none")
        lo = c.min(axis=0)
        hi = c.max(axis=0) + 1
        return CellBox(int(lo[0]), int(lo[1]), int(hi[0]), int(hi[1]))

    @property
    def shape(self) -> tuple[int, int]:
        """(rows, cols) the box spans."""
        return (self.row1 - self.row0, self.col1 - self.col0)

    @property
    def is_empty(self) -> bool:
        """True when the box holds no cell (zero rows or zero cols)."""
        return self.row1 == self.row0 or self.col1 == self.col0

    def union(self, other: CellBox | None) -> CellBox:
        """The bounding box of both boxes (`self` when `other` is None)."""
        if other is None:
            return self
        return CellBox(
            min(self.row0, other.row0),
            min(self.col0, other.col0),
            max(self.row1, other.row1),
            max(self.col1, other.col1),
        )

    def intersection(self, other: CellBox) -> CellBox:
        """The overlap of two boxes (an empty box anchored inside `self` when they are apart)."""
        row0 = max(self.row0, other.row0)
        col0 = max(self.col0, other.col0)
        return CellBox(
            row0, col0, max(row0, min(self.row1, other.row1)), max(col0, min(self.col1, other.col1))
        )

    def contains_box(self, other: CellBox) -> bool:
        """True when `other` lies entirely inside this box."""
        return (
            self.row0 <= other.row0
            and self.col0 <= other.col0
            and other.row1 <= self.row1
            and other.col1 <= self.col1
        )

    def expanded(self, cells: int) -> CellBox:
        """The box grown by `cells` on every side."""
        return CellBox(
            self.row0 - cells, self.col0 - cells, self.row1 + cells, self.col1 + cells
        )

    def shifted(self, rows: int, cols: int) -> CellBox:
        """The box moved by `rows` and `cols`."""
        return CellBox(self.row0 + rows, self.col0 + cols, self.row1 + rows, self.col1 + cols)

    def coarsened(self, factor: int) -> CellBox:
        """The box of `factor`-times-larger lattice cells covering this one (same anchor)."""
        if factor < 1:
            raise ValueError(f"factor must be >= 1, got {factor}")
        return CellBox(
            self.row0 // factor,
            self.col0 // factor,
            -(-self.row1 // factor),
            -(-self.col1 // factor),
        )

    def refined(self, factor: int) -> CellBox:
        """The same area on the lattice `factor` times finer (inverse of `coarsened`)."""
        if factor < 1:
            raise ValueError(f"factor must be >= 1, got {factor}")
        return CellBox(
            self.row0 * factor, self.col0 * factor, self.row1 * factor, self.col1 * factor
        )

    def spec(self, anchor_x_m: float, anchor_y_m: float, resolution_m: float) -> GridSpec:
        """The GridSpec of this box on a lattice whose cell (0, 0) has its corner at the anchor."""
        rows, cols = self.shape
        return GridSpec(
            anchor_x_m + self.col0 * resolution_m,
            anchor_y_m + self.row0 * resolution_m,
            resolution_m,
            rows,
            cols,
        )

    def slices_in(self, outer: CellBox) -> tuple[slice, slice]:
        """Index slices selecting this box inside an array that stores `outer`."""
        if not outer.contains_box(self):
            raise ValueError(f"{self} is not inside {outer}")
        return (
            slice(self.row0 - outer.row0, self.row1 - outer.row0),
            slice(self.col0 - outer.col0, self.col1 - outer.col0),
        )


def _grown_axis(old: tuple[int, int], need: tuple[int, int]) -> tuple[int, int]:
    """[lo, hi) holding `need`: `old` if it does, else `need` plus half its size on each side
    that grew and at most a quarter (of what `old` had) on a side that did not."""
    if old[0] <= need[0] and need[1] <= old[1]:
        return old
    spare = max((need[1] - need[0]) // 2, 1)
    lo = need[0] - spare if need[0] < old[0] else max(old[0], need[0] - spare // 2)
    hi = need[1] + spare if need[1] > old[1] else min(old[1], need[1] + spare // 2)
    return lo, hi


def grown_box(old: CellBox | None, need: CellBox, minimum_cells: int = 1) -> CellBox:
    """The box a growable array should cover to hold `need` (its used cells plus the new ones).

    `old` itself while it holds `need`; else each axis that must grow gets `need` plus 50 % spare
    on the side(s) it grew, keeping up to 25 % on the other: an array that keeps growing is
    reallocated O(log size) times per axis and stays within 2x of `need` per axis, 4x in area
    (doubling the whole old box instead reached 12x on a long-range log). The first box is `need`
    centred in at least `minimum_cells` per axis.
    """
    if old is None:
        rows, cols = need.shape
        pad_r, pad_c = max(minimum_cells - rows, 0), max(minimum_cells - cols, 0)
        return CellBox(
            need.row0 - pad_r // 2,
            need.col0 - pad_c // 2,
            need.row1 + pad_r - pad_r // 2,
            need.col1 + pad_c - pad_c // 2,
        )
    r0, r1 = _grown_axis((old.row0, old.row1), (need.row0, need.row1))
    c0, c1 = _grown_axis((old.col0, old.col1), (need.col0, need.col1))
    return CellBox(r0, c0, r1, c1)


@njit(cache=True)
def _tile_runs(cells, tile):  # type: ignore[no-untyped-def]
    """See tile_boxes (at least one cell)."""
    rows, cols = cells[:, 0] // tile, cells[:, 1] // tile
    row0, col0 = rows.min(), cols.min()
    width = cols.max() - col0 + 2  # a spare column: runs never wrap to the next row
    keys = np.unique((rows - row0) * width + (cols - col0))
    out = np.empty((len(keys), 4), dtype=np.int64)
    n = 0
    for i in range(len(keys)):
        if i > 0 and keys[i] == keys[i - 1] + 1:
            out[n - 1, 3] += tile
            continue
        row, col = keys[i] // width + row0, keys[i] % width + col0
        out[n, 0], out[n, 1] = row * tile, col * tile
        out[n, 2], out[n, 3] = (row + 1) * tile, (col + 1) * tile
        n += 1
    return out[:n]


def tile_boxes(cells: NDArray[np.int64], tile: int) -> NDArray[np.int64]:
    """The `tile` x `tile` tiles of the lattice (aligned to cell (0, 0)) holding some of the
    (K, 2) `cells`, as boxes (n, 4): rows of [row0, col0, row1, col1), each a run of adjacent
    tiles along a row of tiles, in row-major order.

    Views track what a scan changed by tile: a few boxes along the walls it saw, where one
    bounding box would often span the map."""
    if tile < 1:
        raise ValueError(f"tile must be >= 1, got {tile}")
    c = np.ascontiguousarray(cells, dtype=np.int64).reshape(-1, 2)
    if len(c) == 0:
        return np.zeros((0, 4), dtype=np.int64)
    return _tile_runs(c, tile)


@njit(cache=True)
def _disjoint_cover(a):  # type: ignore[no-untyped-def]
    """See disjoint_cover (non-empty boxes only)."""
    rows = np.unique(np.concatenate((a[:, 0], a[:, 2])))
    cols = np.unique(np.concatenate((a[:, 1], a[:, 3])))
    bands, spans = len(rows) - 1, len(cols) - 1
    covered = np.zeros((bands, spans), dtype=np.bool_)
    for k in range(a.shape[0]):
        r0, r1 = np.searchsorted(rows, a[k, 0]), np.searchsorted(rows, a[k, 2])
        c0, c1 = np.searchsorted(cols, a[k, 1]), np.searchsorted(cols, a[k, 3])
        covered[r0:r1, c0:c1] = True
    out = np.empty((bands * spans, 4), dtype=np.int64)
    n = 0
    # The runs of the band above: start and end column (compressed) and their box in `out`.
    above = np.empty((2, 3, spans), dtype=np.int64)
    n_above = 0
    for b in range(bands):
        here = above[(b + 1) % 2]
        prev = above[b % 2]
        n_here = j = c = 0
        while c < spans:
            if not covered[b, c]:
                c += 1
                continue
            start = c
            while c < spans and covered[b, c]:
                c += 1
            while j < n_above and prev[0, j] < start:
                j += 1
            if j < n_above and prev[0, j] == start and prev[1, j] == c:
                k = prev[2, j]
                out[k, 2] = rows[b + 1]
            else:
                k = n
                out[k, 0], out[k, 1] = rows[b], cols[start]
                out[k, 2], out[k, 3] = rows[b + 1], cols[c]
                n += 1
            here[0, n_here], here[1, n_here], here[2, n_here] = start, c, k
            n_here += 1
        n_above = n_here
    return out[:n].copy()


def disjoint_cover(boxes: NDArray[np.int64]) -> NDArray[np.int64]:
    """Disjoint boxes whose union is the union of `boxes` ((n, 4) rows of [row0, col0, row1,
    col1); empty ones ignored), in the same form.

    The plane is cut at every box edge; each band between consecutive row edges is covered by
    maximal runs of column intervals, and a run continues the box of the band above when it
    spans the same columns. A view refreshed box by box then recomputes no cell twice where
    the neighbourhoods of nearby changes overlap.
    """
    a = np.asarray(boxes, dtype=np.int64).reshape(-1, 4)
    a = a[(a[:, 2] > a[:, 0]) & (a[:, 3] > a[:, 1])]
    if len(a) <= 1:
        return a
    return _disjoint_cover(a)


def boxes_of(box: CellBox | None) -> NDArray[np.int64]:
    """`box` as boxes in the (n, 4) form of `disjoint_cover` (no row for None or an empty box)."""
    if box is None or box.is_empty:
        return np.zeros((0, 4), dtype=np.int64)
    return np.array([[box.row0, box.col0, box.row1, box.col1]], dtype=np.int64)


def clipped(boxes: NDArray[np.int64], within: CellBox) -> NDArray[np.int64]:
    """The parts of (n, 4) `boxes` inside `within`, boxes left empty dropped."""
    lo = np.array([within.row0, within.col0, within.row0, within.col0])
    hi = np.array([within.row1, within.col1, within.row1, within.col1])
    inside = np.clip(np.asarray(boxes, dtype=np.int64).reshape(-1, 4), lo, hi)
    return inside[(inside[:, 2] > inside[:, 0]) & (inside[:, 3] > inside[:, 1])]


class BoxUnion:
    """A growing union of boxes (where a view is out of date), in the (n, 4) form of
    `disjoint_cover`. Parts are kept as added and merged into one disjoint cover once there are
    `MERGE_AFTER` of them, so a union that is seldom taken stays bounded by the area it covers.
    """

    MERGE_AFTER = 64

    def __init__(self) -> None:
        self._parts: list[NDArray[np.int64]] = []

    def __bool__(self) -> bool:
        """Whether some box was added since the last `take`."""
        return bool(self._parts)

    def add(self, boxes: NDArray[np.int64]) -> None:
        """Add (n, 4) boxes; past MERGE_AFTER parts, all are merged into one disjoint cover."""
        if len(boxes):
            self._parts.append(boxes)
        if len(self._parts) > self.MERGE_AFTER:
            self._parts = [disjoint_cover(np.concatenate(self._parts))]

    def take(self) -> NDArray[np.int64]:
        """The union as disjoint boxes (no row: empty); the union is empty afterwards."""
        parts, self._parts = self._parts, []
        if not parts:
            return boxes_of(None)
        return disjoint_cover(np.concatenate(parts))
