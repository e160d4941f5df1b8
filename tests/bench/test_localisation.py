"""bench.localisation: the success figures and the CLI end to end on a real log."""

import json

import pytest

from bench.data import corrected_log
from bench.localisation import main, rates

from .conftest import run_bench, usage_error

LOG = corrected_log("aces")


def test_rates_count_both_bars() -> None:
    errs = [(0.01, 0.1), (0.07, 0.2), (0.02, 0.9), (0.5, 0.0)]  # (metres, degrees)
    r = rates(errs)
    assert r["success_5cm_0.5deg"] == 0.25 and r["success_10cm_1deg"] == 0.75
    assert r["t50_m"] == pytest.approx(0.045)


def test_bad_arguments_are_named(capsys: pytest.CaptureFixture[str]) -> None:
    assert "--queries must be >= 1" in usage_error(main, capsys, "--data", "x.gz", "--queries", "0")


@pytest.mark.skipif(not LOG.exists(), reason=f"real log {LOG} not available")
def test_bench_localisation_json_on_a_real_log() -> None:
    # A small map and one query: the full-resolution baseline search takes ~10 s a query here.
    out = run_bench("localisation", "--data", str(LOG), "--limit", "20", "--queries", "1",
                    "--json")
    assert out.returncode == 0, out.stderr
    report = json.loads(out.stdout)
    assert set(report["global"]) == {"level_1", "level_0_baseline"}
    for g in report["global"].values():
        assert g["queries"] == 1 and 0.0 <= g["success_5cm_0.5deg"] <= g["success_10cm_1deg"] <= 1
    localise, slam = report["tracking"]["localise"], report["tracking"]["slam_baseline"]
    assert localise["scans"] == slam["scans"] == 10
    assert localise["statuses"]["localised"] == 1 and "initialised" not in localise["statuses"]
    assert slam["statuses"]["initialised"] == 1
