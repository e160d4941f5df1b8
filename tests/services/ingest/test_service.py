"""The ingest service on real processes: it publishes nothing before a subscriber is there,
and a log's damage is named, never a crash."""

from __future__ import annotations

import gzip
import os
import subprocess
import sys

import numpy as np
import pytest
from scanflow import keys

pytestmark = [pytest.mark.integration]

def test_ingest_waits_for_a_subscriber_before_publishing(launcher, bus, start):
    deskewed = bus.record(keys.deskewed_scan())
    launcher.start(
        "ingest",
        SCANFLOW_INGEST_WINDOW="0",
        SCANFLOW_INGEST_DRAIN_TIMEOUT_S="0.5",
        SCANFLOW_INGEST_SIM_DURATION_S="1",
    )
    bus.wait_until(lambda: "ingest/0" in bus.alive(), 30.0, "ingest up")
    start("deskew")
    bus.wait_until(lambda: len(deskewed) == 10, 30.0, "all 10 scans, none published into nothing")
    assert [m.seq for m in deskewed] == list(range(10))


def test_ingest_skips_a_logs_unreadable_lines_and_says_which(launcher, bus, start, data_file):
    """The good records are published, each bad line is logged by its number, and the
    process ends cleanly (before, CARMEN lines were skipped without a word)."""
    lines = gzip.decompress(data_file("aces-corrected.log.gz").read_bytes()).split(b"\n")[:200]
    lines[150:150] = [b"FLASER 180 1.0 oops"]  # line 151, between the 2nd and 3rd scan
    log = launcher.log_dir / "damaged.log"
    log.write_bytes(b"\n".join(lines) + b"\n")
    scans = sum(line.startswith(b"FLASER 180 ") for line in lines) - 1
    start("deskew")
    deskewed = bus.record(keys.deskewed_scan())
    proc = launcher.start("ingest", SCANFLOW_INGEST_LOG=str(log), SCANFLOW_INGEST_WINDOW="0",
                          SCANFLOW_INGEST_DRAIN_TIMEOUT_S="0.5")
    proc.wait(60)
    text = launcher.log_text("ingest")
    assert proc.returncode == 0, text
    assert f"skipped an unreadable record: {log}:151: " in text
    bus.wait_until(lambda: len(deskewed) == scans, 30.0, f"all {scans} good scans")


def test_ingest_ends_cleanly_where_a_bag_breaks(launcher, bus):
    """A bag that cannot be read: named in the log, and an exit of 0 rather than a traceback
    (compose restarts a failed ingest, which would replay the log and break again, forever)."""
    bag = launcher.log_dir / "broken_bag"
    bag.mkdir()
    (bag / "metadata.yaml").write_text("not: a bag\n")
    proc = launcher.start("ingest", SCANFLOW_INGEST_LOG=str(bag),
                          SCANFLOW_INGEST_DRAIN_TIMEOUT_S="0.5")
    proc.wait(60)
    text = launcher.log_text("ingest")
    assert proc.returncode == 0, text
    assert "the log cannot be read on, replays end here (0 scans of it published)" in text
    assert f"cannot open bag {bag}" in text and "Traceback" not in text


def test_an_unexpected_error_ends_the_process_rather_than_hanging_it(launcher):
    """An error no handler expects (here from the source) ends the process with status 1 and
    the error logged: before, the open session's threads kept it alive, ignoring SIGTERM."""
    script = (
        "import services.ingest.service as s\n"
        "def broken(*args, **kwargs):\n"
        "    raise RuntimeError('a bug in the source')\n"
        "s.source_events = broken\n"
        "s.main()\n"
    )
    env = {**os.environ, "SCANFLOW_ZENOH_CONNECT": f"tcp/127.0.0.1:{launcher.zenoh_port}"}
    done = subprocess.run([sys.executable, "-c", script], env=env, capture_output=True,
                          text=True, timeout=60, check=False)
    assert done.returncode == 1, done.stderr
    assert "ingest/0 stops on an error: RuntimeError('a bug in the source')" in done.stderr


def test_odometry_no_message_can_carry_is_skipped_and_named() -> None:
    """A log's odometry 2e6 m out (a glitching driver; 1e308 m broke the deskewer's scans and
    is refused by Odometry itself now, so the loaders skip it): the wire refuses it, so ingest
    skips the record, counted and logged, and publishes the rest; it must not end the replay
    on the error."""
    from scanflow.config import IngestSettings, ZenohSettings
    from scanflow.geometry import Pose2D
    from scanflow.scan import LaserScan, Odometry
    from scanflow.wire import OdometryMessage, ScanMessage, decode_any

    from services.ingest.service import Ingest

    far = Odometry(0.05, Pose2D(2e6, 0.0, 0.0), robot_id="robot", seq=1)
    events = [
        Odometry(0.0, Pose2D(), robot_id="robot", seq=0), far,
        LaserScan(np.ones(8), 0.0, 0.1, stamp_s=0.1, robot_id="robot", seq=0),
    ]
    ingest = Ingest(IngestSettings(window=0, wait_subscribers_s=0.0),
                    ZenohSettings(mode="peer", connect=[]))
    sent: list = []
    ingest.shell.put = lambda key, payload: sent.append(decode_any(payload))
    try:
        ingest._publish(events)
    finally:
        ingest.shell.close(flush_s=0.0)
    assert [type(m) for m in sent] == [OdometryMessage, ScanMessage]
    assert ingest.shell.counters.get("source.skipped") == 1


def test_the_simulators_odometry_settings_reach_its_source() -> None:
    """SCANFLOW_INGEST_SIM_ODOM_YAW_NOISE (and _SCALE_ERROR) reach the simulated source: the
    same run published with its odometry's heading drifting ends elsewhere in heading."""
    from scanflow.config import IngestSettings, ZenohSettings
    from scanflow.geometry import angle_diff
    from scanflow.wire import OdometryMessage, decode_any

    from services.ingest.service import Ingest

    def last_heading(yaw_noise: float) -> float:
        settings = IngestSettings(window=0, wait_subscribers_s=0.0, sim_duration_s=3.0,
                                  sim_seed=1, sim_odom_scale_error=0.0,
                                  sim_odom_yaw_noise=yaw_noise)
        ingest = Ingest(settings, ZenohSettings(mode="peer", connect=[]))
        sent: list = []
        ingest.shell.put = lambda key, payload: sent.append(decode_any(payload))
        try:
            assert ingest.replay_once() == 30
        finally:
            ingest.shell.close(flush_s=0.0)
        return [m for m in sent if isinstance(m, OdometryMessage)][-1].odom.pose.theta

    assert abs(angle_diff(last_heading(0.0), last_heading(0.05))) > 1e-3
