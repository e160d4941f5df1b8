"""bench.scan_to_map runs end to end on a few real pairs and a short simulated tour."""

import json
import math

import numpy as np
import pytest
from scanflow.maps.occupancy import OccupancyGrid

from bench.data import corrected_log
from bench.scan_to_map import centres_only

from .conftest import run_bench

LOG = corrected_log("intel")


@pytest.mark.skipif(not LOG.exists(), reason=f"real log {LOG} not available")
def test_bench_scan_to_map_reports_every_method_both_map_fields_and_ndt_on_a_map():
    args = ["--json", "--pairs", "3", "--sim-seconds", "1.5", "--map-scans", "12"]
    args += ["--data", str(LOG)]
    out = run_bench("scan_to_map", *args, timeout_s=120, check=True)
    result = json.loads(out.stdout)
    assert result["real"]["pairs"] == 3
    for method in ("gn", "lm", "ndt"):
        row = result["real"][method]
        assert row["ms_median"] > 0 and row["cpu_ms_median"] >= 0
        assert 0.0 <= row["success_5cm_0.5deg"] <= row["success_10cm_1deg"] <= 1.0
    sim = result["sim"]
    assert sim["scans"] == 15
    for fields in ("mean_hits", "cell_centres"):
        assert math.isfinite(sim[fields]["trans_mm_median"])
        assert sim[fields]["trans_mm_median"] <= sim[fields]["trans_mm_p95"]
    on_map = result["map"]
    assert on_map["matches"] == 11 and on_map["final_occupied_cells"] > 0
    kept, rebuilt = on_map["ndt_kept_cells"], on_map["ndt_rebuilt_cells"]
    assert kept["ms_median"] > 0 and rebuilt["ms_median"] > 0
    assert kept["success_10cm_1deg"] == rebuilt["success_10cm_1deg"]
    assert on_map["max_pose_difference"] < 1e-6


def test_centres_only_keeps_the_log_odds_and_drops_the_hits() -> None:
    grid = OccupancyGrid()
    grid.insert_scan(np.array([[1.0, 0.0], [0.0, 1.0]]), np.zeros(2))
    plain = centres_only(grid)
    assert plain.extent == grid.extent and np.array_equal(plain.log_odds, grid.log_odds)
    assert grid.hit_sums.any() and not plain.hit_sums.any()


def test_centres_only_of_an_empty_grid_is_an_empty_grid() -> None:
    """An empty map has no extent (None): its copy is as empty, not an AttributeError."""
    plain = centres_only(OccupancyGrid())
    assert plain.is_empty and plain.extent is None
