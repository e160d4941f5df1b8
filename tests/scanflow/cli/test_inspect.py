"""`scanflow inspect`: JSON and text summaries of a real CARMEN log, a bag and broken input."""

from __future__ import annotations

import dataclasses
import json
import math
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from rosbags.rosbag2 import Writer
from rosbags.typesys import Stores, get_typestore
from scanflow.cli import _register, app
from scanflow.cli.inspect import LogSummary
from scanflow.geometry import Pose2D
from scanflow.scan import LaserScan
from typer.testing import CliRunner

_register()
runner = CliRunner()
REQUIRED_KEYS = {"scans", "beams", "fov_deg", "duration_s", "rate_hz", "odometry", "robots"}


def _aces() -> Path:
    base = os.environ.get("SCANFLOW_DATA_DIR")
    folder = Path(base) if base else Path(__file__).resolve().parents[3] / ".." / "shared" / "data"
    path = folder / "aces-corrected.log.gz"
    if not path.is_file():
        pytest.skip(f"real log not found at {path} (set SCANFLOW_DATA_DIR)")
    return path


def _json(args: list[str]) -> dict:
    result = runner.invoke(app, ["inspect", *args])
    assert result.exit_code == 0, result.output
    return json.loads(result.stdout)


def test_json_on_the_aces_log() -> None:
    path = _aces()
    out = _json(["--json", str(path)])
    assert out.keys() >= REQUIRED_KEYS
    assert out["format"] == "carmen"
    assert out["scans"] == 440 and out["beams"] == [180]
    assert out["fov_deg"] == pytest.approx(179.0)
    assert (out["angle_min_deg"], out["angle_max_deg"]) == (-90.0, 89.0)
    assert out["duration_s"] == pytest.approx(1318.06, abs=0.01)  # data README: 1318 s
    assert out["rate_hz"] == pytest.approx(439 / out["duration_s"], rel=1e-4)
    assert out["odometry"] == 7814 and out["robots"] == ["robot"]
    assert out["malformed"] == 0
    assert 0 < out["dropped_beam_fraction"] < 0.05
    assert out["range_m"]["max"] < 50.0 <= max(out["no_return_at_m"])
    assert out["lidar_mounts_m_m_deg"] == [[0.0, 0.0, 0.0]]


def test_the_lidar_mounts_are_listed() -> None:
    summary = LogSummary()
    scan = LaserScan(np.ones(4, np.float32), 0.0, 0.1, range_max_m=10.0)
    for mount in (Pose2D(0.2, -0.05, math.radians(90.0)), Pose2D(0.2, -0.0500001, math.pi / 2)):
        summary.add_scan(dataclasses.replace(scan, mount=mount))
    assert summary.to_dict()["lidar_mounts_m_m_deg"] == [[0.2, -0.05, 90.0]]


def test_text_output_on_the_aces_log() -> None:
    result = runner.invoke(app, ["inspect", str(_aces())])
    assert result.exit_code == 0
    assert "scans: 440" in result.stdout and "beams: [180]" in result.stdout


def test_malformed_lines_are_counted(tmp_path: Path) -> None:
    path = tmp_path / "broken.log"
    good = "FLASER 3 1 2 60 0 0 0 0 0 0 5.0 h 5.0"
    path.write_text(f"{good}\nFLASER 3 1 2\n{good.replace('5.0', '6.0')}\nODOM 0 0 0 0 0 0 5 h 5\n")
    out = _json(["--json", str(path)])
    assert out["scans"] == 2 and out["odometry"] == 1 and out["malformed"] == 1
    assert out["errors"][0].startswith(f"{path}:2:")
    assert out["dropped_beam_fraction"] == pytest.approx(2 / 6)
    assert out["duration_s"] == 1.0 and out["rate_hz"] == 1.0


def _write_bag(path: Path, stamps_s: list[float], beams: int) -> Path:
    store = get_typestore(Stores.ROS2_HUMBLE)
    t = store.types
    with Writer(path, version=9) as writer:
        conn = writer.add_connection("/robot3/scan", "sensor_msgs/msg/LaserScan", typestore=store)
        for stamp in stamps_s:
            header = t["std_msgs/msg/Header"](
                stamp=t["builtin_interfaces/msg/Time"](sec=int(stamp), nanosec=0), frame_id="laser"
            )
            msg = t["sensor_msgs/msg/LaserScan"](
                header=header, angle_min=-np.pi, angle_max=np.pi, angle_increment=np.pi / 180,
                time_increment=0.0, scan_time=0.1, range_min=0.1, range_max=10.0,
                ranges=np.full(beams, 2.0, dtype=np.float32),
                intensities=np.zeros(0, dtype=np.float32),
            )  # fmt: skip
            data = store.serialize_cdr(msg, "sensor_msgs/msg/LaserScan")
            writer.write(conn, int(stamp * 1e9), data)
    return path


def test_json_on_a_ros2_bag(tmp_path: Path) -> None:
    bag = _write_bag(tmp_path / "bag", [10.0, 11.0, 12.0], beams=360)
    out = _json(["--json", str(bag)])
    assert out["format"] == "rosbag2"
    assert out["scans"] == 3 and out["beams"] == [360] and out["odometry"] == 0
    assert out["fov_deg"] == pytest.approx(359.0)
    assert out["duration_s"] == 2.0 and out["rate_hz"] == 1.0
    assert out["robots"] == ["robot3"]
    assert out["range_m"] == {"min": 2.0, "max": 2.0, "mean": 2.0}


def test_missing_file_exits_with_a_message(tmp_path: Path) -> None:
    result = runner.invoke(app, ["inspect", str(tmp_path / "nope.log")])
    assert result.exit_code == 2
    assert "nope.log" in result.stderr


def test_python_dash_m_entry_point(tmp_path: Path) -> None:
    bag = _write_bag(tmp_path / "bag", [1.0, 2.0], beams=10)
    proc = subprocess.run(
        [sys.executable, "-m", "scanflow", "inspect", "--json", str(bag)],
        capture_output=True, text=True, check=True, timeout=120,
    )  # fmt: skip
    assert json.loads(proc.stdout)["scans"] == 2
