"""bench.deskew: beam errors with and without deskewing on the fast circle, setup, timings."""

from __future__ import annotations

import itertools
import json
import math
import sys

import numpy as np
import pytest
from scanflow.sim import SimFrame, simulate

from bench import deskew
from bench.deskew import _config, _fast_circle, _odometry_feeder, accuracy_run, run, speed

DURATION_S = 1.0


@pytest.fixture(scope="module")
def report() -> dict:
    return run(repeats=2, duration_s=DURATION_S)


@pytest.fixture(scope="module")
def frames() -> list[SimFrame]:
    return list(simulate(_config(360, DURATION_S), _fast_circle()))


def beam_errors_mm(frames: list[SimFrame]) -> np.ndarray:
    """Distance of each measured (distorted) endpoint from its true endpoint, in mm."""
    return 1e3 * np.concatenate(
        [np.hypot(*(f.scan.robot_points() - f.true_points).T) for f in frames]
    )


def test_the_setup_is_the_motion_the_simulated_robot_makes(
    report: dict, frames: list[SimFrame]
) -> None:
    setup = report["setup"]
    assert setup["simulated_s"] == DURATION_S and setup["odometry_noise"] == "none"
    assert len(frames) == round(DURATION_S * setup["rate_hz"])
    assert all(f.scan.beam_count == setup["beams"] for f in frames)
    dt = 1.0 / setup["rate_hz"]
    v, w = setup["speed_mps"], math.radians(setup["yaw_rate_dps"])
    chord = 2 * v / w * math.sin(w * dt / 2)
    for a, b in itertools.pairwise(frames):
        step = a.true_pose.inverse() * b.true_pose
        assert b.scan.stamp_s - a.scan.stamp_s == pytest.approx(dt)
        assert step.theta == pytest.approx(w * dt)
        assert step.translation_norm() == pytest.approx(chord)
    stamps = np.array([o.stamp_s for f in frames for o in f.odometry])
    assert np.allclose(np.diff(np.unique(stamps)), 1.0 / setup["odometry_rate_hz"])


def test_odometry_deskewing_leaves_only_the_chord_error_of_linear_interpolation(
    report: dict, frames: list[SimFrame]
) -> None:
    odometry, setup = report["odometry_accuracy"], report["setup"]
    raw = beam_errors_mm(frames)
    assert odometry["scans"] == len(frames) and odometry["sources_used"] == ["odometry"]
    assert odometry["uncompensated_mean_mm"] == pytest.approx(raw.mean())
    assert odometry["uncompensated_max_mm"] == pytest.approx(raw.max())
    # Between two 50 Hz samples the arc is replaced by its chord: at most v w dt^2 / 8 off.
    dt = 1.0 / setup["odometry_rate_hz"]
    bound_mm = 1e3 * setup["speed_mps"] * math.radians(setup["yaw_rate_dps"]) * dt**2 / 8
    assert 0.5 * bound_mm < odometry["deskewed_max_mm"] <= 1.001 * bound_mm
    assert 0 < odometry["deskewed_mean_mm"] <= odometry["deskewed_max_mm"]
    assert odometry["deskewed_max_mm"] < 1e-3 * odometry["uncompensated_mean_mm"]


def test_the_constant_velocity_model_is_exact_on_a_constant_twist_after_its_warm_up(
    report: dict, frames: list[SimFrame]
) -> None:
    model = report["constant_velocity_accuracy"]
    raw = beam_errors_mm(frames[2:])
    assert model["scans"] == len(frames) - 2 and model["sources_used"] == ["constant_velocity"]
    assert model["uncompensated_mean_mm"] == pytest.approx(raw.mean())
    assert model["uncompensated_max_mm"] == pytest.approx(raw.max())
    assert model["deskewed_max_mm"] < 1e-6


def test_without_a_pose_source_the_deskewed_errors_are_the_uncompensated_ones(
    frames: list[SimFrame],
) -> None:
    none = accuracy_run(frames, lambda frame: None)
    assert none["sources_used"] == ["none"] and none["scans"] == len(frames)
    assert none["deskewed_mean_mm"] == pytest.approx(none["uncompensated_mean_mm"])
    assert none["deskewed_max_mm"] == pytest.approx(none["uncompensated_max_mm"])
    fed = accuracy_run(frames, _odometry_feeder(), warmup=3)
    assert fed["scans"] == len(frames) - 3
    assert fed["uncompensated_mean_mm"] == pytest.approx(beam_errors_mm(frames[3:]).mean())


def test_every_timing_counts_each_scan_of_each_pass(report: dict) -> None:
    scans = round(1.0 * report["setup"]["rate_hz"]) - 2  # of 1 s; the first and last left out
    for figures, repeats in ((report["speed_360_beams"], 2), (report["speed_1440_beams"], 1)):
        assert set(figures) == {"deskew_only", "with_scan_validity_mask",
                                "deskew_only_mounted_lidar"}
        for timing in figures.values():
            assert timing["calls"] == repeats * scans
            assert 0 < timing["median_us"] <= timing["p90_us"] and timing["cpu_median_us"] >= 0
    assert speed(360, 3)["deskew_only"]["calls"] == 3 * scans


def test_the_command_line_prints_the_figures_as_json(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    monkeypatch.setattr(sys, "argv", ["bench.deskew", "--json", "--repeats", "1",
                                      "--duration", "0.5"])
    deskew.main()
    printed = json.loads(capsys.readouterr().out)
    assert printed["setup"]["simulated_s"] == 0.5
    assert printed["odometry_accuracy"]["scans"] == 5
    # The speed figures come from a run of their own, 1 s long whatever --duration says.
    assert printed["speed_360_beams"]["deskew_only"]["calls"] == 8
