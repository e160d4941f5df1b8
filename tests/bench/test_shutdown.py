"""bench.shutdown: a stop of the whole system keeps every scan deskew took, and says so."""

from __future__ import annotations

import json

import pytest

from .conftest import run_bench

pytestmark = [pytest.mark.integration, pytest.mark.slow]


def test_a_stop_after_the_robot_sent_keeps_every_scan_taken() -> None:
    done = run_bench("shutdown", "--runs", "1", "--scans", "60", "--after", "1", "--json",
                     check=True)
    (run,) = json.loads(done.stdout)["runs"]
    assert run["exit_code"] == 0 and set(run["service_exits"].values()) == {"0"}
    assert set(run["service_exits"]) == {"ingest", "gateway", "deskew", "matcher", "mapserver",
                                         "router"}
    assert run["scans_sent"] == run["scans_accepted_before_stop"] == run["poses_kept"] == 60
    assert run["stop_s"] > 0.0


def test_bad_arguments_are_a_usage_error() -> None:
    done = run_bench("shutdown", "--runs", "0")
    assert done.returncode == 2 and "--runs and --scans must be >= 1" in done.stderr
