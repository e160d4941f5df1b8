"""Point moments per block of cells, and the normal distributions they give (Biber & Strasser
2003): compiled accumulation of (count, sums, sums of products) from points or from the set
cells of occupancy masks, on plain cells or the 2 x 2 blocks of the overlapping grids; then each
block's mean and the inverse of its covariance with the eigenvalues floored (a wall's points are
nearly collinear). `ndt_cells` builds its cell sets from these.
"""

from __future__ import annotations

import math
from typing import cast

import numpy as np
from numba import njit
from numpy.typing import NDArray

EIGEN_FLOOR_RATIO = 0.1  # smallest eigenvalue >= this fraction of the largest
EIGEN_FLOOR_M2 = 1e-4  # and >= (1 cm)^2


@njit(cache=True)
def _add_point(  # type: ignore[no-untyped-def]
    x, y, row, col, origin_x, origin_y, size, rows, cols, span, index, moments, touched, n
):
    """Add (x, y), which lies in cell (row, col), to the moments of each block holding that
    cell (see sparse_moments); returns the new number of blocks touched."""
    for r in range(max(row - span + 1, 0), min(row, rows - 1) + 1):
        for c in range(max(col - span + 1, 0), min(col, cols - 1) + 1):
            flat = r * cols + c
            k = index[flat]
            if k < 0:
                k = index[flat] = n
                touched[n] = flat
                n += 1
            dx = x - (origin_x + c * size)
            dy = y - (origin_y + r * size)
            m = moments[k]
            m[0] += 1.0
            m[1] += dx
            m[2] += dy
            m[3] += dx * dx
            m[4] += dx * dy
            m[5] += dy * dy
    return n


@njit(cache=True)
def _kept_blocks(index, moments, touched, n, min_points):  # type: ignore[no-untyped-def]
    """Drop the touched blocks with fewer than `min_points` points, renumbering the rest."""
    kept = 0
    for k in range(n):
        if moments[k, 0] >= min_points:
            moments[kept] = moments[k]
            touched[kept] = touched[k]
            index[touched[k]] = kept
            kept += 1
        else:
            index[touched[k]] = -1
    return index, moments[:kept], touched[:kept]


@njit(cache=True)
def sparse_moments(
    points: NDArray[np.float64], origin_x: float, origin_y: float, size: float,
    rows: int, cols: int, span: int, min_points: int,
) -> tuple[NDArray[np.int64], NDArray[np.float64], NDArray[np.int64]]:
    """(flat index of kept block numbers or -1, (K, 6) moments of the kept blocks, (K,) flat
    position of each kept block).

    Block (r, c) covers span x span cells of `size` from cell (r, c) (corner at origin +
    (c, r) * size): span 1 gives plain cells; span 2 the 2 x 2 blocks of OverlappingCells, each
    point added to the four blocks holding it. Points outside every block are skipped. Moments
    (count, sum x, sum y, sum xx, sum xy, sum yy) are accumulated only for blocks holding
    points, about each block's corner (small sums, no cancellation far from the origin);
    blocks with fewer than `min_points` points are dropped.
    """
    capacity = min(points.shape[0] * span * span, rows * cols)
    index = np.full(rows * cols, -1, dtype=np.int64)
    moments = np.zeros((capacity, 6))
    touched = np.empty(capacity, dtype=np.int64)
    n = np.int64(0)  # not the literal 0: _add_point and _kept_blocks compile once
    for i in range(points.shape[0]):
        x, y = points[i, 0], points[i, 1]
        n = _add_point(
            x, y, math.floor((y - origin_y) / size), math.floor((x - origin_x) / size),
            origin_x, origin_y, size, rows, cols, span, index, moments, touched, n,
        )  # fmt: skip
    return _kept_blocks(index, moments, touched, n, min_points)


@njit(cache=True)
def _mask_moments(  # type: ignore[no-untyped-def]
    mask, row0, col0, res, block_row0, block_col0, size, rows, cols, span, min_points
):
    """sparse_moments of the centres of the set cells of `mask`, a window from cell (row0,
    col0) of the lattice of `res` cells with its corner at the origin (no list of the cells),
    for the blocks from (block_row0, block_col0) of the lattice of `size` cells.

    A centre's cell of that lattice is floor((fine + 0.5) * res / size), whatever the box (as
    `_LatticeBlocks._bins` marks it dirty): from the box's corner, rounding put a centre on a
    cell border in either cell depending on the box."""
    index = np.full(rows * cols, -1, dtype=np.int64)
    moments = np.zeros((rows * cols, 6))
    touched = np.empty(rows * cols, dtype=np.int64)
    origin_x, origin_y, scale = block_col0 * size, block_row0 * size, res / size
    n = np.int64(0)  # not the literal 0: _add_point and _kept_blocks compile once
    for i in range(mask.shape[0]):
        y = (row0 + i + 0.5) * res
        row = math.floor((row0 + i + 0.5) * scale) - block_row0
        for j in range(mask.shape[1]):
            if mask[i, j]:
                n = _add_point(
                    (col0 + j + 0.5) * res, y, row,
                    math.floor((col0 + j + 0.5) * scale) - block_col0,
                    origin_x, origin_y, size, rows, cols, span, index, moments, touched, n,
                )  # fmt: skip
    return _kept_blocks(index, moments, touched, n, min_points)


@njit(cache=True)
def boxes_moments(
    masks: NDArray[np.bool_], starts: NDArray[np.int64],
    fine: NDArray[np.int64], blocks: NDArray[np.int64],
    res: float, size: float, span: int, min_points: int,
) -> tuple[NDArray[np.int64], NDArray[np.bool_], NDArray[np.float64], NDArray[np.float64]]:
    """_mask_moments of several boxes of blocks at once: box k covers blocks[k] (by first
    cell, on the lattice of `size` cells from the anchor), its occupied mask is the window
    fine[k] of fine cells, stored row-major at masks[starts[k]:]. Returns the (row, col) of
    every block of every box (box after box, row-major), whether each is kept (>= min_points
    points), and the (K, 6) moments of the kept ones in that order with the (K, 2) corners
    (x, y from the anchor) they are taken about."""
    total = 0
    for k in range(len(blocks)):
        total += (blocks[k, 2] - blocks[k, 0]) * (blocks[k, 3] - blocks[k, 1])
    block_rc = np.empty((total, 2), dtype=np.int64)
    live = np.zeros(total, dtype=np.bool_)
    moments = np.empty((total, 6))
    corners = np.empty((total, 2))
    b = n_live = 0
    for k in range(len(blocks)):
        r0, c0, r1, c1 = blocks[k, 0], blocks[k, 1], blocks[k, 2], blocks[k, 3]
        shape = (fine[k, 2] - fine[k, 0], fine[k, 3] - fine[k, 1])
        mask = masks[starts[k] : starts[k] + shape[0] * shape[1]].reshape(shape)
        index, kept, _ = _mask_moments(
            mask, fine[k, 0], fine[k, 1], res, r0, c0, size, r1 - r0, c1 - c0, span,
            min_points,
        )  # fmt: skip
        for i in range((r1 - r0) * (c1 - c0)):
            row, col = i // (c1 - c0), i % (c1 - c0)
            block_rc[b, 0], block_rc[b, 1] = r0 + row, c0 + col
            if index[i] >= 0:
                live[b] = True
                moments[n_live] = kept[index[i]]
                corners[n_live, 0] = c0 * size + col * size  # as _add_point takes them
                corners[n_live, 1] = r0 * size + row * size
                n_live += 1
            b += 1
    return block_rc, live, moments[:n_live], corners[:n_live]


def block_distributions(
    kept: tuple[NDArray[np.int64], NDArray[np.float64], NDArray[np.int64]],
    origin: tuple[float, float],
    size: float,
    cols: int,
) -> tuple[NDArray[np.int64], NDArray[np.float64], NDArray[np.float64], NDArray[np.int64]]:
    """(flat index of block numbers or -1, means, inverse covariances, counts) from what
    sparse_moments or _mask_moments returned for blocks of `size` cells, `cols` per row,
    from `origin`."""
    index, moments, flat = kept
    # Integer block numbers times a float size: float64 (numpy's stub says floating[Any]).
    corners = cast(
        NDArray[np.float64], np.column_stack((flat % cols, flat // cols)) * size + origin
    )
    return (index, *cell_distributions(moments, corners))


def cell_distributions(
    moments: NDArray[np.float64], about: NDArray[np.float64]
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.int64]]:
    """(means, regularised inverse covariances, counts) from `sparse_moments`' moments
    (taken about `about`: one point, or one per row)."""
    n, sx, sy, sxx, sxy, syy = moments.T
    mx, my = sx / n, sy / n
    dof = np.maximum(n - 1, 1)
    cov = np.empty((len(n), 2, 2))
    cov[:, 0, 0] = (sxx - n * mx * mx) / dof
    cov[:, 0, 1] = cov[:, 1, 0] = (sxy - n * mx * my) / dof
    cov[:, 1, 1] = (syy - n * my * my) / dof
    means = np.column_stack((mx, my)) + about
    return means, regularised_inverse(cov), n.astype(np.int64)


def regularised_inverse(cov: NDArray[np.float64]) -> NDArray[np.float64]:
    """Inverse of (K, 2, 2) symmetric covariances after flooring their eigenvalues.

    Closed form for 2 x 2: eigenvalues mid -+ radius, major axis at half the angle of
    (a - c, 2 b).
    """
    a, b, c = cov[:, 0, 0], cov[:, 0, 1], cov[:, 1, 1]
    mid = 0.5 * (a + c)
    radius = np.hypot(0.5 * (a - c), b)
    small, large = mid - radius, mid + radius
    floor = np.maximum(EIGEN_FLOOR_RATIO * large, EIGEN_FLOOR_M2)
    inv_small = 1.0 / np.maximum(small, floor)
    inv_large = 1.0 / np.maximum(large, floor)
    phi = 0.5 * np.arctan2(2.0 * b, a - c)
    cos2, sin2, cs = np.cos(phi) ** 2, np.sin(phi) ** 2, np.cos(phi) * np.sin(phi)
    out = np.empty_like(cov)
    out[:, 0, 0] = cos2 * inv_large + sin2 * inv_small
    out[:, 0, 1] = out[:, 1, 0] = cs * (inv_large - inv_small)
    out[:, 1, 1] = sin2 * inv_large + cos2 * inv_small
    return out
