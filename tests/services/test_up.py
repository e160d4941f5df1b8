"""`scanflow up` end to end: everything starts, the run completes, Ctrl-C or SIGTERM stops it
all cleanly (every service, the gateway too, reports exit 0, and so does `scanflow up`)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest
from scanflow.maps.export import load_map

from services.common.launch import free_port

pytestmark = [pytest.mark.integration, pytest.mark.slow]


def up_command(data, *extra: str) -> list[str]:
    return [
        sys.executable, "-m", "scanflow", "up", "--rate", "0", "--limit", "15",
        "--port", str(free_port()), "--zenoh-port", str(free_port()), "--data-dir", str(data),
        *extra,
    ]


def run_until_ingest_is_done(cmd: list[str], out, stop_signal, env=None) -> subprocess.Popen:
    with out.open("wb") as sink:
        proc = subprocess.Popen(cmd, stdout=sink, stderr=subprocess.STDOUT, env=env)
        try:
            deadline = time.monotonic() + 120
            while "ingest exited with code 0" not in out.read_text():
                assert proc.poll() is None, out.read_text()
                assert time.monotonic() < deadline, out.read_text()
                time.sleep(0.3)
        finally:
            proc.send_signal(stop_signal)
            proc.wait(60)
    return proc


@pytest.mark.parametrize("stop_signal", [signal.SIGINT, signal.SIGTERM], ids=["ctrl-c", "sigterm"])
def test_up_runs_the_simulator_through_and_stops_cleanly(tmp_path, stop_signal):
    out = tmp_path / "up.out"
    data = tmp_path / "data"
    proc = run_until_ingest_is_done(up_command(data), out, stop_signal)
    text = out.read_text()
    assert proc.returncode == 0, text
    for line in ("gateway:  http://127.0.0.1:", f"data dir: {data}", "Ctrl-C stops everything."):
        assert line in text
    for service in ("ingest", "gateway", "mapserver", "matcher", "deskew", "router"):
        assert f"  {service}: exit 0" in text, text
    assert (data / "robot.snapshot.npz").exists()


def test_up_on_a_prior_map_localises_without_changing_it(tmp_path):
    maps, data, out = tmp_path / "maps", tmp_path / "data", tmp_path / "up.out"
    subprocess.run([sys.executable, "-m", "scanflow", "run", "--duration", "3", "--json",
                    "--map-out", str(maps)], check=True, capture_output=True)
    env = {**os.environ, "SCANFLOW_FRONTEND_UPDATE_MAP": "false"}
    cmd = up_command(data, "--prior-map", str(maps / "map.npz"))
    proc = run_until_ingest_is_done(cmd, out, signal.SIGINT, env)
    text = out.read_text()
    assert proc.returncode == 0, text
    assert f"map:      every robot starts on {maps / 'map.npz'}" in text
    # The map server started the robot on the prior map, and localising inserted nothing.
    served = load_map(data / "robot.snapshot.npz")
    np.testing.assert_array_equal(served.log_odds, load_map(maps / "map.npz").log_odds)


def test_up_names_a_missing_prior_map(tmp_path):
    cmd = up_command(tmp_path / "data", "--prior-map", str(tmp_path / "none.npz"))
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=60)
    assert done.returncode == 2 and "no file at" in done.stderr


def test_up_with_loop_closure_runs_the_back_end_in_the_services(tmp_path):
    """Culling set from the shell (SCANFLOW_BACKEND_CULL_M) is reported; that it reaches the
    matcher is tests/services/test_backend_services.py's."""
    out, data = tmp_path / "up.out", tmp_path / "data"
    env = {**os.environ, "SCANFLOW_BACKEND_CULL_M": "0.3"}
    proc = run_until_ingest_is_done(up_command(data, "--loop-closure"), out, signal.SIGINT, env)
    text = out.read_text()
    assert proc.returncode == 0, text
    assert "back end: loop closure on" in text
    assert "keyframes culled within 0.3 m / 10.0 deg of one drawn" in text
    with np.load(data / "robot.snapshot.npz") as snap:  # the map server kept the keyframes
        assert len(snap["keyframes_seqs"]) > 0
