"""The distributed pipeline's numbers: Zenoh transport alone, end-to-end throughput against the
in-process pipeline, ingest-to-pose latency at real-time rate, and resident memory per service.

    python -m bench.pipeline [--json] [--data LOG] [--limit N] [--rounds K]
                             [--only transport,throughput,latency,memory]

Every service runs as its own process through a router on a free loopback port, exactly as
`scanflow up` starts them (matchers on CPUs of their own; `SCANFLOW_LAUNCH_MATCHER_CPUS=0` in
the environment measures them unpinned). Latencies are measured by one observer process that
sees both the raw scan and its pose on the bus (one clock). The services and the in-process
baseline both read SCANFLOW_BACKEND_* from the environment (loop closure off by default).
"""

from __future__ import annotations

import argparse
import json
import os
import tempfile
import threading
import time
from collections.abc import Callable, Iterable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np
import zenoh
from scanflow import keys
from scanflow.config import BackendSettings, LaunchSettings, ZenohSettings
from scanflow.pipeline import Pipeline
from scanflow.scan import LaserScan
from scanflow.wire import PoseEstimateMessage, ScanMessage, ServiceStatsMessage

from bench.cpu import process_cpu_s
from bench.data import corrected_log
from services.common.launch import PIPELINE as SERVICES
from services.common.launch import Launcher, free_port
from services.common.process import available_cpus
from services.common.zsession import open_session
from services.ingest.sources import source_events

FREIBURG = corrected_log("freiburg-079")


@contextmanager
def running(services: tuple[str, ...], **settings: str) -> Iterator[tuple[Launcher, Any]]:
    """A router, `services` and an observer session; everything stopped on exit. With a CPU
    plan this process (the observer's Zenoh and callback threads) keeps off the matchers' CPUs
    while the services run, as the light services do."""
    with tempfile.TemporaryDirectory(prefix="scanflow-bench-") as tmp:
        launcher = Launcher.local(
            Path(tmp) / "logs", free_port(), SCANFLOW_MAPSERVER_DATA_DIR=str(Path(tmp) / "data"),
            **settings,
        )
        with threads_on(launcher.cpus.shared if launcher.cpus is not None else []):
            launcher.start("router")
            session = open_session(
                ZenohSettings(connect=[f"tcp/127.0.0.1:{launcher.zenoh_port}"])
            )
            try:
                for name in services:
                    launcher.start(name)
                launcher.wait_healthy(services)
                yield launcher, session
            finally:
                session.close()
                launcher.stop_all()


@contextmanager
def threads_on(cpus: list[int]) -> Iterator[None]:
    """Every thread of this process (and those it starts meanwhile) on `cpus`, restored after;
    empty: leave them where they are."""
    if not cpus:
        yield
        return
    before = available_cpus()

    def pin(to: list[int]) -> None:
        for tid in os.listdir("/proc/self/task"):
            try:
                os.sched_setaffinity(int(tid), to)
            except (ProcessLookupError, PermissionError):  # a thread that just ended
                continue

    pin(cpus)
    try:
        yield
    finally:
        pin(before)


class Observer:
    """Arrival times (one clock) of raw scans and poses by (robot, seq), and the pose count."""

    def __init__(self, session: Any) -> None:
        self.raw_s: dict[int, float] = {}
        self.pose_s: dict[int, float] = {}
        self.poses = 0  # every pose received, across replays
        self.done = threading.Condition()
        self._raw = session.declare_subscriber(
            keys.raw_scan(), self._on(self.raw_s, ScanMessage.decode)
        )
        self._pose = session.declare_subscriber(
            keys.pose(), self._on(self.pose_s, PoseEstimateMessage.decode)
        )

    def first_raw_only(self, timeout_s: float) -> None:
        """Keep the first raw scan's arrival, then stop receiving raw scans: a throughput run
        needs only its start, and this process shares the services' CPUs."""
        with self.done:
            if not self.done.wait_for(lambda: self.raw_s, timeout_s):
                raise TimeoutError(f"no raw scan after {timeout_s} s")
        self._raw.undeclare()

    def _on(
        self, table: dict[int, float], decode: Callable[[bytes], ScanMessage | PoseEstimateMessage]
    ) -> Callable[[Any], None]:
        def record(sample: Any) -> None:
            now = time.perf_counter()
            table[decode(sample.payload.to_bytes()).seq] = now
            with self.done:
                self.poses += table is self.pose_s
                self.done.notify_all()

        return record

    def wait_poses(self, count: int, timeout_s: float) -> None:
        """Wait until `count` poses arrived in all (replays included)."""
        with self.done:
            if not self.done.wait_for(lambda: self.poses >= count, timeout_s):
                raise TimeoutError(f"{self.poses} of {count} poses after {timeout_s} s")


def stats(session: Any, service: str) -> ServiceStatsMessage:
    """The stats of `service` instance 0 (first reply within 5 s); RuntimeError when none."""
    for reply in session.get(keys.stats(service, "0"), timeout=5.0):
        if reply.ok is not None:
            return ServiceStatsMessage.decode(reply.ok.payload.to_bytes())
    raise RuntimeError(f"no stats from {service}")


def transport(count: int = 3000, latency_count: int = 500) -> dict[str, Any]:
    """A 1081-beam ScanMessage through the router alone: burst msgs/s, paced latency."""
    scan = LaserScan(
        ranges_m=np.random.default_rng(0).uniform(0.5, 20.0, 1081).astype(np.float32),
        angle_min_rad=-2.356, angle_increment_rad=0.004363, range_max_m=30.0,
    )
    payload = ScanMessage(scan).encode()
    with running(()) as (launcher, session):
        receiver = open_session(ZenohSettings(connect=[f"tcp/127.0.0.1:{launcher.zenoh_port}"]))
        arrivals: list[float] = []
        done = threading.Event()

        def on_sample(sample: Any) -> None:
            arrivals.append(time.perf_counter())
            if len(arrivals) == count + latency_count:
                done.set()

        sub = receiver.declare_subscriber("bench/scan", on_sample)
        pub = session.declare_publisher(
            "bench/scan",
            congestion_control=zenoh.CongestionControl.BLOCK,
            reliability=zenoh.Reliability.RELIABLE,
        )
        time.sleep(1.0)
        t0 = time.perf_counter()
        for _ in range(count):
            pub.put(payload)
        while len(arrivals) < count:
            time.sleep(0.001)
        burst_s = arrivals[count - 1] - t0
        sent: list[float] = []
        for _ in range(latency_count):
            sent.append(time.perf_counter())
            pub.put(payload)
            time.sleep(0.002)
        done.wait(30.0)
        latency_ms = 1e3 * (np.array(arrivals[count:]) - np.array(sent[: len(arrivals) - count]))
        sub.undeclare()
        receiver.close()
    return {
        "payload_bytes": len(payload),
        "burst_messages": count,
        "msgs_per_s": count / burst_s,
        "mbytes_per_s": count * len(payload) / burst_s / 1e6,
        "latency_ms_p50": float(np.percentile(latency_ms, 50)),
        "latency_ms_p99": float(np.percentile(latency_ms, 99)),
    }


def throughput(log: Path, limit: int | None, rounds: int = 1) -> dict[str, Any]:
    """Scans/s through ingest -> deskew -> matcher (-> map server) as fast as backpressure
    allows, against the in-process pipeline, `rounds` times alternating (each ratio pairs runs
    minutes apart, so load drift on a shared machine shows). Two baselines: the in-process
    pipeline on events already in memory (strict: the services also pay for reading the log,
    in ingest), and reading the log as it goes, as ingest does (like for like). Per service and
    scan: CPU (Linux /proc), worker busy time and time blocked in puts, in ms."""
    events = list(source_events(str(log), "robot", 1.0, 0, limit))
    scans = sum(isinstance(e, LaserScan) for e in events)
    runs = [_throughput_round(log, limit, events, scans) for _ in range(rounds)]
    return {
        "log": log.name,
        "scans": scans,
        "matcher_cpus": LaunchSettings().matcher_cpus,
        "services_vs_in_process_median": float(
            np.median([run["services_vs_in_process"] for run in runs])
        ),
        "services_vs_in_process_reading_log_median": float(
            np.median([run["services_vs_in_process_reading_log"] for run in runs])
        ),
        "rounds": runs,
    }


def _in_process(events: Iterable[Any]) -> tuple[float, float]:
    """(wall s, CPU s) of the in-process pipeline over `events` (a list, or a log being read),
    with the back end as SCANFLOW_BACKEND_* sets it (as the services have it)."""
    pipeline = Pipeline(backend=BackendSettings())
    t0, cpu0 = time.perf_counter(), time.process_time()
    for event in events:
        if isinstance(event, LaserScan):
            pipeline.process(event)
        else:
            pipeline.add_odometry(event)
    return time.perf_counter() - t0, time.process_time() - cpu0


def _throughput_round(
    log: Path, limit: int | None, events: list[Any], scans: int
) -> dict[str, Any]:
    in_process_s, in_process_cpu_s = _in_process(events)
    reading_s, _ = _in_process(source_events(str(log), "robot", 1.0, 0, limit))
    settings = {"SCANFLOW_INGEST_LOG": str(log), "SCANFLOW_INGEST_RATE": "0"}
    if limit is not None:
        settings["SCANFLOW_INGEST_LIMIT"] = str(limit)
    with running(SERVICES) as (launcher, session):
        observer = Observer(session)
        before = {name: _load(launcher, session, name) for name in SERVICES}
        launcher.start("ingest", **settings)
        observer.first_raw_only(timeout_s=120)
        observer.wait_poses(scans, timeout_s=20 * in_process_s + 120)
        services_s = max(observer.pose_s.values()) - min(observer.raw_s.values())
        after = {name: _load(launcher, session, name) for name in SERVICES}
    per_scan_ms = {
        name: {k: round(1e3 * (after[name][k] - before[name][k]) / scans, 3) for k in after[name]}
        for name in SERVICES
    }
    return {
        "scans": scans,
        "in_process_scans_per_s": scans / in_process_s,
        "in_process_cpu_ms_per_scan": 1e3 * in_process_cpu_s / scans,
        "in_process_reading_log_scans_per_s": scans / reading_s,
        "services_scans_per_s": scans / services_s,
        "services_vs_in_process": in_process_s / services_s,
        "services_vs_in_process_reading_log": reading_s / services_s,
        "load_average": os.getloadavg()[0],
        "per_scan_ms": per_scan_ms,
    }


def _load(launcher: Launcher, session: Any, name: str) -> dict[str, float]:
    """A service's CPU seconds so far (all threads), its worker's busy seconds and the
    seconds its puts took (blocked by a slow subscriber)."""
    gauges = stats(session, name).gauges
    return {
        "cpu": process_cpu_s(launcher.processes[name].pid),
        "worker_busy": gauges["worker_busy_s"],
        "put": gauges["put_s"],
    }


def latency(duration_s: float) -> dict[str, Any]:
    """Ingest publish -> pose publish on the simulator at real-time rate (10 Hz)."""
    settings = {"SCANFLOW_INGEST_RATE": "1", "SCANFLOW_INGEST_SIM_DURATION_S": str(duration_s)}
    with running(SERVICES) as (launcher, session):
        observer = Observer(session)
        launcher.start("ingest", **settings)
        observer.wait_poses(int(duration_s * 10), timeout_s=duration_s + 60)
        ms = [1e3 * (observer.pose_s[s] - observer.raw_s[s]) for s in observer.pose_s]
    return {
        "source": f"simulator, {duration_s:.0f} s at 10 Hz, 360 beams",
        "scans": len(ms),
        "latency_ms_p50": float(np.percentile(ms, 50)),
        "latency_ms_p99": float(np.percentile(ms, 99)),
        "latency_ms_max": float(np.max(ms)),
    }


def memory(log: Path, limit: int | None, replays: int = 3) -> dict[str, Any]:
    """RSS of every service after each of `replays` replays of the log in a row, each taken
    once that replay is done and before the next starts (every map full, at the same point)."""
    settings = {"SCANFLOW_INGEST_LOG": str(log), "SCANFLOW_INGEST_RATE": "0"}
    if limit is not None:
        settings["SCANFLOW_INGEST_LIMIT"] = str(limit)
    scans = sum(isinstance(e, LaserScan) for e in source_events(str(log), "robot", 1.0, 0, limit))
    rss_mib: dict[str, list[float]] = {name: [] for name in SERVICES}
    map_mib = []
    with running(SERVICES) as (launcher, session):
        observer = Observer(session)
        for replay in range(1, replays + 1):
            launcher.start("ingest", **settings)  # each run restarts the seqs: a new replay
            observer.wait_poses(replay * scans, timeout_s=3600)
            launcher.processes["ingest"].wait(60)  # drained and closed
            time.sleep(1.0)  # let the map server apply the last poses
            for name in SERVICES:
                figures = stats(session, name).gauges
                rss_mib[name].append(round(figures["rss_bytes"] / 2**20, 1))
                if name == "mapserver":
                    map_mib.append(round(figures.get("robot.map_bytes", 0.0) / 2**20, 1))
    return {
        "log": log.name,
        "scans_per_replay": scans,
        "rss_mib_after_each_replay": rss_mib,
        "map_mib_after_each_replay": map_mib,
    }


def main() -> None:
    """Run the --only sections (transport, throughput, latency, memory) and print them."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--json", action="store_true", help="print one JSON object")
    parser.add_argument("--data", type=Path, default=FREIBURG, help="the log (freiburg-079)")
    parser.add_argument("--limit", type=int, default=None, help="scans of the log to use")
    parser.add_argument("--latency-s", type=float, default=30.0, help="simulated seconds")
    parser.add_argument("--replays", type=int, default=3, help="replays for the memory figure")
    parser.add_argument("--only", default="transport,throughput,latency,memory")
    parser.add_argument("--rounds", type=int, default=3, help="throughput rounds (alternating)")
    args = parser.parse_args()
    wanted = set(args.only.split(","))
    needs_log = wanted & {"throughput", "memory"}
    if needs_log and not args.data.exists():
        raise SystemExit(f"{args.data} not found (set SCANFLOW_DATA_DIR or --data)")
    results: dict[str, Any] = {"date": time.strftime("%Y-%m-%d"), "cpus": os.cpu_count()}
    if "transport" in wanted:
        results["transport"] = transport()
    if "throughput" in wanted:
        results["throughput"] = throughput(args.data, args.limit, args.rounds)
    if "latency" in wanted:
        results["latency"] = latency(args.latency_s)
    if "memory" in wanted:
        results["memory"] = memory(args.data, args.limit, args.replays)
    if args.json:
        print(json.dumps(results, indent=2))
        return
    for section, figures in results.items():
        print(f"{section}: {figures}")


if __name__ == "__main__":
    main()
