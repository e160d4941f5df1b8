"""bench.maps runs end to end on a coarse path (and a short real log) and reports what
BENCHMARKS.md quotes."""

import json

import pytest

from bench.data import corrected_log

from .conftest import run_bench


def test_bench_maps_reports_times_and_memory():
    out = run_bench("maps", "--json", "--step-m", "8", "--rebuilds", "1", timeout_s=120,
                    check=True)
    result = json.loads(out.stdout)
    mapping, revisit = result["phases"]["mapping"], result["phases"]["revisit"]
    assert result["resolution_m"] == 0.05
    assert mapping["scans"] == revisit["scans"] > 10
    assert mapping["insert_ms"]["mean"] > 0 and result["full_rebuild_field0_ms"]["mean"] > 0
    assert result["mapped_area_m2"] > 1500  # the whole 40 m x 40 m building
    # Revisiting a mapped area grows neither the grid nor the views.
    assert revisit["storage_generation"] == mapping["storage_generation"]
    assert revisit["map_bytes"] == mapping["map_bytes"]


LOG = corrected_log("intel")


@pytest.mark.skipif(not LOG.exists(), reason=f"real log {LOG} not available")
def test_bench_maps_times_view_refresh_and_rebuild_on_a_small_and_a_large_map():
    args = ["--json", "--views-only", "--data", str(LOG), "--limit", "60", "--tile-cells", "8"]
    out = run_bench("maps", *args, "--small-scans", "10", "--samples", "5", timeout_s=120,
                    check=True)
    views = json.loads(out.stdout)["views"]
    assert views["scans"] == 60 and views["tile_cells"] == 8 and "phases" not in views
    small, large = views["small"], views["large"]
    assert (small["after_scans"], large["after_scans"]) == (15, 60)
    assert 0 < small["occupied_cells"] <= large["occupied_cells"]
    for window in (small, large):
        assert window["ndt_cells"] > 0 and len(window["overlapping_blocks"]) == 3
        assert all(blocks > 0 for blocks in window["overlapping_blocks"])
        for view in ("field0", "pyramid", "maxpool", "ndt", "overlapping"):
            assert window[f"{view}_refresh_ms"]["p50"] <= window[f"{view}_refresh_ms"]["max"]
            assert window[f"{view}_rebuild_ms"]["mean"] > 0
    # Every keyframe's insert is timed, and the redraw of all of them.
    assert 0 < views["insert_ms"]["p50"] <= views["insert_ms"]["max"]
    assert views["inserts_total_s"] >= views["insert_ms"]["max"] / 1e3
    assert views["redraw_s"] > 0
