"""bench.slam: both passes on the simulator and on a log's first keyframes."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from bench.slam import main, run_log, run_sim

REPO = Path(__file__).resolve().parents[2]
DATA = Path(os.environ.get("SCANFLOW_DATA_DIR", REPO / ".." / "shared" / "data"))
INTEL = DATA / "intel-corrected.log.gz"


def test_sim_reports_both_passes_and_the_closures_help() -> None:
    report = run_sim("loop", 100.0, 0.03, 0.01)
    plain, closed = report["frontend"], report["loop_closure"]
    assert "closures" not in plain
    assert closed["closures"] > 0 and closed["disagreeing"] == 0
    assert closed["keyframes"] <= report["scans"]
    assert closed["ate_rmse_m"] < plain["ate_rmse_m"]
    # The drifted lap draws walls twice; the optimised one does not.
    assert closed["occupied_cells"] < plain["occupied_cells"]
    assert Path(closed["map_png"]).exists()


@pytest.mark.skipif(not INTEL.exists(), reason="the shared intel log is not beside the checkout")
def test_log_mode_scores_against_the_corrected_poses() -> None:
    report = run_log(INTEL, 60)
    assert report["scans"] == 60
    assert report["odometry"]["ate_rmse_m"] > report["frontend"]["ate_rmse_m"]
    assert 0 < report["loop_closure"]["keyframes"] <= 60
    assert report["loop_closure"]["ate_rmse_m"] < report["odometry"]["ate_rmse_m"]


def test_main_needs_a_source(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit):
        main([])
    assert "--data PATH or --sim" in capsys.readouterr().err
