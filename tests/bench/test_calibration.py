"""bench.calibration: simulated mounts come back, the CLI refuses bad arguments."""

import json
import math

import pytest

from bench.calibration import main

from .conftest import run_bench, usage_error


def test_simulated_mounts_come_back_and_not_calibrating_is_the_baseline() -> None:
    out = run_bench("calibration", "--sim", "--duration", "20", "--json")
    assert out.returncode == 0, out.stderr
    report = json.loads(out.stdout)
    assert set(report) == {"front, turned 20 deg", "rear-facing", "side, 90 deg", "centre"}
    for name, case in report.items():
        assert case["status"] == "ok", name
        assert case["error_m"] < 0.03 and case["error_deg"] < 1.0, (name, case)
    rear = report["rear-facing"]
    assert rear["uncalibrated_error_m"] == 0.25 and rear["uncalibrated_error_deg"] == 180.0
    assert math.isfinite(rear["residual_rms_m"]) and rear["pairs_used"] >= 20


def test_bad_arguments_are_named(capsys: pytest.CaptureFixture[str]) -> None:
    assert "--step must be >= 1" in usage_error(main, capsys, "--sim", "--step", "0")
