"""bench.frontend's simulator mode: the mounted-lidar runs and the --mount argument."""

from __future__ import annotations

import argparse
import math

import pytest
from scanflow.frontend import default_settings
from scanflow.geometry import Pose2D

from bench.frontend import parse_mount, run_sim


def test_a_mount_adds_the_run_that_ignores_it_and_that_run_is_worse() -> None:
    report = run_sim(default_settings(), 3.0, 4, Pose2D(0.4, 0.05, math.radians(20.0)))
    assert set(report) >= {"deskewed", "raw", "mount_ignored"}
    worst = {run: report[run]["max_position_error_m"] for run in ("deskewed", "mount_ignored")}
    assert worst["deskewed"] < 0.15
    assert worst["mount_ignored"] > 2 * worst["deskewed"]
    assert "mount_ignored" not in run_sim(default_settings(), 1.0, 4)


def test_parse_mount_takes_metres_and_degrees_and_names_bad_input() -> None:
    assert parse_mount("0.4,-0.1,90") == Pose2D(0.4, -0.1, math.pi / 2)
    with pytest.raises(argparse.ArgumentTypeError, match="X_M,Y_M,YAW_DEG"):
        parse_mount("0.4,-0.1")
