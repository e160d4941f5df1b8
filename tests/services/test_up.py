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
import zenoh
from scanflow import keys
from scanflow.config import ZenohSettings
from scanflow.maps.export import load_map
from scanflow.scan import LaserScan
from scanflow.wire import decode_any

from services.common.launch import free_port
from services.common.zsession import open_session
from services.ingest.sources import bus_message, source_events

# Six whole `scanflow up` runs (about 70 s): `make test` runs them beside the rest
# (tools/run-tests.sh), after the container tests.
pytestmark = [pytest.mark.integration, pytest.mark.slow, pytest.mark.second_lane]


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




def test_ctrl_c_stops_with_the_data_so_scans_deskew_holds_still_reach_the_map(tmp_path):
    """A robot's own Zenoh client sends scans and odometry, the odometry for its last second
    never comes: deskew holds those scans, waiting for it (odom_wait_s). Ctrl-C: the services
    stop with the data (ingest and gateway first, then deskew, matcher, map server, each once
    the one before has exited), so the scans deskew flushes at its stop are still matched and
    mapped: every scan has its pose in the map server's snapshot."""
    out, data, zenoh_port = tmp_path / "up.out", tmp_path / "data", free_port()
    cmd = up_command(data)
    cmd[cmd.index("--zenoh-port") + 1] = str(zenoh_port)
    cmd[cmd.index("--limit") + 1] = "1"  # the built-in robot: one scan, then ingest is done
    env = {**os.environ, "SCANFLOW_DESKEW_ODOM_WAIT_S": "120"}
    events = list(source_events(None, "ext", 20.0, 3, None))
    scans = [e for e in events if isinstance(e, LaserScan)]
    cut_s = scans[-10].stamp_s  # no odometry from here on: the last 10 scans are held
    sent = [e for e in events if isinstance(e, LaserScan) or e.stamp_s < cut_s]
    with out.open("wb") as sink:
        proc = subprocess.Popen(cmd, stdout=sink, stderr=subprocess.STDOUT, env=env)
        try:
            deadline = time.monotonic() + 120
            while "ingest exited with code 0" not in out.read_text():
                assert proc.poll() is None and time.monotonic() < deadline, out.read_text()
                time.sleep(0.3)
            robot = open_session(ZenohSettings(connect=[f"tcp/127.0.0.1:{zenoh_port}"]))
            for event in sent:
                robot.put(*bus_message(event), congestion_control=zenoh.CongestionControl.BLOCK)

            def held() -> bool:  # every earlier scan mapped, the last 10 held by deskew
                replies = robot.get(keys.stats("mapserver", "0"), timeout=2.0)
                stats = [decode_any(r.ok.payload.to_bytes()) for r in replies if r.ok]
                return bool(stats) and stats[0].gauges.get("seq.ext/pose.last") == scans[-11].seq

            while not held():
                assert time.monotonic() < deadline, "the scans before the cut never mapped"
                time.sleep(0.2)
            robot.close()
        finally:
            proc.send_signal(signal.SIGINT)
            proc.wait(90)
    text = out.read_text()
    assert proc.returncode == 0, text
    with np.load(data / "ext.snapshot.npz") as snap:
        assert len(snap["poses"]) == len(scans)
        assert int(snap["last_seq"]) == scans[-1].seq
