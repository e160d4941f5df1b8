"""`scanflow calibrate`: the mount estimate from a real log's keyframes, and its refusals."""

from __future__ import annotations

import gzip
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


def _strict_json(text: str) -> object:
    """`text` parsed as JSON proper: NaN and Infinity, which Python would take, are refused."""
    def refuse(token: str) -> object:
        raise ValueError(f"{token} is not JSON")
    return json.loads(text, parse_constant=refuse)


def test_no_estimate_in_json_is_valid_json(tmp_path: Path) -> None:
    """A log with too few keyframes: the spreads of no estimate are null, not NaN tokens."""
    log = tmp_path / "few.log"
    ranges = " ".join(["3.0"] * 180)
    log.write_text("".join(f"FLASER 180 {ranges} 0 0 0 0 0 0 {t} host {t}\n" for t in (1, 2)))
    _register()
    result = CliRunner().invoke(app, ["calibrate", "--log", str(log), "--json"])
    assert result.exit_code == 1, result.output
    out = _strict_json(result.output)
    assert out["status"] == "too_few_pairs"
    assert out["std_m_m_deg"] == [None, None, None] and out["residual_rms_m"] is None


def test_a_ros2_bag_is_named_as_no_carmen_log(tmp_path: Path) -> None:
    """A bag's directory is a log, just not one calibrate reads (it said 'no log at')."""
    bag = tmp_path / "bag"
    bag.mkdir()
    (bag / "metadata.yaml").write_text("rosbag2_bagfile_information: {}\n")
    _register()
    result = CliRunner().invoke(app, ["calibrate", "--log", str(bag)])
    assert result.exit_code == 2 and "calibrate reads CARMEN logs" in result.output


def test_a_log_cut_short_is_calibrated_on_what_was_read_and_says_so(tmp_path: Path) -> None:
    """A gzip log cut off mid-stream: the keyframes before the cut are used, and the break is
    named (on stderr, or counted in --json), not passed over in silence."""
    ranges = " ".join(["3.0"] * 180)
    text = "".join(f"FLASER 180 {ranges} 0 0 0 0 0 0 {t} host {t}\n" for t in range(1, 200))
    log = tmp_path / "cut.log.gz"
    log.write_bytes(gzip.compress(text.encode())[:-40])
    _register()
    result = CliRunner().invoke(app, ["calibrate", "--log", str(log), "--json"])
    out = json.loads(result.stdout)
    assert out["skipped_records"] == 1 and out["keyframes"] > 100
    result = CliRunner().invoke(app, ["calibrate", "--log", str(log)])
    assert "1 unreadable records of the log skipped" in result.output
    assert "cannot be read past here" in result.output
