"""Ingest's flow control: the credit window and the pacer."""

from __future__ import annotations

import threading
import time

import pytest

from services.ingest.flow import CreditWindow, Pacer


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
