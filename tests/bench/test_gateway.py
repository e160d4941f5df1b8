"""bench.gateway: every scenario (posted scans and other sources' scans on the bus among them)
runs against the real gateway process, without an error, and is timed."""

from __future__ import annotations

import json

from .conftest import run_bench


def test_every_scenario_answers_and_is_timed() -> None:
    done = run_bench("gateway", "--seconds", "0.3", "--concurrency", "2", "--bus-scans", "100",
                     "--json", timeout_s=240, check=True)
    report = json.loads(done.stdout)
    scenarios = ("latest_pose", "match_scan_to_scan", "match_scan_to_map", "post_scan",
                 "latest_pose_bus_scans")
    for name in scenarios:
        assert report[name]["requests"] > 0 and report[name]["errors"] == 0, (name, report)
        assert report[name]["gateway_cpu_s"] >= 0.0
