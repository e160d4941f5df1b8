"""Nearest-neighbour association for ICP-family matchers, and the outlier rules they share.

`GridIndex` over the target points: a uniform bucket grid (points sorted by cell). Its lookups
are numba functions callable from compiled solver loops: at 180-361 points a scipy cKDTree
query costs 0.1-0.3 ms per iteration from Python (profiled), the compiled grid lookup ~20 us.
A lookup searches square rings of cells outward from the query and stops once no farther cell
can hold a nearer point, so a wide gate costs little on a dense (densified) target.
Outlier rejection: a distance gate that adapts to the robust spread of the current association
(KISS-ICP's idea of a data-driven threshold), and trimming to a fixed inlier fraction.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numba import njit
from numpy.typing import NDArray

from scanflow.matching.surface import GAP_BASE_M, GAP_PER_RANGE

# Robust sigma from the median absolute deviation of a Gaussian.
MAD_TO_SIGMA = 1.4826
# Grid cells grow beyond the requested size when the target would need more cells than this.
MAX_GRID_CELLS = 1 << 16
# A lookup skips cells farther than this factor x its bound (> 1: rounding never makes it skip
# one that holds a point within the bound, only visit one more).
CELL_SLACK = 1.0 + 1e-9


@njit(cache=True)
def adaptive_gate_m(distances_m: NDArray[np.float64], floor_m: float, ceiling_m: float) -> float:
    """Next association gate: 3 robust sigmas of the current distances, within [floor, ceiling]."""
    if len(distances_m) == 0:
        return ceiling_m
    gate = 3.0 * MAD_TO_SIGMA * np.median(distances_m)
    return min(max(gate, floor_m), ceiling_m)


# What compiled lookups take: (points, order, starts, origin_x_m, origin_y_m, cell_m, cols, rows).
GridArrays = tuple[
    NDArray[np.float64], NDArray[np.int64], NDArray[np.int64], float, float, float, int, int
]


@dataclass(frozen=True, eq=False)
class GridIndex:
    """Bucket grid over the target points (sorted by cell) for compiled lookups."""

    points: NDArray[np.float64]
    order: NDArray[np.int64]
    starts: NDArray[np.int64]
    origin_x_m: float
    origin_y_m: float
    cell_m: float
    cols: int
    rows: int

    @staticmethod
    def build(points: NDArray[np.float64], cell_m: float = 0.25) -> GridIndex:
        """Bucket the points into cells of `cell_m` (larger if the grid would be too big)."""
        if not cell_m > 0.0:
            raise ValueError(f"cell_m must be > 0, got {cell_m}")
        if len(points) == 0:
            raise ValueError("a grid needs at least one point")
        return GridIndex(points, *_bucket(points, cell_m, MAX_GRID_CELLS))

    @property
    def arrays(self) -> GridArrays:
        """The grid as one tuple for the numba lookups (`grid_k_nearest`)."""
        return (self.points, self.order, self.starts, self.origin_x_m, self.origin_y_m,
                self.cell_m, self.cols, self.rows)


@njit(cache=True)
def _bucket(
    points: NDArray[np.float64], cell_m: float, max_cells: int
) -> tuple[NDArray[np.int64], NDArray[np.int64], float, float, float, int, int]:
    """The grid's layout in one compiled call (a match builds two or three): cells of `cell_m`,
    larger when more than `max_cells` would cover the points, a cell of margin around them."""
    n = len(points)
    lo_x, lo_y = points[:, 0].min(), points[:, 1].min()
    hi_x, hi_y = points[:, 0].max(), points[:, 1].max()
    cell = max(cell_m, math.sqrt((hi_x - lo_x + 2 * cell_m) * (hi_y - lo_y + 2 * cell_m)
                                 / max_cells))
    ox, oy = lo_x - cell, lo_y - cell
    cols = int((hi_x - ox) / cell) + 2
    rows = int((hi_y - oy) / cell) + 2
    keys = np.empty(n, dtype=np.int64)
    for i in range(n):
        keys[i] = int((points[i, 1] - oy) / cell) * cols + int((points[i, 0] - ox) / cell)
    order = np.argsort(keys, kind="mergesort").astype(np.int64)
    starts = np.zeros(rows * cols + 1, dtype=np.int64)
    for i in range(n):
        starts[keys[i] + 1] += 1
    for c in range(rows * cols):
        starts[c + 1] += starts[c]
    return order, starts, ox, oy, cell, cols, rows


@njit(cache=True)
def grid_k_nearest(
    grid: GridArrays,
    qx: float,
    qy: float,
    radius_m: float,
    best_d2: NDArray[np.float64],
    best_j: NDArray[np.int64],
) -> int:
    """Fill best_j / best_d2 (caller's buffers of length k, nearest first) with the k nearest
    target points within radius_m of (qx, qy), -1 / inf padded; return how many were found."""
    points, order, starts, ox, oy, cell, cols, rows = grid
    k = len(best_j)
    best_d2[:] = np.inf
    best_j[:] = -1
    cx = math.floor((qx - ox) / cell)
    cy = math.floor((qy - oy) / cell)
    r2 = radius_m * radius_m
    # Square rings of cells outward from the query's cell: a point outside rings 0..r-1 lies
    # beyond their block's nearest edge, so the search stops once the k-th best (or the
    # radius) is nearer than that; within a ring, a cell whose nearest edge is beyond them
    # cannot give a point. Both bounds carry CELL_SLACK against rounding.
    for ring in range(math.ceil(radius_m / cell) + 1):
        bound = min(r2, best_d2[k - 1]) * CELL_SLACK
        if ring > 0:
            inner = min(qx - (ox + (cx - ring + 1) * cell), ox + (cx + ring) * cell - qx,
                        qy - (oy + (cy - ring + 1) * cell), oy + (cy + ring) * cell - qy)
            if bound <= inner * inner:
                break
        for yy in range(max(cy - ring, 0), min(cy + ring + 1, rows)):
            edge_row = yy == cy - ring or yy == cy + ring
            gap_y = max(oy + yy * cell - qy, qy - (oy + (yy + 1) * cell), 0.0)
            for xx in range(cx - ring, cx + ring + 1, 1 if edge_row else 2 * ring):
                if xx < 0 or xx >= cols:
                    continue
                gap_x = max(ox + xx * cell - qx, qx - (ox + (xx + 1) * cell), 0.0)
                if gap_x * gap_x + gap_y * gap_y > min(r2, best_d2[k - 1]) * CELL_SLACK:
                    continue
                c = yy * cols + xx
                for s in range(starts[c], starts[c + 1]):
                    j = order[s]
                    dx = points[j, 0] - qx
                    dy = points[j, 1] - qy
                    d2 = dx * dx + dy * dy
                    if d2 <= r2 and d2 < best_d2[k - 1]:
                        m = k - 1
                        while m > 0 and best_d2[m - 1] > d2:
                            best_d2[m] = best_d2[m - 1]
                            best_j[m] = best_j[m - 1]
                            m -= 1
                        best_d2[m] = d2
                        best_j[m] = j
    count = 0
    while count < k and best_j[count] >= 0:
        count += 1
    return count


@njit(cache=True)
def grid_nearest_all(
    grid: GridArrays, queries: NDArray[np.float64], radii_m: NDArray[np.float64]
) -> NDArray[np.int64]:
    """Index of each query's nearest grid point within its radius radii_m[i] (-1 if none)."""
    best_d2 = np.empty(1)
    best_j = np.empty(1, dtype=np.int64)
    out = np.empty(len(queries), dtype=np.int64)
    for i in range(len(queries)):
        grid_k_nearest(grid, queries[i, 0], queries[i, 1], radii_m[i], best_d2, best_j)
        out[i] = best_j[0]
    return out


@njit(cache=True)
def grid_within_any(
    grid: GridArrays, queries: NDArray[np.float64], radius_m: float
) -> NDArray[np.bool_]:
    """Which grid points lie within radius_m of at least one query (each query visits only
    the cells its disc's bounding box covers)."""
    points, order, starts, ox, oy, cell, cols, rows = grid
    near = np.zeros(len(points), dtype=np.bool_)
    r2 = radius_m * radius_m
    for i in range(len(queries)):
        qx, qy = queries[i, 0], queries[i, 1]
        x0 = max(math.floor((qx - radius_m - ox) / cell), 0)
        x1 = min(math.floor((qx + radius_m - ox) / cell), cols - 1)
        y0 = max(math.floor((qy - radius_m - oy) / cell), 0)
        y1 = min(math.floor((qy + radius_m - oy) / cell), rows - 1)
        for yy in range(y0, y1 + 1):
            for xx in range(x0, x1 + 1):
                c = yy * cols + xx
                for s in range(starts[c], starts[c + 1]):
                    j = order[s]
                    dx = points[j, 0] - qx
                    dy = points[j, 1] - qy
                    if dx * dx + dy * dy <= r2:
                        near[j] = True
    return near


# Thinning of a dense point target (`thin_dense_target`): bearing bins of this width seen from
# the target's origin, split along the range at a gap (an occlusion edge) or a depth (a surface
# running away from the origin), both far above range noise: a cut through a wall's noise would
# split its points into two parallel walls, each biased by half the noise.
THIN_BELOW_DEG = 0.4
THIN_GAP_M = 0.05
THIN_DEPTH_M = 0.2


@njit(cache=True)
def _depth_chunks(
    bins: NDArray[np.int64], ranges: NDArray[np.float64], gap_m: float, depth_m: float
) -> NDArray[np.int64]:
    """Cluster label of each point sorted by (bin, range): a new cluster starts at a new bin,
    a range gap over gap_m, or a range depth_m beyond the cluster's first."""
    labels = np.empty(len(bins), dtype=np.int64)
    label = 0
    first_m = ranges[0]
    labels[0] = 0
    for i in range(1, len(bins)):
        if (bins[i] != bins[i - 1] or ranges[i] - ranges[i - 1] > gap_m
                or ranges[i] - first_m > depth_m):
            label += 1
            first_m = ranges[i]
        labels[i] = label
    return labels


@njit(cache=True)
def _bearing_bins(points: NDArray[np.float64], width: float) -> NDArray[np.int64]:
    """Each point's bearing bin, `width` rad wide, seen from the origin."""
    return np.floor(np.arctan2(points[:, 1], points[:, 0]) / width).astype(np.int64)


@njit(cache=True)
def _any_shared(bins: NDArray[np.int64]) -> bool:
    """Whether two of the bins are the same (the common answer, no, in one compiled call)."""
    ordered = np.sort(bins)
    return bool(np.any(ordered[1:] == ordered[:-1]))


def thin_dense_target(
    points: NDArray[np.float64], below_deg: float = THIN_BELOW_DEG
) -> NDArray[np.float64]:
    """`points` as given, or, where two or more share a bearing bin `below_deg` wide seen from
    the origin (and a range chunk: THIN_GAP_M, THIN_DEPTH_M), the centroid of each such cluster, in
    bearing order.

    Why: a target line is fitted over a point's k nearest neighbours, and an ICP pair is a
    nearest point, both tuned on scans of 180-361 beams (>= 0.5 deg apart). On a denser target
    (3,000+ beams: RPLidar S2/S3, an accumulated point set) the k nearest lie a few mm apart and
    the range noise (~1 cm) dominates their scatter: the fit fails the flatness test, or points
    anywhere, and nearest-point pairs sit inside a band of noise. A line's fit needs an extent
    of ~15 noise sigmas to pass the flatness test; averaging the beams of each `below_deg` bin
    gives the target the spacing the fits were tuned for and cuts the noise by the square root
    of the beams merged (bins along the bearing, not a Cartesian voxel grid: range noise is
    radial, and cells about as small as the noise split a wall's points by their noise into
    two parallel walls). A scan whose beams are >= 0.5 deg apart has at most one point per bin,
    so it comes back as it is, the very same array. Like the free-space check, this reads a
    point target as seen from its origin.
    """
    if below_deg <= 0.0 or len(points) < 2:
        return points
    width = math.radians(below_deg)
    bins = _bearing_bins(np.ascontiguousarray(points, dtype=np.float64), width)
    if not _any_shared(bins):
        return points
    ranges = np.hypot(points[:, 0], points[:, 1])
    order = np.lexsort((ranges, bins))
    labels = _depth_chunks(bins[order], ranges[order], THIN_GAP_M, THIN_DEPTH_M)
    count = int(labels[-1]) + 1
    sizes = np.bincount(labels, minlength=count).astype(np.float64)
    return np.column_stack((
        np.bincount(labels, points[order, 0], count) / sizes,
        np.bincount(labels, points[order, 1], count) / sizes,
    ))


@njit(cache=True)
def partner_reach_m(
    x: float, y: float, radius_m: float, gap_base_m: float, gap_per_range: float
) -> float:
    """How far a point at (x, y) reaches for a line partner: `radius_m`, or as far as one
    surface spans at its range (`surface_gap_m`: gap_base_m + gap_per_range x range), if
    that is farther."""
    return max(radius_m, gap_base_m + gap_per_range * math.hypot(x, y))


@njit(cache=True)
def _lines(
    grid: GridArrays, k: int, radius_m: float, fit_radius_m: float, max_flatness: float,
    gap_base_m: float, gap_per_range: float, wanted: NDArray[np.bool_],
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.bool_], NDArray[np.int64],
           NDArray[np.float64]]:
    n = len(grid[0])
    normals = np.zeros((n, 2))
    centres = np.zeros((n, 2))
    ok = np.zeros(n, dtype=np.bool_)
    neighbours = np.full((n, k), -1, dtype=np.int64)
    spread = np.zeros(n)
    out = (normals, centres, ok, neighbours, spread)
    asked = np.flatnonzero(wanted)
    _fit_lines(asked, grid, radius_m, fit_radius_m, max_flatness, gap_base_m, gap_per_range, out)
    # A wanted two-point line's partner, whose own patch judges it (`unconfirmed_patches`).
    partners = np.empty(len(asked), dtype=np.int64)
    count = 0
    for i in asked:
        j = neighbours[i, 1]
        if ok[i] and j >= 0 and (k == 2 or neighbours[i, 2] < 0) and not wanted[j]:
            partners[count] = j
            count += 1
    _fit_lines(np.unique(partners[:count]), grid, radius_m, fit_radius_m, max_flatness,
               gap_base_m, gap_per_range, out)
    return out


@njit(cache=True)
def _fit_lines(  # type: ignore[no-untyped-def]
    indices, grid, radius_m, fit_radius_m, max_flatness, gap_base_m, gap_per_range, out,
):
    # The lines of the points `indices` into their rows of `out` (see `target_lines`).
    points = grid[0]
    normals, centres, ok, neighbours, spread = out
    k = neighbours.shape[1]
    best_d2 = np.empty(k)
    best_j = np.empty(k, dtype=np.int64)
    for i in indices:
        # Up to k neighbours within the fit radius (as many as the local density gives, so
        # sparse scans keep short lines and dense ones average noise), else the two-point line.
        count = grid_k_nearest(grid, points[i, 0], points[i, 1], fit_radius_m, best_d2, best_j)
        if count < 2:
            reach = partner_reach_m(points[i, 0], points[i, 1], radius_m, gap_base_m,
                                    gap_per_range)
            count = min(grid_k_nearest(grid, points[i, 0], points[i, 1], reach, best_d2,
                                       best_j), 2)
        if count < 2:
            continue
        mx = 0.0
        my = 0.0
        for m in range(count):
            mx += points[best_j[m], 0]
            my += points[best_j[m], 1]
        mx /= count
        my /= count
        sxx = 0.0
        syy = 0.0
        sxy = 0.0
        for m in range(count):
            dx = points[best_j[m], 0] - mx
            dy = points[best_j[m], 1] - my
            sxx += dx * dx
            syy += dy * dy
            sxy += dx * dy
        # Closed-form eigen-decomposition of the 2x2 scatter: major axis angle and eigenvalues.
        half_tr = 0.5 * (sxx + syy)
        disc = math.sqrt(max(0.25 * (sxx - syy) ** 2 + sxy * sxy, 0.0))
        lam_max = half_tr + disc
        lam_min = half_tr - disc
        if lam_max <= 0.0 or lam_min > max_flatness * lam_max:
            continue
        phi = 0.5 * math.atan2(2.0 * sxy, sxx - syy)
        normals[i, 0] = -math.sin(phi)
        normals[i, 1] = math.cos(phi)
        centres[i, 0] = mx
        centres[i, 1] = my
        neighbours[i, :count] = best_j[:count]
        spread[i] = lam_max - lam_min
        ok[i] = True


@dataclass(frozen=True, eq=False)
class TargetLines:
    """The line fitted through each target point's neighbourhood (total least squares).

    `normals` and `centres` (the neighbours' centroid) define the line; `ok` is False where it
    is unusable; `neighbours` (-1 padded) and `spread_m2` (major minus minor scatter
    eigenvalue) let the covariance propagate the target points' noise through the fit.
    """

    normals: NDArray[np.float64]
    centres: NDArray[np.float64]
    ok: NDArray[np.bool_]
    neighbours: NDArray[np.int64]
    spread_m2: NDArray[np.float64]


def target_lines(
    grid: GridIndex,
    k: int = 8,
    radius_m: float = 0.5,
    fit_radius_m: float = 0.2,
    max_flatness: float = 0.05,
    seen_from_origin: bool = False,
    wanted: NDArray[np.bool_] | None = None,
) -> TargetLines:
    """Line of each target point from its nearest neighbours (itself included): up to k within
    `fit_radius_m`, at least the two-point line to the nearest within `radius_m`; not ok when it
    has no neighbour or the patch is not line-like (minor/major scatter > max_flatness: corners,
    clutter). Points of one scan `seen_from_origin` reach for that nearest neighbour as far as
    one surface spans at their range (`surface_gap_m`), if that is farther: a far wall's
    points lie further apart than any fixed radius tuned indoors. With `wanted` (a mask over
    the points) only those lines are fitted, and the partners of their two-point lines
    (`unconfirmed_patches` reads them); every other row is not ok."""
    if not k >= 2:
        raise ValueError(f"k must be >= 2, got {k}")
    if not 0.0 < fit_radius_m <= radius_m:
        raise ValueError(f"fit_radius_m must be in (0, radius_m={radius_m}], got {fit_radius_m}")
    n = len(grid.points)
    if wanted is None:
        wanted = np.ones(n, dtype=np.bool_)
    elif wanted.shape != (n,):
        raise ValueError(f"wanted must hold one flag per point ({n}), got shape {wanted.shape}")
    gap_base_m, gap_per_range = (GAP_BASE_M, GAP_PER_RANGE) if seen_from_origin else (0.0, 0.0)
    return TargetLines(*_lines(grid.arrays, k, radius_m, fit_radius_m, max_flatness, gap_base_m,
                               gap_per_range, np.ascontiguousarray(wanted, dtype=np.bool_)))


def surface_normals(points: NDArray[np.float64]) -> NDArray[np.float64]:
    """Unit normal of the line through each point's neighbours in its own scan (`target_lines`,
    seen from the origin); zero where the neighbourhood is no line (a corner, clutter, a lone
    point). The field matchers take the field's slope across these surfaces only."""
    lines = target_lines(GridIndex.build(points), seen_from_origin=True)
    return np.where(lines.ok[:, None], lines.normals, 0.0)
