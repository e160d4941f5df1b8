"""bench.map_state: the matcher's whole map against the same inserts sent again."""

from __future__ import annotations

import json

import pytest

from bench.data import corrected_log
from bench.map_state import main

INTEL = corrected_log("intel")


@pytest.mark.skipif(not INTEL.exists(), reason="the shared intel log is not beside the checkout")
def test_both_ways_end_with_the_trackers_map_and_are_measured(capsys) -> None:
    main(["--data", str(INTEL), "--limit", "40", "--json"])
    report = json.loads(capsys.readouterr().out)
    assert report["scans"] == 40 and 0 < report["inserts"] <= 40
    for way in ("state", "inserts_again"):
        assert report[way]["bytes"] > 0 and report[way]["take_ms"] > 0
    assert report["state"]["build_ms_under_lock"] > 0
