"""Scans cast in the simulator's `rooms` world from chosen poses, and the world mapped from
them as a prior map, for front-end tests."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import pytest
from numpy.typing import NDArray
from scanflow.config import FrontendSettings
from scanflow.frontend import insert_scan
from scanflow.geometry import Pose2D
from scanflow.maps.matching_map import MatchingMap
from scanflow.maps.occupancy import OccupancyGrid, OccupancyParams
from scanflow.sim import get_world, static_scan

BEAMS = 360
RANGE_MAX_M = 12.0
WORLD_FRAME = Pose2D()


def scan_points(pose: Pose2D, beams: int = BEAMS) -> NDArray[np.float64]:
    """Valid endpoints (sensor frame) of a full-circle scan taken at `pose` in `rooms`."""
    angles = np.arange(beams) * (2 * np.pi / beams)
    return static_scan(get_world("rooms").segments, pose, angles, RANGE_MAX_M)


@pytest.fixture
def scan_at() -> Callable[[Pose2D], NDArray[np.float64]]:
    return scan_points


@pytest.fixture
def settings() -> FrontendSettings:
    return FrontendSettings.model_construct()


def prior_grid_in(
    scan_at: Callable[[Pose2D], NDArray[np.float64]], map_from_world: Pose2D = WORLD_FRAME
) -> OccupancyGrid:
    """The rooms world mapped from its waypoints at their true poses, drawn in the map frame
    `map_from_world` (T_map_world)."""
    world = MatchingMap(OccupancyGrid(OccupancyParams(resolution_m=0.05)))
    for x, y in get_world("rooms").waypoints:
        at = Pose2D(float(x), float(y), 0.0)
        insert_scan(world, scan_at(at), map_from_world * at)
    return world.grid


@pytest.fixture
def prior_grid() -> Callable[..., OccupancyGrid]:
    """`prior_grid(scan_at, map_from_world)`: a fresh prior map of `rooms` on every call."""
    return prior_grid_in
