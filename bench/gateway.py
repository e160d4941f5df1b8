"""Gateway load on loopback: latest-pose queries/s (p50/p99), 360-beam match requests/s and
scans posted/s, with the gateway's CPU time in each scenario.

The gateway runs as its real process (`python -m services.gateway`, uvicorn) in Zenoh peer mode;
this process is the other peer: it publishes pose estimates and answers match queries with the
matcher's own request handler (`services.matcher.requests.answer`, the library's `match`), so
match figures include real ICP/GN work on simulated 360-beam scans. An httpx asyncio client
keeps `--concurrency` requests in flight for `--seconds` per scenario. One scenario queries
the latest pose while this peer puts `--bus-scans` 360-beam raw scans a second (other robots'
sources) that the gateway reads.
Run: `python -m bench.gateway [--seconds 5] [--concurrency 8] [--bus-scans 400] [--json]`.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import zenoh
from scanflow import keys
from scanflow.config import ZenohSettings
from scanflow.geometry import Pose2D
from scanflow.maps.matching_map import MatchingMap
from scanflow.scan import LaserScan
from scanflow.sim import SimConfig, SimFrame, simulate
from scanflow.wire import MatchRequest, PoseEstimateMessage, ScanMessage

from bench.cpu import process_cpu_s
from services.common.launch import free_port, wait_for_port
from services.common.zsession import open_session
from services.matcher.requests import answer

API_KEY = "bench"


def scan_json(scan: LaserScan) -> dict[str, Any]:
    """The scan as a POST body: ranges (non-finite: null), angles, range limits, stamp, sweep."""
    ranges = [None if not np.isfinite(r) else float(r) for r in scan.ranges_m]
    return {
        "ranges_m": ranges,
        "angle_min_rad": scan.angle_min_rad,
        "angle_increment_rad": scan.angle_increment_rad,
        "range_min_m": scan.range_min_m,
        "range_max_m": scan.range_max_m,
        "stamp_s": scan.stamp_s,
        "scan_duration_s": scan.scan_duration_s,
    }


def bench_world() -> tuple[list[SimFrame], MatchingMap]:
    """Simulated 360-beam frames (1 s at 10 Hz) and a map built from them at their true poses."""
    frames = list(simulate(SimConfig(beams=360, duration_s=1.0, seed=1)))
    world = MatchingMap()
    for frame in frames:
        points = frame.true_pose.transform_points(frame.true_points)
        world.update(points, np.array([frame.true_pose.x, frame.true_pose.y]))
    return frames, world


def serve_peer(session: zenoh.Session, world: MatchingMap) -> list[Any]:
    """Answer scan-to-scan and scan-to-map match queries the way the matcher does."""

    def on_query(query: zenoh.Query) -> None:
        payload = query.payload
        if payload is None:
            raise ValueError("a match query needs a MatchRequest payload")
        request = MatchRequest.decode(payload.to_bytes())
        query.reply(query.key_expr, answer(request, lambda _robot: world).encode())

    return [
        session.declare_queryable(keys.scan_match(), on_query),
        session.declare_queryable(keys.robot_match("bench"), on_query),
    ]


def publish_poses(session: zenoh.Session, count: int) -> None:
    """`count` estimates of robot "bench" at 10 Hz, so the pose cache has something to serve."""
    for seq in range(count):
        pose = Pose2D(0.01 * seq, 0.0, 0.0)
        message = PoseEstimateMessage(
            "bench", seq, 0.1 * seq, pose, np.eye(3) * 1e-4, "ok", "gn", 5, 0.9
        )
        session.put(keys.pose("bench"), message.encode())


async def load(
    client: httpx.AsyncClient, send: Callable[[], Any], seconds: float, concurrency: int
) -> dict[str, float]:
    """Keep `concurrency` requests in flight for `seconds`; rate and latency percentiles."""
    latencies: list[float] = []
    errors = 0
    deadline = time.perf_counter() + seconds

    async def worker() -> None:
        nonlocal errors
        while time.perf_counter() < deadline:
            t0 = time.perf_counter()
            response = await send()
            latencies.append(time.perf_counter() - t0)
            errors += not response.is_success

    t_start = time.perf_counter()
    await asyncio.gather(*(worker() for _ in range(concurrency)))
    elapsed = time.perf_counter() - t_start
    q = statistics.quantiles(latencies, n=100)
    return {
        "requests": len(latencies),
        "errors": errors,
        "per_s": len(latencies) / elapsed,
        "p50_ms": q[49] * 1e3,
        "p99_ms": q[98] * 1e3,
    }


class BusScans:
    """Puts 360-beam raw scans of 10 robots, `per_s` a second in all, while in a `with`."""

    def __init__(self, session: zenoh.Session, scan: LaserScan, per_s: float) -> None:
        self.session, self.scan, self.per_s = session, scan, per_s
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self._put, daemon=True)

    def _put(self) -> None:
        period_s, seq, start = 1.0 / self.per_s, 0, time.perf_counter()
        while not self.stop.is_set():
            robot = f"bus{seq % 10}"
            scan = ScanMessage(LaserScan(self.scan.ranges_m, self.scan.angle_min_rad,
                                         self.scan.angle_increment_rad, robot_id=robot,
                                         seq=seq // 10))
            self.session.put(keys.raw_scan(robot), scan.encode())
            seq += 1
            time.sleep(max(0.0, start + seq * period_s - time.perf_counter()))

    def __enter__(self) -> BusScans:
        self.thread.start()
        return self

    def __exit__(self, *_exc: object) -> None:
        self.stop.set()
        self.thread.join()


async def run(
    frames: list[SimFrame], seconds: float, concurrency: int, http_port: int,
    gateway_pid: int, bus: BusScans,
) -> dict[str, dict[str, float]]:
    """Rate, latency and gateway CPU time of each scenario: latest pose, both matches, posted
    scans, and latest pose while `bus` puts scans."""
    first, second = frames[0], frames[1]
    body_s2s = {"method": "icp", "source": scan_json(second.scan), "target": scan_json(first.scan)}
    x, y, theta = first.true_pose.to_array().tolist()
    body_s2m = {"method": "gn", "source": scan_json(first.scan), "robot_id": "bench",
                "initial_guess": {"x_m": x + 0.05, "y_m": y - 0.05, "theta_rad": theta + 0.02}}
    headers = {"X-API-Key": API_KEY}
    base = f"http://127.0.0.1:{http_port}"
    limits = httpx.Limits(max_connections=concurrency)
    async with httpx.AsyncClient(base_url=base, headers=headers, limits=limits,
                                 timeout=30.0) as client:
        for body in (body_s2s, body_s2m):  # warm up (numba compiles, caches fill)
            (await client.post("/api/v1/match", json=body)).raise_for_status()

        async def measured(send: Callable[[], Any]) -> dict[str, float]:
            cpu0 = process_cpu_s(gateway_pid)
            result = await load(client, send, seconds, concurrency)
            return {**result, "gateway_cpu_s": process_cpu_s(gateway_pid) - cpu0}

        results = {
            "latest_pose": await measured(lambda: client.get("/api/v1/robots/bench/pose")),
            "match_scan_to_scan": await measured(
                lambda: client.post("/api/v1/match", json=body_s2s)),
            "match_scan_to_map": await measured(
                lambda: client.post("/api/v1/match", json=body_s2m)),
            "post_scan": await measured(
                lambda: client.post("/api/v1/robots/posted/scans", json=body_s2m["source"])),
        }
        with bus:
            results["latest_pose_bus_scans"] = await measured(
                lambda: client.get("/api/v1/robots/bench/pose"))
        return results


def main() -> None:
    """Start the gateway with this process as its Zenoh peer, run the scenarios, print them."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=5.0, help="per scenario")
    parser.add_argument("--concurrency", type=int, default=8)
    parser.add_argument("--bus-scans", type=float, default=400.0,
                        help="raw scans a second on the bus in the last scenario")
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args()

    frames, world = bench_world()
    zenoh_port, http_port = free_port(), free_port()
    peer = open_session(ZenohSettings(mode="peer", listen=[f"tcp/127.0.0.1:{zenoh_port}"]))
    declared = serve_peer(peer, world)
    env = {**os.environ, "SCANFLOW_ZENOH_MODE": "peer",
           "SCANFLOW_ZENOH_CONNECT": f"tcp/127.0.0.1:{zenoh_port}",
           "SCANFLOW_GATEWAY_PORT": str(http_port), "SCANFLOW_GATEWAY_API_KEY": API_KEY,
           "SCANFLOW_GATEWAY_LOG_LEVEL": "WARNING", "SCANFLOW_GATEWAY_QUERY_TIMEOUT_S": "30"}
    log_path = Path(tempfile.mkdtemp(prefix="bench-gateway-")) / "gateway.log"
    with log_path.open("wb") as log:
        gateway = subprocess.Popen(
            [sys.executable, "-m", "services.gateway"], env=env, stdout=log, stderr=log
        )
    try:
        wait_for_port(http_port, 30.0)
        time.sleep(1.0)  # the peers find each other
        publish_poses(peer, 200)
        time.sleep(0.5)
        bus = BusScans(peer, frames[0].scan, args.bus_scans)
        results = asyncio.run(
            run(frames, args.seconds, args.concurrency, http_port, gateway.pid, bus))
    finally:
        gateway.terminate()
        gateway.wait(15)
        for entity in declared:
            entity.undeclare()
        peer.close()
    report = {"seconds": args.seconds, "concurrency": args.concurrency, "beams": 360,
              "bus_scans_per_s": args.bus_scans,
              "python": platform.python_version(), "cpus": os.cpu_count(),
              "gateway_log": str(log_path), **results}
    if args.json:
        print(json.dumps(report, indent=2))
        return
    print(f"gateway on loopback, {args.concurrency} in flight, {args.seconds} s per scenario")
    for name, r in results.items():
        print(f"{name:22s} {r['per_s']:8.1f} req/s  p50 {r['p50_ms']:7.2f} ms  "
              f"p99 {r['p99_ms']:7.2f} ms  gateway CPU {r['gateway_cpu_s']:5.2f} s  "
              f"({r['requests']} requests, {r['errors']} errors)")


if __name__ == "__main__":
    main()
