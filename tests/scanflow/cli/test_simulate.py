"""`scanflow simulate`: the simulator and deskewer in-process, summarised as JSON or refused."""

from __future__ import annotations

import json

from scanflow.cli import _register, app
from typer.testing import CliRunner

from .conftest import assert_usage_error


def test_simulate_json_summary():
    _register()
    result = CliRunner().invoke(app, ["simulate", "--duration", "0.5", "--seed", "2", "--json"])
    assert result.exit_code == 0, result.output
    summary = json.loads(result.output)
    assert summary["scans"] == 5 and summary["beams"] == 5 * 360
    assert summary["deskew_sources"] == {"odometry": 5}
    assert summary["mean_distortion_after_mm"] < summary["mean_distortion_before_mm"]


def test_simulate_rejects_unknown_world():
    _register()
    result = CliRunner().invoke(app, ["simulate", "--world", "moon"])
    assert result.exit_code != 0
    assert "moon" in result.output


def test_simulate_refuses_a_bad_seed_or_duration_without_a_traceback():
    for option, value in (("--seed", "-1"), ("--duration", "inf"), ("--duration", "7200")):
        assert_usage_error(["simulate", option, value, "--json"], value)
