"""Where a front end starts: the prior map and start pose its settings name (file I/O here,
so that the tracker itself stays pure)."""

from __future__ import annotations

import copy
from pathlib import Path

from scanflow.config import FrontendSettings
from scanflow.frontend.tracker import occupancy_params
from scanflow.geometry import Pose2D
from scanflow.maps.export import load_map
from scanflow.maps.occupancy import OccupancyGrid


class PriorMapError(ValueError):
    """The prior map a setting names cannot be used (missing, unreadable or empty), or none is
    named where localising only needs one."""


def load_prior_map(settings: FrontendSettings) -> OccupancyGrid | None:
    """The grid of `settings.prior_map`, None when unset; refused unset with update_map off
    (localise only), which the tracker would otherwise refuse at each robot's first scan."""
    if not settings.prior_map:
        if not settings.update_map:
            raise PriorMapError("update_map=false (localise only) needs a prior map; prior_map "
                                "is unset")
        return None
    path = Path(settings.prior_map)
    if not path.is_file():
        raise PriorMapError(f"prior_map: no file at {path}")
    try:
        grid = load_map(path, occupancy_params(settings))
    except (OSError, ValueError, KeyError) as exc:
        raise PriorMapError(f"prior_map {path}: {exc}") from exc
    if not grid.occupied_mask().any():
        raise PriorMapError(f"prior_map {path}: the map has no occupied cell")
    return grid


class FrontendStart:
    """The start pose and prior map the settings name, read once (a bad file fails here, at
    start-up, not when a robot first appears); every robot gets a copy of the map of its own."""

    def __init__(self, settings: FrontendSettings) -> None:
        self.pose: Pose2D | None = settings.start_pose()
        self._grid = load_prior_map(settings)

    def grid(self) -> OccupancyGrid | None:
        """A fresh copy of the prior map (None without one): robots never share a grid."""
        return None if self._grid is None else copy.deepcopy(self._grid)
