"""bench.cpu: another process's CPU seconds, read from /proc."""

from __future__ import annotations

import os

from bench.cpu import process_cpu_s


def test_the_cpu_seconds_of_a_process_count_its_work() -> None:
    before = process_cpu_s(os.getpid())
    for _ in range(100_000):  # some seconds of work, far more than the clock tick it needs
        sum(range(10_000))
        if process_cpu_s(os.getpid()) > before:
            break
    # Checked after work, not before it: a loaded machine can tick between `before` and a check.
    assert process_cpu_s(os.getpid()) > before >= 0.0
