"""Shared inputs of the bench tests."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scanflow.geometry import Pose2D
from scanflow.io.carmen import Keyframe
from scanflow.scan import LaserScan


@pytest.fixture
def frames() -> list[Keyframe]:
    """Seven log records of a robot driving 10 cm per scan past a sloped wall."""
    ranges = np.linspace(1.0, 4.0, 180)
    return [
        Keyframe(
            LaserScan(ranges, -math.pi / 2, math.pi / 180, stamp_s=0.1 * i),
            Pose2D(0.1 * i, 0.0, 0.0), Pose2D(0.1 * i, 0.0, 0.0),
        )
        for i in range(7)
    ]
