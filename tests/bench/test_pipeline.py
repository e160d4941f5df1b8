"""bench.pipeline: observer, stats and pinning on a stand-in bus; each section for real."""

from __future__ import annotations

import os
import sys
import threading
from collections.abc import Callable
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest
from scanflow import keys
from scanflow.config import LaunchSettings
from scanflow.geometry import Pose2D
from scanflow.scan import LaserScan
from scanflow.wire import PoseEstimateMessage, ScanMessage, ServiceStatsMessage

from bench import pipeline
from bench.pipeline import FREIBURG, SERVICES, Observer, stats, threads_on

needs_log = pytest.mark.skipif(not FREIBURG.exists(), reason=f"real log {FREIBURG} not available")


def real_services(test: Callable[[], None]) -> Callable[[], None]:
    """Integration, slow, and in make test's second process: real services for ~10 s each
    (balances its two processes)."""
    for mark in (pytest.mark.second_lane, pytest.mark.slow, pytest.mark.integration):
        test = mark(test)
    return test


class FakeSession:
    """Subscriptions by key, replies to queries by selector; delivers samples by hand."""

    def __init__(self, replies: dict[str, list[Any]] | None = None) -> None:
        self.callbacks: dict[str, Any] = {}
        self.undeclared: list[str] = []
        self.replies = replies or {}

    def declare_subscriber(self, key: str, callback: Any) -> Any:
        self.callbacks[key] = callback
        return SimpleNamespace(undeclare=lambda: self.undeclared.append(key))

    def deliver(self, key: str, payload: bytes) -> None:
        self.callbacks[key](SimpleNamespace(payload=SimpleNamespace(to_bytes=lambda: payload)))

    def get(self, selector: str, timeout: float) -> list[Any]:
        return self.replies.get(selector, [])


def raw(seq: int) -> bytes:
    return ScanMessage(LaserScan(np.ones(8, np.float32), 0.0, 0.1, seq=seq)).encode()


def pose(seq: int) -> bytes:
    return PoseEstimateMessage("robot", seq, 0.1 * seq, Pose2D(), np.eye(3), "tracked", "gn", 3,
                               0.5).encode()


def test_the_observer_times_raw_scans_and_poses_by_seq_and_counts_poses_across_replays() -> None:
    session = FakeSession()
    observer = Observer(session)
    assert set(session.callbacks) == {keys.raw_scan(), keys.pose()}
    for seq in range(3):
        session.deliver(keys.raw_scan(), raw(seq))
        session.deliver(keys.pose(), pose(seq))
    first = dict(observer.pose_s)
    for seq in range(3):  # the poses of a replay, its raw scans not received
        session.deliver(keys.pose(), pose(seq))
    assert sorted(observer.raw_s) == sorted(observer.pose_s) == [0, 1, 2]
    assert observer.poses == 6  # a replay restarts the seqs: the count goes on
    assert all(observer.raw_s[s] <= observer.pose_s[s] for s in range(3))
    assert all(observer.pose_s[s] > first[s] for s in range(3))  # the latest arrival is kept
    observer.wait_poses(6, timeout_s=0.0)
    with pytest.raises(TimeoutError, match="6 of 7 poses"):
        observer.wait_poses(7, timeout_s=0.05)


class SignallingCondition(threading.Condition):
    """A condition that says when a thread starts waiting on it."""

    def __init__(self) -> None:
        super().__init__()
        self.waiting = threading.Event()

    def wait(self, timeout: float | None = None) -> bool:
        self.waiting.set()
        return super().wait(timeout)


def test_a_waiter_for_poses_is_woken_by_the_pose_that_completes_the_count() -> None:
    session = FakeSession()
    observer = Observer(session)
    observer.done = SignallingCondition()
    waiter = threading.Thread(target=observer.wait_poses, args=(2, None), daemon=True)
    waiter.start()
    assert observer.done.waiting.wait(30.0)  # waiting with no timeout: only a wake-up ends it
    for seq in range(2):
        session.deliver(keys.pose(), pose(seq))
    waiter.join(30.0)
    assert not waiter.is_alive() and observer.poses == 2


def test_first_raw_only_keeps_the_first_raw_scan_and_stops_listening_to_raw_scans() -> None:
    session = FakeSession()
    observer = Observer(session)
    with pytest.raises(TimeoutError, match="no raw scan"):
        observer.first_raw_only(timeout_s=0.05)
    assert session.undeclared == []
    threading.Timer(0.1, session.deliver, (keys.raw_scan(), raw(4))).start()
    observer.first_raw_only(timeout_s=30.0)
    assert list(observer.raw_s) == [4] and session.undeclared == [keys.raw_scan()]


def test_stats_is_the_first_ok_reply_of_instance_0() -> None:
    message = ServiceStatsMessage("matcher", "0", 1.0, {"in": 3}, {"worker_busy_s": 2.5})
    error = SimpleNamespace(ok=None)
    ok = SimpleNamespace(ok=SimpleNamespace(payload=SimpleNamespace(
        to_bytes=lambda: message.encode())))
    session = FakeSession({keys.stats("matcher", "0"): [error, ok]})
    assert stats(session, "matcher").gauges == {"worker_busy_s": 2.5}
    with pytest.raises(RuntimeError, match="no stats from deskew"):
        stats(session, "deskew")


def affinity(tid: int = 0) -> set[int]:
    return os.sched_getaffinity(tid)


def test_threads_on_pins_every_thread_of_the_process_and_restores_them() -> None:
    before = affinity()
    if len(before) < 2:
        pytest.skip("needs two CPUs")
    one = [min(before)]
    started = threading.Event()
    stop = threading.Event()
    tids: list[int] = []

    def idle() -> None:
        tids.append(threading.get_native_id())
        started.set()
        stop.wait(30.0)

    older = threading.Thread(target=idle)
    older.start()
    started.wait(30.0)
    try:
        with threads_on(one):
            assert affinity() == affinity(tids[0]) == set(one)
            newer = []
            thread = threading.Thread(target=lambda: newer.append(affinity()))
            thread.start()
            thread.join()
            assert newer == [set(one)]
        assert affinity() == affinity(tids[0]) == before
        with threads_on([]):
            assert affinity() == before
    finally:
        stop.set()
        older.join()


def test_a_missing_log_is_named_before_anything_starts(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    missing = tmp_path / "missing.log.gz"
    monkeypatch.setattr(sys, "argv", ["bench.pipeline", "--only", "memory", "--data",
                                      str(missing)])
    with pytest.raises(SystemExit, match=f"{missing} not found"):
        pipeline.main()


@pytest.mark.integration
def test_transport_through_the_router_alone() -> None:
    report = pipeline.transport(count=200, latency_count=50)
    scan = LaserScan(np.ones(1081, np.float32), -2.356, 0.004363, range_max_m=30.0)
    assert report["payload_bytes"] == len(ScanMessage(scan).encode())
    assert report["burst_messages"] == 200
    rate = report["msgs_per_s"]
    assert rate > 0
    assert report["mbytes_per_s"] == pytest.approx(rate * report["payload_bytes"] / 1e6)
    assert 0 < report["latency_ms_p50"] <= report["latency_ms_p99"]


@real_services
@needs_log
def test_throughput_of_the_services_against_the_in_process_pipeline() -> None:
    report = pipeline.throughput(FREIBURG, 20, rounds=1)
    assert report["log"] == FREIBURG.name and report["scans"] == 20
    assert report["matcher_cpus"] == LaunchSettings().matcher_cpus
    (round_,) = report["rounds"]
    assert round_["scans"] == 20
    assert report["services_vs_in_process_median"] == round_["services_vs_in_process"]
    assert (report["services_vs_in_process_reading_log_median"]
            == round_["services_vs_in_process_reading_log"])
    # In-process time over the services' time: the services' rate over the in-process rate.
    services = round_["services_scans_per_s"]
    assert round_["services_vs_in_process"] == pytest.approx(
        services / round_["in_process_scans_per_s"])
    assert round_["services_vs_in_process_reading_log"] == pytest.approx(
        services / round_["in_process_reading_log_scans_per_s"])
    assert round_["in_process_cpu_ms_per_scan"] > 0 and round_["load_average"] >= 0
    assert set(round_["per_scan_ms"]) == set(SERVICES)
    for name, figures in round_["per_scan_ms"].items():
        assert set(figures) == {"cpu", "worker_busy", "put"}
        assert all(value >= 0 for value in figures.values()), name
    assert round_["per_scan_ms"]["matcher"]["worker_busy"] > 0
    assert round_["per_scan_ms"]["matcher"]["cpu"] > 0


@real_services
def test_latency_from_ingest_to_pose_at_real_time_rate() -> None:
    report = pipeline.latency(1.0)
    assert report["scans"] == 10 and report["source"].startswith("simulator, 1 s at 10 Hz")
    assert 0 < report["latency_ms_p50"] <= report["latency_ms_p99"] <= report["latency_ms_max"]


@real_services
@needs_log
def test_memory_of_every_service_after_each_replay() -> None:
    report = pipeline.memory(FREIBURG, 10, replays=2)
    assert report["log"] == FREIBURG.name and report["scans_per_replay"] == 10
    assert set(report["rss_mib_after_each_replay"]) == set(SERVICES)
    for name, rss in report["rss_mib_after_each_replay"].items():
        assert len(rss) == 2 and all(mib > 50 for mib in rss), name  # MiB: a Python process
    first, second = report["map_mib_after_each_replay"]
    assert 0 < first <= second
