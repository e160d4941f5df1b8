"""bench.maps runs end to end on a coarse path and reports what BENCHMARKS.md quotes."""

import json
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]


def test_bench_maps_reports_times_and_memory():
    out = subprocess.run(
        [sys.executable, "-m", "bench.maps", "--json", "--step-m", "8", "--rebuilds", "1"],
        cwd=REPO,
        capture_output=True,
        text=True,
        check=True,
        timeout=120,
    )
    result = json.loads(out.stdout)
    mapping, revisit = result["phases"]["mapping"], result["phases"]["revisit"]
    assert result["resolution_m"] == 0.05
    assert mapping["scans"] == revisit["scans"] > 10
    assert mapping["insert_ms"]["mean"] > 0 and result["full_rebuild_field0_ms"]["mean"] > 0
    assert result["mapped_area_m2"] > 1500  # the whole 40 m x 40 m building
    # Revisiting a mapped area grows neither the grid nor the views.
    assert revisit["storage_generation"] == mapping["storage_generation"]
    assert revisit["map_bytes"] == mapping["map_bytes"]
