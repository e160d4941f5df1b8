"""bench.deskew_downstream: scan-to-scan errors vs the true motion, raw and deskewed."""

from __future__ import annotations

import itertools
import json
import math
from types import SimpleNamespace

import numpy as np
import pytest
from scanflow.frontend import default_settings
from scanflow.geometry import Pose2D
from scanflow.sim import SimConfig, simulate

from bench import deskew_downstream
from bench.deskew_downstream import LEVELS, main, pair_errors
from bench.frontend import run_sim


def test_deskewing_lowers_the_scan_to_scan_error_at_fast_motion() -> None:
    """5 s at 1.5 m/s and 180 deg/s: the raw scans' p95 error is several times the deskewed."""
    errors = pair_errors(1.5, 180.0, 5.0, 0, "icp")
    raw, fixed = errors["raw"], errors["deskewed"]
    assert raw["pairs"] == fixed["pairs"] == 49
    for summary in (raw, fixed):
        assert 0 < summary["trans_median_mm"] <= summary["trans_p95_mm"]
        assert 0 < summary["rot_median_deg"] <= summary["rot_p95_deg"]
    assert fixed["trans_p95_mm"] < 0.5 * raw["trans_p95_mm"]
    assert fixed["rot_p95_deg"] < 0.5 * raw["rot_p95_deg"]
    assert fixed["trans_median_mm"] < raw["trans_median_mm"]
    assert fixed["trans_p95_mm"] < 5.0  # a few mm: the matcher's own error


def test_the_error_is_the_estimate_against_the_true_motion_between_scan_stamps(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """A matcher that returns its guess: the errors are those of the odometry increment, worked
    out here from the simulated run's own odometry samples and true poses."""
    calls = []

    def at_guess(source: np.ndarray, target: np.ndarray, guess: Pose2D, method: str):  # type: ignore[no-untyped-def]
        calls.append((source, target, method))
        return SimpleNamespace(pose=guess)

    monkeypatch.setattr(deskew_downstream, "match", at_guess)
    errors = pair_errors(1.0, 90.0, 2.0, 3, "some-method")
    frames = list(simulate(SimConfig(duration_s=2.0, seed=3, max_speed_mps=1.0,
                                     max_yaw_rate_dps=90.0)))
    # 50 Hz odometry, 10 Hz scans: a sample at each scan stamp (up to rounding of the stamps).
    odometry = {round(o.stamp_s, 6): o.pose for f in frames for o in f.odometry}
    trans, rot = [], []
    for a, b in itertools.pairwise(frames):
        truth = a.true_pose.inverse() * b.true_pose
        guess = odometry[round(a.scan.stamp_s, 6)].inverse() * odometry[round(b.scan.stamp_s, 6)]
        error = truth.inverse() * guess
        trans.append(1e3 * error.translation_norm())
        rot.append(abs(math.degrees(error.theta)))
    assert max(trans) > 1.0  # the 1 % odometry scale error shows
    for kind in ("raw", "deskewed"):
        summary = errors[kind]
        assert summary["pairs"] == len(frames) - 1
        assert summary["trans_median_mm"] == pytest.approx(np.median(trans))
        assert summary["trans_p95_mm"] == pytest.approx(np.percentile(trans, 95))
        assert summary["rot_median_deg"] == pytest.approx(np.median(rot))
        assert summary["rot_p95_deg"] == pytest.approx(np.percentile(rot, 95))
    # Each pair: the later scan matched against the earlier, raw points first, then deskewed.
    assert len(calls) == 2 * (len(frames) - 1)
    for k, (source, target, method) in enumerate(calls[::2], start=1):
        assert method == "some-method"
        assert np.array_equal(source, frames[k].scan.robot_points())
        assert np.array_equal(target, frames[k - 1].scan.robot_points())
    for k, (source, _, _) in enumerate(calls[1::2], start=1):
        distorted, true = frames[k].scan.robot_points(), frames[k].true_points
        assert source.shape == distorted.shape
        off = np.hypot(*(source - true).T).mean()
        assert off < 0.5 * np.hypot(*(distorted - true).T).mean(), k


def test_the_command_line_reports_every_level_and_the_front_end_at_the_fastest(
    capsys: pytest.CaptureFixture[str],
) -> None:
    main(["--duration", "1.0", "--seed", "2", "--json"])
    report = json.loads(capsys.readouterr().out)
    assert report["method"] == "icp" and report["duration_s"] == 1.0
    assert [(lv["speed_mps"], lv["yaw_rate_dps"]) for lv in report["levels"]] == list(LEVELS)
    for level in report["levels"]:
        again = pair_errors(level["speed_mps"], level["yaw_rate_dps"], 1.0, 2, "icp")
        for kind in ("raw", "deskewed"):
            assert level["scan_to_scan"][kind] == pytest.approx(again[kind]), level
        assert level["scan_to_scan"]["raw"]["pairs"] == 9
    fast = report["frontend_fast"]
    assert (fast["speed_mps"], fast["yaw_rate_dps"]) == LEVELS[-1]
    assert fast["scans"] == 10
    front_end = run_sim(default_settings(), 1.0, 2)
    for run in ("deskewed", "raw"):
        assert fast[run]["ate_rmse_m"] == pytest.approx(front_end[run]["ate_rmse_m"])
