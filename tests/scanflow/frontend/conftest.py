"""Scans cast in the simulator's `rooms` world from chosen poses, for front-end tests."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import pytest
from numpy.typing import NDArray
from scanflow.config import FrontendSettings
from scanflow.geometry import Pose2D
from scanflow.sim import cast_rays, get_world

BEAMS = 360
RANGE_MAX_M = 12.0


def scan_points(pose: Pose2D, beams: int = BEAMS) -> NDArray[np.float64]:
    """Valid endpoints (sensor frame) of a full-circle scan taken at `pose` in `rooms`."""
    segments = get_world("rooms").segments
    angles = np.arange(beams) * (2 * np.pi / beams)
    ranges = cast_rays(np.tile([pose.x, pose.y], (beams, 1)), angles + pose.theta, segments,
                       RANGE_MAX_M)
    ok = np.isfinite(ranges)
    return np.column_stack((ranges[ok] * np.cos(angles[ok]), ranges[ok] * np.sin(angles[ok])))


@pytest.fixture
def scan_at() -> Callable[[Pose2D], NDArray[np.float64]]:
    return scan_points


@pytest.fixture
def settings() -> FrontendSettings:
    return FrontendSettings.model_construct()
