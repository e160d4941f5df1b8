"""bench.cpu: another process's CPU seconds, read from /proc."""

from __future__ import annotations

import os

from bench.cpu import process_cpu_s


def test_the_cpu_seconds_of_a_process_count_its_work() -> None:
    before = process_cpu_s(os.getpid())
    total = 0
    while process_cpu_s(os.getpid()) <= before:  # a clock tick of work at least
        total += sum(range(10_000))
    assert total > 0 and process_cpu_s(os.getpid()) > before >= 0.0
