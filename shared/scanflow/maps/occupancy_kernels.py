"""The occupancy grid's compiled loops: one scan's or many scans' update, hit sums, pooled hit
means and occupied windows, all in storage cells (`OccupancyGrid` owns the arrays and the
bookkeeping; these only walk them)."""

from __future__ import annotations

import numpy as np
from numba import njit
from numpy.typing import NDArray

from scanflow.maps.raycast import ray_length, trace_ray

HIT_UNITS_PER_CELL = 256  # hit offsets are stored in 1/256 of a cell
HIT_COUNT_MAX = 255


@njit(cache=True)
def pooled_hit_means(
    log_odds: NDArray[np.float32], observed: NDArray[np.bool_],
    hit_xy: NDArray[np.uint16], hit_n: NDArray[np.uint8],
    threshold: np.float32, boxes: NDArray[np.int64], factor: int, row0: int, col0: int,
) -> NDArray[np.float64]:
    """See OccupancyGrid.occupied_hit_means_in: `boxes` (n, 4) of the coarse lattice counted
    from the frame's first cell, (row0, col0) the frame's first fine cell in storage indices
    (boxes may reach outside the storage: those cells are empty)."""
    total = 0
    for k in range(boxes.shape[0]):
        total += (boxes[k, 2] - boxes[k, 0]) * (boxes[k, 3] - boxes[k, 1])
    out = np.empty((total, 2))
    n_out = 0
    stored_rows, stored_cols = log_odds.shape
    for k in range(boxes.shape[0]):
        for cr in range(boxes[k, 0], boxes[k, 2]):
            for cc in range(boxes[k, 1], boxes[k, 3]):
                sx = sy = n = 0.0
                for i in range(factor):
                    r = row0 + cr * factor + i
                    if r < 0 or r >= stored_rows:
                        continue
                    for j in range(factor):
                        c = col0 + cc * factor + j
                        if c < 0 or c >= stored_cols or not observed[r, c]:
                            continue
                        if log_odds[r, c] <= threshold:
                            continue
                        count = float(hit_n[r, c])
                        if count > 0:
                            sx += (hit_xy[0, r, c] + 0.5 * count) / HIT_UNITS_PER_CELL + j * count
                            sy += (hit_xy[1, r, c] + 0.5 * count) / HIT_UNITS_PER_CELL + i * count
                            n += count
                        else:
                            sx += 0.5 + j
                            sy += 0.5 + i
                            n += 1.0
                if n > 0:
                    out[n_out, 0] = cr + min(max(sy / (factor * n), 0.0), 1.0) - 0.5
                    out[n_out, 1] = cc + min(max(sx / (factor * n), 0.0), 1.0) - 0.5
                    n_out += 1
    return out[:n_out]


@njit(cache=True)
def accumulate_hits(
    hit_xy: NDArray[np.uint16], hit_n: NDArray[np.uint8],
    cells: NDArray[np.int64], units: NDArray[np.uint16],
) -> None:
    """Add each hit's (x, y) offset units to its cell ((n, 2) rows and columns), halving a
    full cell's weight first."""
    for k in range(cells.shape[0]):
        r, c = cells[k, 0], cells[k, 1]
        if hit_n[r, c] == HIT_COUNT_MAX:  # keep half the weight, same mean
            half = HIT_COUNT_MAX // 2
            hit_n[r, c] = half
            hit_xy[0, r, c] = round(hit_xy[0, r, c] * half / HIT_COUNT_MAX)
            hit_xy[1, r, c] = round(hit_xy[1, r, c] * half / HIT_COUNT_MAX)
        hit_n[r, c] += 1
        hit_xy[0, r, c] += units[k, 0]
        hit_xy[1, r, c] += units[k, 1]


@njit(cache=True, nogil=True)
def update_cells(
    log_odds: NDArray[np.float32], observed: NDArray[np.bool_], box: NDArray[np.int64],
    origin: NDArray[np.int64], hits: NDArray[np.int64], misses: NDArray[np.int64],
    miss_lo: np.float32, hit_lo: np.float32, lo_min: np.float32, lo_max: np.float32,
    threshold: np.float32,
) -> NDArray[np.int64]:
    """One scan's update, in storage cells: every cell a beam to a hit passes (the hit
    excluded) or a no-return beam reaches (its end included) gets `miss_lo` once, every hit
    cell `hit_lo` once (and no miss), each clamped to [lo_min, lo_max] and marked observed.
    Visits the beams' cells only, and a scratch mask of their bounding box `box` (row0, col0,
    row1, col1) for "done already". Returns the (K, 2) cells whose occupied state (observed and
    log-odds > threshold) flipped, row-major."""
    row0, col0 = box[0], box[1]
    done = np.zeros((box[2] - row0, box[3] - col0), dtype=np.uint8)  # 1 free, 2 hit, 3 hit done
    for i in range(hits.shape[0]):
        done[hits[i, 0] - row0, hits[i, 1] - col0] = 2
    longest, total = 1, 0
    for ends in (hits, misses):
        for i in range(ends.shape[0]):
            length = ray_length(origin[0], origin[1], ends[i, 0], ends[i, 1])
            longest, total = max(longest, length), total + length
    ray = np.empty((longest, 2), dtype=np.int64)
    flipped = np.empty(total, dtype=np.int64)  # no cell is visited more than its rays visit it
    # Typed counts, not the literals 1 / 0 / 0: _clear compiles once, not once per call.
    one, zero = np.int64(1), np.int64(0)
    n = _clear(log_odds, observed, done, row0, col0, origin, hits, one, ray, miss_lo, lo_min,
               lo_max, threshold, flipped, zero)
    n = _clear(log_odds, observed, done, row0, col0, origin, misses, zero, ray, miss_lo, lo_min,
               lo_max, threshold, flipped, n)
    for i in range(hits.shape[0]):
        r, c = hits[i, 0], hits[i, 1]
        if _visit(log_odds, observed, done, row0, col0, r, c, 2, hit_lo, lo_min, lo_max,
                  threshold):
            flipped[n] = r * log_odds.shape[1] + c
            n += 1
    order = np.sort(flipped[:n])
    cells = np.empty((n, 2), dtype=np.int64)
    cells[:, 0] = order // log_odds.shape[1]
    cells[:, 1] = order % log_odds.shape[1]
    return cells


@njit(cache=True, nogil=True)
def _clear(  # type: ignore[no-untyped-def]
    log_odds, observed, done, row0, col0, origin, ends, short, ray, miss_lo, lo_min, lo_max,
    threshold, flipped, n,
):
    """The free-space part of `update_cells`: the rays to `ends`, each but its last `short`
    cells, clear every cell not done yet; flipped cells go on `flipped[n:]`, the new n is
    returned."""
    for i in range(ends.shape[0]):
        count = trace_ray(ray, origin[0], origin[1], ends[i, 0], ends[i, 1])
        for k in range(count - short):
            r, c = ray[k, 0], ray[k, 1]
            if _visit(log_odds, observed, done, row0, col0, r, c, 0, miss_lo, lo_min, lo_max,
                      threshold):
                flipped[n] = r * log_odds.shape[1] + c
                n += 1
    return n


@njit(cache=True, nogil=True, inline="always")
def _visit(  # type: ignore[no-untyped-def]
    log_odds, observed, done, row0, col0, r, c, waiting, delta, lo_min, lo_max, threshold
):
    """Update cell (r, c) by `delta`, clamped, if its scratch state is `waiting` (then it is
    done: 1 after a miss, 3 after a hit); whether its occupied state flipped."""
    if done[r - row0, c - col0] != waiting:
        return False
    done[r - row0, c - col0] = waiting + 1
    before = observed[r, c] and log_odds[r, c] > threshold
    value = min(max(log_odds[r, c] + delta, lo_min), lo_max)
    log_odds[r, c] = value
    observed[r, c] = True
    return before != (value > threshold)


@njit(cache=True, nogil=True)
def insert_many(
    log_odds: NDArray[np.float32], observed: NDArray[np.bool_],
    hit_xy: NDArray[np.uint16], hit_n: NDArray[np.uint8],
    origins: NDArray[np.int64], hits: NDArray[np.int64], hit_starts: NDArray[np.int64],
    misses: NDArray[np.int64], miss_starts: NDArray[np.int64], units: NDArray[np.uint16],
    miss_lo: np.float32, hit_lo: np.float32, lo_min: np.float32, lo_max: np.float32,
    threshold: np.float32,
) -> None:
    """`update_cells` then `accumulate_hits` for each scan in turn, in storage cells: scan
    s has origins[s], hits[hit_starts[s]:hit_starts[s + 1]] and likewise misses."""
    box = np.empty(4, dtype=np.int64)
    for s in range(origins.shape[0]):
        h = hits[hit_starts[s]:hit_starts[s + 1]]
        m = misses[miss_starts[s]:miss_starts[s + 1]]
        if h.shape[0] == 0 and m.shape[0] == 0:
            continue
        box[0], box[1] = origins[s, 0], origins[s, 1]
        box[2], box[3] = origins[s, 0], origins[s, 1]
        for ends in (h, m):
            for i in range(ends.shape[0]):
                box[0], box[1] = min(box[0], ends[i, 0]), min(box[1], ends[i, 1])
                box[2], box[3] = max(box[2], ends[i, 0]), max(box[3], ends[i, 1])
        box[2] += 1
        box[3] += 1
        update_cells(log_odds, observed, box, origins[s], h, m, miss_lo, hit_lo, lo_min,
                      lo_max, threshold)
        accumulate_hits(hit_xy, hit_n, h, units[hit_starts[s]:hit_starts[s + 1]])


@njit(cache=True)
def occupied_windows(
    log_odds: NDArray[np.float32], observed: NDArray[np.bool_], threshold: np.float32,
    boxes: NDArray[np.int64], row0: int, col0: int,
) -> tuple[NDArray[np.bool_], NDArray[np.int64]]:
    """See OccupancyGrid.occupied_in_boxes; (row0, col0) is the storage's first cell."""
    sizes = (boxes[:, 2] - boxes[:, 0]) * (boxes[:, 3] - boxes[:, 1])
    starts = np.zeros(len(boxes) + 1, dtype=np.int64)
    starts[1:] = np.cumsum(sizes)
    out = np.zeros(starts[-1], dtype=np.bool_)
    stored_rows, stored_cols = log_odds.shape
    for k in range(len(boxes)):
        width = boxes[k, 3] - boxes[k, 1]
        for r in range(max(boxes[k, 0], row0), min(boxes[k, 2], row0 + stored_rows)):
            at = starts[k] + (r - boxes[k, 0]) * width - boxes[k, 1]
            sr = r - row0
            for c in range(max(boxes[k, 1], col0), min(boxes[k, 3], col0 + stored_cols)):
                out[at + c] = observed[sr, c - col0] and log_odds[sr, c - col0] > threshold
    return out, starts
