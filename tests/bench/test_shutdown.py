"""bench.shutdown: a stop of the whole system keeps every scan deskew took, and says so."""

from __future__ import annotations

import json

import pytest

from bench.shutdown import main

from .conftest import run_bench, usage_error

# A whole system stopped after 200 scans (about 30 s): `make test` runs it beside the rest
# (tools/run-tests.sh), with the container tests.
pytestmark = [pytest.mark.integration, pytest.mark.slow, pytest.mark.second_lane]


def test_a_stop_right_after_the_robot_sent_keeps_every_scan() -> None:
    """Ctrl-C straight after the last put: scans still on the wire reach deskew during its
    drain, and every stage hands its drain on to the next (af05050 kept 102 of 200 here)."""
    done = run_bench("shutdown", "--runs", "1", "--scans", "200", "--after", "0", "--json",
                     check=True, timeout_s=600.0)
    (run,) = json.loads(done.stdout)["runs"]
    assert run["exit_code"] == 0 and set(run["service_exits"].values()) == {"0"}
    assert set(run["service_exits"]) == {"ingest", "gateway", "deskew", "matcher", "mapserver",
                                         "router"}
    assert run["scans_sent"] == run["poses_kept"] == 200
    assert run["stop_s"] > 0.0


def test_bad_arguments_are_a_usage_error(capsys: pytest.CaptureFixture[str]) -> None:
    assert "--runs and --scans must be >= 1" in usage_error(main, capsys, "--runs", "0")
