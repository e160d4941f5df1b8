"""`scanflow calibrate`: the mount estimate from a real log's keyframes, and its refusals."""

from __future__ import annotations

import json
import math
import os
from pathlib import Path

import pytest
from scanflow.cli import _register, app
from typer.testing import CliRunner

REPO = Path(__file__).resolve().parents[3]
DATA = Path(os.environ.get("SCANFLOW_DATA_DIR", REPO / ".." / "shared" / "data"))
LOG = DATA / "aces-corrected.log.gz"


@pytest.mark.skipif(not LOG.exists(), reason=f"real log {LOG} not available")
def test_calibrate_a_real_log() -> None:
    _register()
    result = CliRunner().invoke(app, ["calibrate", "--log", str(LOG), "--limit", "120", "--json"])
    assert result.exit_code == 0, result.output
    out = json.loads(result.output)
    assert out["status"] == "ok" and out["keyframes"] == 120
    assert 5 <= out["pairs_used"] <= out["pairs_matched"] <= 119
    assert all(math.isfinite(v) for v in out["mount_m_m_deg"] + out["std_m_m_deg"])
    # A lidar on a robot: within half a metre of its centre, and (FLASER) facing forward.
    x, y, yaw_deg = out["mount_m_m_deg"]
    assert math.hypot(x, y) < 0.5 and abs(yaw_deg) < 10.0
    text = CliRunner().invoke(app, ["calibrate", "--log", str(LOG), "--limit", "120"]).output
    assert "SCANFLOW_INGEST_MOUNT=" in text


@pytest.mark.skipif(not LOG.exists(), reason=f"real log {LOG} not available")
def test_too_few_keyframes_is_no_estimate_and_says_why() -> None:
    _register()
    result = CliRunner().invoke(app, ["calibrate", "--log", str(LOG), "--limit", "3"])
    assert result.exit_code == 1 and "too_few_pairs" in result.output


def test_calibrate_names_a_missing_log(tmp_path: Path) -> None:
    _register()
    result = CliRunner().invoke(app, ["calibrate", "--log", str(tmp_path / "none.log")])
    assert result.exit_code == 2 and "no log at" in result.output
