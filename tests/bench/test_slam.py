"""bench.slam: both passes on the simulator and on a log's first keyframes."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scanflow.frontend import default_settings

from bench.data import corrected_log
from bench.slam import main, run_log, run_log_starts, run_sim

INTEL = corrected_log("intel")


def test_sim_reports_both_passes_and_the_closures_help(monkeypatch: pytest.MonkeyPatch) -> None:
    """The ring with 5 % yaw noise in the odometry: the front end's heading drifts (0.11 m ATE),
    loop closure takes it back (0.05 m). With 1 % the front end's error lies along the
    corridors and cancels over the lap, leaving the revisit nothing to correct (BENCHMARKS.md,
    "Scan matching", the thirty-sixth session)."""
    monkeypatch.delenv("SCANFLOW_BACKEND_CULL_M", raising=False)
    report = run_sim("loop", 100.0, 0.03, 0.05)
    plain, closed = report["frontend"], report["loop_closure"]
    assert "closures" not in plain
    assert closed["closures"] > 0 and closed["disagreeing"] == 0
    assert closed["keyframes"] <= report["scans"]
    assert closed["culled"] == 0 and closed["cull_m"] == 0.0  # culling is opt-in
    assert closed["ate_rmse_m"] < plain["ate_rmse_m"]
    # As the services serve it (corrected at the redraw, no last optimisation) the path is
    # better than the front end's too.
    assert closed["served_ate_rmse_m"] < plain["ate_rmse_m"]
    # The drifted lap draws walls twice; the optimised one does not.
    assert closed["occupied_cells"] < plain["occupied_cells"]
    assert Path(closed["map_png"]).exists()


def test_the_front_end_s_method_reaches_both_passes(monkeypatch: pytest.MonkeyPatch) -> None:
    """--method: the ring with gn+plicp, whose front end alone drifts far less than gn's
    (BENCHMARKS.md "Front end"), so loop closure has less left to correct."""
    monkeypatch.delenv("SCANFLOW_BACKEND_CULL_M", raising=False)
    settings = default_settings()
    gn = run_sim("loop", 30.0, 0.03, 0.01, settings=settings)
    fine = run_sim("loop", 30.0, 0.03, 0.01,
                   settings=settings.model_copy(update={"method": "gn+plicp"}))
    assert gn["method"] == "gn" and fine["method"] == "gn+plicp"
    assert fine["frontend"]["ate_rmse_m"] < 0.5 * gn["frontend"]["ate_rmse_m"]


def test_sim_counts_the_culled_inserts(monkeypatch: pytest.MonkeyPatch) -> None:
    """SCANFLOW_BACKEND_CULL_M reaches the back end as in `scanflow run`: 0.3 m is past the
    0.2 m motion filter, so some inserts hang from earlier keyframes."""
    monkeypatch.setenv("SCANFLOW_BACKEND_CULL_M", "0.3")
    closed = run_sim("loop", 30.0, 0.03, 0.01)["loop_closure"]
    assert closed["cull_m"] == 0.3 and closed["culled"] > 0
    assert closed["keyframes"] + closed["culled"] <= 300


def test_sim_on_a_prior_map_closes_the_loop_in_its_frame(monkeypatch: pytest.MonkeyPatch) -> None:
    """The ring's first 30 s as a prior map, then 80 s from the same start on it: the front
    end alone comes back round drifted; with loop closure the keyframes close on those made
    on the prior map, and the errors in the prior map's frame shrink (0.16 -> 0.05 m mean,
    with 3 % yaw noise in the odometry)."""
    monkeypatch.delenv("SCANFLOW_BACKEND_CULL_M", raising=False)
    report = run_sim("loop", 80.0, 0.03, 0.03, prior_s=30.0)
    plain, closed = report["frontend"], report["loop_closure"]
    assert report["prior_s"] == 30.0 and closed["closures"] > 0
    assert plain["abs_mean_m"] > 0.1 and closed["abs_mean_m"] < 0.5 * plain["abs_mean_m"]
    assert closed["abs_max_m"] < 0.5 * plain["abs_max_m"]


@pytest.mark.skipif(not INTEL.exists(), reason="the shared intel log is not beside the checkout")
def test_log_mode_scores_against_the_corrected_poses() -> None:
    report = run_log(INTEL, 60)
    assert report["scans"] == 60
    assert report["odometry"]["ate_rmse_m"] > report["frontend"]["ate_rmse_m"]
    assert 0 < report["loop_closure"]["keyframes"] <= 60
    assert report["loop_closure"]["ate_rmse_m"] < report["odometry"]["ate_rmse_m"]



@pytest.mark.skipif(not INTEL.exists(), reason="the shared intel log is not beside the checkout")
def test_log_starts_run_both_passes_from_each_start() -> None:
    """Each start runs the log's rest: its own ATE per pass, and their median and largest."""
    report = run_log_starts(INTEL, 40, 2)
    for label in ("frontend", "loop_closure"):
        row = report[label]
        ates = row["ate_by_start_m"]
        assert len(ates) == 2 and len(set(ates)) == 2 and all(0.0 <= a < 1.0 for a in ates)
        assert row["median_ate_m"] == pytest.approx(np.median(ates))
        assert row["max_ate_m"] == max(ates)
    with pytest.raises(ValueError, match=r"starts must be in 1\.\.39"):
        run_log_starts(INTEL, 40, 40)
    with pytest.raises(ValueError, match="starts"):
        run_log_starts(INTEL, 40, -1)

def test_main_needs_a_source(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit):
        main([])
    assert "--data PATH or --sim" in capsys.readouterr().err
