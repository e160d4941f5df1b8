"""Unit checks of the service shell pieces that need no network: counters, seqs, inbox, flow."""

from __future__ import annotations

import os
import subprocess
import sys
import threading
import time
from types import SimpleNamespace

import pytest
import zenoh
from hypothesis import given
from hypothesis import strategies as st

from services.common.counters import Counters, SeqTracker
from services.common.inbox import Inbox
from services.common.launch import Launcher
from services.common.resend import resend_range, resend_selector
from services.common.robots import RobotLimit
from services.common.shell import robots_only
from services.ingest.flow import CreditWindow, Pacer


def test_counters_from_many_threads():
    counters = Counters()

    def bump():
        for _ in range(1000):
            counters.add("x")

    threads = [threading.Thread(target=bump) for _ in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert counters.snapshot() == {"x": 4000}


@given(st.lists(st.integers(0, 50), min_size=1, max_size=60))
def test_seq_tracker_counts_every_missing_seq(seqs):
    tracker = SeqTracker()
    expected_missed = expected_restarts = 0
    last = -1
    for seq in seqs:
        if last >= 0 and seq <= last:
            expected_restarts += 1
        elif last >= 0:
            expected_missed += seq - last - 1
        last = seq
        tracker.observe("r/scan", seq)
    snap = tracker.snapshot()["r/scan"]
    assert snap == {
        "last_seq": seqs[-1],
        "received": len(seqs),
        "missed": expected_missed,
        "restarts": expected_restarts,
    }


def test_seq_tracker_resume_counts_the_gap_after_a_restart():
    tracker = SeqTracker()
    tracker.resume("r/pose", 9)
    assert tracker.is_restart("r/pose", 3)
    assert tracker.observe("r/pose", 15) == 5


def test_inbox_blocks_instead_of_dropping_and_releases_on_stop():
    stop = threading.Event()
    inbox = Inbox(2, stop)
    assert inbox.put("a", 1) and inbox.put("a", 2)
    done = threading.Event()

    def producer():
        inbox.put("a", 3)
        done.set()

    threading.Thread(target=producer, daemon=True).start()
    assert not done.wait(0.3)  # full: the producer waits
    assert inbox.get() == ("a", 1)
    assert done.wait(2.0)
    assert [inbox.get(), inbox.get()] == [("a", 2), ("a", 3)]
    stop.set()
    assert inbox.put("a", 4) is False  # stopping: refuses rather than block shutdown


def test_credit_window_waits_for_poses():
    stop = threading.Event()
    credit = CreditWindow(window=2, stall_timeout_s=30.0, stop=stop)
    assert credit.acquire("r", 0) and credit.acquire("r", 1)
    released = threading.Event()

    def publisher():
        credit.acquire("r", 3)  # needs the pose of scan 1
        released.set()

    threading.Thread(target=publisher, daemon=True).start()
    credit.on_pose("r", 0)
    assert not released.wait(0.3)
    credit.on_pose("r", 1)
    assert released.wait(2.0)
    assert credit.stalls == 0


def test_credit_window_resumes_after_a_stall_and_counts_it():
    credit = CreditWindow(window=1, stall_timeout_s=0.2, stop=threading.Event())
    assert credit.acquire("r", 5)  # nothing acknowledged, no pose comes: stall, then go
    assert credit.stalls == 1
    assert credit.acquire("r", 6)  # the window restarted at scan 5
    assert not credit.drain("r", 6, timeout_s=0.1)
    credit.on_pose("r", 6)
    assert credit.drain("r", 6, timeout_s=0.1)


class _RecordingStop(threading.Event):
    """A stop event whose waits are recorded instead of slept."""

    def __init__(self) -> None:
        super().__init__()
        self.waits: list[float] = []

    def wait(self, timeout=None):
        self.waits.append(timeout)
        return False


def test_pacer_follows_stamps_at_the_rate_and_ignores_backward_stamps(monkeypatch):
    monkeypatch.setattr(time, "monotonic", lambda: 1000.0)
    stop = _RecordingStop()
    pacer = Pacer(rate=10.0, stop=stop)
    for stamp in (100.0, 100.5, 101.0, 50.0):
        pacer.wait(stamp)
    assert stop.waits == pytest.approx([0.05, 0.1])


def test_pacer_at_rate_zero_never_waits():
    stop = _RecordingStop()
    pacer = Pacer(rate=0.0, stop=stop)
    for stamp in (1.0, 2.0, 3.0):
        pacer.wait(stamp)
    assert stop.waits == []


def _python(code: str) -> subprocess.Popen[bytes]:
    """A child that prints "ready" once `code` (its signal setup) ran, then sleeps."""
    script = f"import signal, sys, time\n{code}\nprint('ready', flush=True)\ntime.sleep(60)"
    proc = subprocess.Popen([sys.executable, "-c", script], stdout=subprocess.PIPE)
    assert proc.stdout is not None and proc.stdout.readline() == b"ready\n"
    return proc


def test_launcher_counts_death_by_its_own_sigterm_as_a_clean_stop(tmp_path):
    launcher = Launcher({}, tmp_path)
    launcher.processes["reraises"] = _python("")  # SIGTERM's default action, as uvicorn's re-raise
    launcher.processes["fails"] = _python(
        "signal.signal(signal.SIGTERM, lambda *_: sys.exit(3))"
    )
    launcher.processes["done"] = subprocess.Popen([sys.executable, "-c", "raise SystemExit(4)"])
    launcher.processes["done"].wait()
    assert launcher.stop_all() == {"done": 4, "fails": 3, "reraises": 0}


@given(st.integers(-1, 10**12), st.integers(1, 10**6))
def test_a_resend_selector_reads_back_as_its_range(after: int, span: int) -> None:
    selector = resend_selector("scanflow/r/map/resend", after, after + span)
    _, parameters = selector.split("?")
    assert resend_range(zenoh.Parameters(parameters)) == (after, after + span)


@pytest.mark.parametrize(
    ("parameters", "named"),
    [("through=4", "after"), ("after=x;through=4", "after"), ("after=2", "through"),
     ("after=-2;through=4", "after"), ("after=4;through=4", "through > after")],
)
def test_a_bad_resend_query_is_refused_naming_the_parameter(parameters: str, named: str) -> None:
    with pytest.raises(ValueError, match=named):
        resend_range(zenoh.Parameters(parameters))


@pytest.mark.parametrize(("service", "name", "value"), [
    ("router", "SCANFLOW_ROUTER_QUEUE_SIZE", "0"),
    ("ingest", "SCANFLOW_INGEST_RATE", "fast"),
    ("deskew", "SCANFLOW_DESKEW_ODOM_WAIT_S", "-1"),
    ("matcher", "SCANFLOW_FRONTEND_MIN_SCORE", "nan"),
    ("mapserver", "SCANFLOW_BACKEND_LOOP_CLOSURE", "perhaps"),
    ("gateway", "SCANFLOW_ZENOH_MODE", "satellite"),
])
def test_a_service_with_a_bad_setting_stops_at_start_naming_it(service, name, value):
    """One line naming the variable, before any session is opened (no router runs here)."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("SCANFLOW_")}
    done = subprocess.run([sys.executable, "-m", f"services.{service}"], env={**env, name: value},
                          capture_output=True, text=True, timeout=60)
    assert done.returncode == 1
    assert f"{service}: bad settings: {name}={value!r}" in done.stderr
    assert "Traceback" not in done.stderr


def test_a_query_for_the_services_keys_passes_robot_queryables_by():
    """A metrics scrape (stats/*/*) also reaches `*/map/resend`: not a robot named 'stats'."""
    seen = []
    handler = robots_only(seen.append, "site/sf")
    for key in ("site/sf/stats/matcher/0", "site/sf/health/deskew/0", "site/sf/r1/map/resend",
                "site/sf/statsbot/initial_pose"):
        handler(SimpleNamespace(key_expr=key))
    assert [q.key_expr for q in seen] == ["site/sf/r1/map/resend", "site/sf/statsbot/initial_pose"]


def test_a_robot_limit_admits_the_known_and_the_first_n_and_reports_each_refused_once():
    refused: list[tuple[str, bool]] = []
    limit = RobotLimit(2, lambda robot_id, first: refused.append((robot_id, first)))
    held: dict[str, object] = {}
    for robot_id in ("a", "b", "c", "a", "c", "d"):
        if limit.admits(robot_id, held):
            held.setdefault(robot_id, object())
    assert sorted(held) == ["a", "b"]
    assert refused == [("c", True), ("c", False), ("d", True)]
    with pytest.raises(ValueError, match="max_robots"):
        RobotLimit(0, lambda *_: None)
