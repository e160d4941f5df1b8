"""Free-space test of an alignment against an occupancy grid: source points on cells the map
has seen free, away from every occupied cell.

The map counterpart of free_space.py. A moved source point is tested when its cell has been
observed; it conflicts when that cell is free with repeated evidence (occupancy probability
below `free_probability`: with the default sensor model, >= 3 more misses than hits) and no
occupied cell lies within `margin_m` (a square window, so a point near a wall never conflicts).
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from scanflow.maps.occupancy import OccupancyGrid
from scanflow.matching.free_space import FreeSpaceTest

FREE_PROBABILITY = 0.25


def map_free_space_test(
    moved: NDArray[np.float64],
    grid: OccupancyGrid,
    margin_m: float,
    free_probability: float = FREE_PROBABILITY,
) -> FreeSpaceTest:
    """Count source points (already in the map frame) on the map's free cells."""
    if not margin_m >= 0.0:
        raise ValueError(f"free-space margin_m must be >= 0, got {margin_m}")
    box = grid.extent
    if box is None or len(moved) == 0:
        return FreeSpaceTest(0, 0)
    log_odds, observed = grid.log_odds, grid.observed
    cells = grid.world_to_cells(moved) - np.array([box.row0, box.col0])
    inside = np.all((cells >= 0) & (cells < np.array(log_odds.shape)), axis=1)
    rows, cols = cells[inside].T
    seen = observed[rows, cols]
    free = seen & (log_odds[rows, cols] < grid.params.threshold_log_odds(free_probability))
    half = math.ceil(margin_m / grid.resolution_m)
    reach = np.arange(-half, half + 1)
    near_rows = np.clip(rows[free, None, None] + reach[:, None], 0, log_odds.shape[0] - 1)
    near_cols = np.clip(cols[free, None, None] + reach[None, :], 0, log_odds.shape[1] - 1)
    occupied = observed[near_rows, near_cols] & (
        log_odds[near_rows, near_cols] > grid.params.threshold_log_odds()
    )
    conflicts = np.count_nonzero(~occupied.any(axis=(1, 2)))
    return FreeSpaceTest(int(np.count_nonzero(seen)), int(conflicts))
