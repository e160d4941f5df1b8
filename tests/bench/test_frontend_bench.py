"""bench.frontend's simulator mode: the mounted-lidar runs and the --mount argument, an outdoor
run."""

from __future__ import annotations

import argparse
import math

import pytest
from scanflow.frontend import default_settings
from scanflow.geometry import Pose2D
from scanflow.io.carmen import load_keyframes
from scanflow.pipeline import Pipeline

from bench.data import corrected_log
from bench.frontend import (
    accuracy,
    parse_mount,
    poses_array,
    run_pass,
    run_sim,
    run_starts,
    settings_for,
)
from bench.lidar import parse_lidar

INTEL = corrected_log("intel")
ACES = corrected_log("aces")


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


def test_an_outdoor_run_with_a_far_reaching_lidar_is_tracked() -> None:
    """The campus seen by a 181-beam, 180-deg lidar reaching 80 m: buildings 15-70 m away."""
    report = run_sim(default_settings(), 6.0, 0, world="campus", lidar=parse_lidar("181,180,80"))
    assert report["lidar"] == [181, 180.0, 80.0]
    run = report["deskewed"]
    assert run["statuses"] == {"initialised": 1, "tracked": report["scans"] - 1}
    assert run["max_position_error_m"] < 0.5 and run["cpu_ms_per_scan"] > 0


def test_with_perfect_odometry_the_error_left_is_the_matching_s() -> None:
    """The ring with exact wheel odometry: gn drifts where its map ends, gn+plicp does not
    (BENCHMARKS.md "Front end")."""
    settings = default_settings()
    runs = {
        method: run_sim(settings.model_copy(update={"method": method}), 8.0, 0,
                        world="loop", perfect_odometry=True)
        for method in ("gn", "gn+plicp")
    }
    assert all(r["world"] == "loop" and r["perfect_odometry"] for r in runs.values())
    gn, fine = (runs[m]["deskewed"] for m in ("gn", "gn+plicp"))
    assert fine["max_position_error_m"] < 0.5 * gn["max_position_error_m"]
    assert fine["final_position_error_m"] < 0.02
    assert abs(fine["final_heading_error_deg"]) < abs(gn["final_heading_error_deg"])


@pytest.mark.skipif(not INTEL.exists(), reason="the shared intel log is not beside the checkout")
def test_starts_runs_the_log_from_each_of_its_first_keyframes() -> None:
    report = run_starts(INTEL, default_settings(), 40, 3)
    ates = report["ate_by_start_m"]
    assert len(ates) == 3 and len(set(ates)) == 3  # each start a different run
    assert all(0.0 < a < 0.5 for a in ates)
    assert report["median_ate_m"] == sorted(ates)[1] and report["max_ate_m"] == max(ates)
    assert len(report["rechecked_scans_by_start"]) == 3


@pytest.mark.skipif(not ACES.exists(), reason="the shared aces log is not beside the checkout")
def test_the_recheck_keeps_aces_from_keyframe_13_on_its_map() -> None:
    """aces from keyframe 13 (BENCHMARKS.md, "Front end", the recheck): at its 209th scan, a
    fast turn, gn lands 17 deg off with a score of 0.43 and passes every check. Without the
    recheck the front end breaks there."""
    frames = load_keyframes(ACES)[13:273]
    truth = poses_array([kf.true_pose for kf in frames])
    runs = {
        ratio: run_pass(Pipeline(settings_for(None, ratio)), frames, f"recheck {ratio}")
        for ratio in (None, 0.0)
    }
    with_recheck, without = (accuracy(runs[r].poses, truth)["ate_rmse_m"] for r in (None, 0.0))
    assert with_recheck < 0.3 < 1.0 < without
    assert runs[None].statuses["recovered"] > runs[0.0].statuses.get("recovered", 0)
    assert runs[None].rechecked >= 1 and runs[None].rechecked_s > 0.0
    assert runs[0.0].rechecked == 0
