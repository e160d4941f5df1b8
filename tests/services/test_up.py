"""`scanflow up` end to end: everything starts, the run completes, Ctrl-C or SIGTERM stops it
all cleanly (every service, the gateway too, reports exit 0, and so does `scanflow up`)."""

from __future__ import annotations

import signal
import subprocess
import sys
import time

import pytest

from services.common.launch import free_port

pytestmark = [pytest.mark.integration, pytest.mark.slow]


@pytest.mark.parametrize("stop_signal", [signal.SIGINT, signal.SIGTERM], ids=["ctrl-c", "sigterm"])
def test_up_runs_the_simulator_through_and_stops_cleanly(tmp_path, stop_signal):
    out = tmp_path / "up.out"
    data = tmp_path / "data"
    cmd = [
        sys.executable, "-m", "scanflow", "up", "--rate", "0", "--limit", "15",
        "--port", str(free_port()), "--zenoh-port", str(free_port()), "--data-dir", str(data),
    ]
    with out.open("wb") as sink:
        proc = subprocess.Popen(cmd, stdout=sink, stderr=subprocess.STDOUT)
        try:
            deadline = time.monotonic() + 120
            while "ingest exited with code 0" not in out.read_text():
                assert proc.poll() is None, out.read_text()
                assert time.monotonic() < deadline, out.read_text()
                time.sleep(0.3)
        finally:
            proc.send_signal(stop_signal)
            proc.wait(60)
    text = out.read_text()
    assert proc.returncode == 0, text
    for line in ("gateway:  http://127.0.0.1:", f"data dir: {data}", "Ctrl-C stops everything."):
        assert line in text
    for service in ("ingest", "gateway", "mapserver", "matcher", "deskew", "router"):
        assert f"  {service}: exit 0" in text, text
    assert (data / "robot.snapshot.npz").exists()
