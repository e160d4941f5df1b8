"""What a clean stop of the whole system costs and keeps: `scanflow up` on the built-in
simulator, a robot's own Zenoh client sends `--scans` scans with their odometry as fast as the
bus takes them, and Ctrl-C comes `--after` seconds after the last one (0: at once, with the
pipeline behind). Reported per run: seconds from Ctrl-C to exit, every service's exit code, and
how many of the robot's scans deskew had taken before the stop and how many have a pose in the
map server's snapshot (every one taken must be there).

    python -m bench.shutdown [--runs 3] [--scans 200] [--after 0] [--json]

A scan still in the client's or the router's queues when deskew stops was never accepted, so
with `--after 0` the snapshot may hold fewer than were sent.
"""

from __future__ import annotations

import argparse
import json
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np
import zenoh
from scanflow import keys
from scanflow.config import ZenohSettings
from scanflow.scan import LaserScan
from scanflow.wire import ServiceStatsMessage

from services.common.launch import free_port
from services.common.zsession import open_session
from services.ingest.sources import bus_message, source_events

ROBOT = "ext"


def send(client: zenoh.Session, scans: int) -> int:
    """Put `scans` simulated scans of ROBOT and their odometry on the bus; how many scans."""
    sent = 0
    for event in source_events(None, ROBOT, scans / 10 + 1, 3, scans):
        client.put(*bus_message(event), congestion_control=zenoh.CongestionControl.BLOCK)
        sent += isinstance(event, LaserScan)
    return sent


def accepted(client: zenoh.Session) -> int:
    """How many of ROBOT's scans deskew has taken off the bus (its stats), -1 if no answer."""
    for reply in client.get(keys.stats("deskew", "0"), timeout=2.0):
        if reply.ok is not None:
            stats = ServiceStatsMessage.decode(reply.ok.payload.to_bytes())
            return stats.counters.get(f"seq.{ROBOT}/scan.received", 0)
    return -1


def one_run(scans: int, after_s: float) -> dict[str, Any]:
    """Start `scanflow up`, send, wait `after_s`, Ctrl-C; the figures of one run."""
    work = Path(tempfile.mkdtemp(prefix="scanflow-bench-shutdown-"))
    zenoh_port, out = free_port(), work / "up.out"
    cmd = [sys.executable, "-m", "scanflow", "up", "--rate", "0", "--limit", "1",
           "--port", str(free_port()), "--zenoh-port", str(zenoh_port),
           "--data-dir", str(work / "data")]
    with out.open("wb") as sink:
        proc = subprocess.Popen(cmd, stdout=sink, stderr=subprocess.STDOUT)
        deadline = time.monotonic() + 180.0
        while "ingest exited with code 0" not in out.read_text():
            if proc.poll() is not None or time.monotonic() > deadline:
                raise RuntimeError(f"scanflow up did not come up:\n{out.read_text()}")
            time.sleep(0.2)
        client = open_session(ZenohSettings(connect=[f"tcp/127.0.0.1:{zenoh_port}"]))
        try:
            sent = send(client, scans)
            time.sleep(after_s)
            taken = accepted(client)  # asked before the stop: a lower bound of what it took
            t0 = time.monotonic()
            proc.send_signal(signal.SIGINT)
            proc.wait(120.0)
            stop_s = time.monotonic() - t0
        finally:
            client.close()
    text = out.read_text()
    codes = {
        line.split(":")[0].strip(): line.split("exit")[1].strip()
        for line in text.splitlines() if line.startswith("  ") and ": exit " in line
    }
    snapshot = work / "data" / f"{ROBOT}.snapshot.npz"
    kept = 0
    if snapshot.exists():
        with np.load(snapshot) as snap:
            kept = len(snap["poses"])
    return {"stop_s": round(stop_s, 3), "exit_code": proc.returncode, "service_exits": codes,
            "scans_sent": sent, "scans_accepted_before_stop": taken, "poses_kept": kept}


def main(argv: list[str] | None = None) -> None:
    """Run the stops and print a line per run, or every figure as JSON."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=3)
    parser.add_argument("--scans", type=int, default=200)
    parser.add_argument("--after", type=float, default=0.0,
                        help="seconds between the last scan sent and Ctrl-C")
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args(argv)
    if args.runs < 1 or args.scans < 1 or args.after < 0:
        parser.error("--runs and --scans must be >= 1 and --after >= 0")
    runs = [one_run(args.scans, args.after) for _ in range(args.runs)]
    if args.json:
        print(json.dumps({"runs": runs, "scans": args.scans, "after_s": args.after}, indent=2))
        return
    for i, r in enumerate(runs):
        print(f"run {i}: {r['stop_s']:.2f} s from Ctrl-C to exit (code {r['exit_code']}), "
              f"{r['poses_kept']} of {r['scans_sent']} scans in the snapshot "
              f"({r['scans_accepted_before_stop']} taken by deskew before the stop)")


if __name__ == "__main__":
    main()
