"""Scans cast in the simulator's `rooms` world from chosen poses, for front-end tests."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import pytest
from numpy.typing import NDArray
from scanflow.config import FrontendSettings
from scanflow.geometry import Pose2D
from scanflow.sim import get_world, static_scan

BEAMS = 360
RANGE_MAX_M = 12.0


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
