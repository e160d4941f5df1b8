"""bench.pose_graph: both solvers minimise the same cost on the same graph."""

from __future__ import annotations

import numpy as np

from bench.pose_graph import build, cost, run, scipy_solve, square_laps


def test_the_baseline_reaches_the_same_optimum() -> None:
    graph, truth = build(2, 60, seed=3)
    start = cost(graph, graph.poses)
    theirs = cost(graph, scipy_solve(graph))
    ours = graph.optimise().final_cost
    assert ours < 0.1 * start
    assert abs(ours - theirs) <= 1e-3 * theirs
    assert np.allclose(square_laps(1, 4)[:, :2], [[0, 0], [20, 0], [20, 20], [0, 20]])
    assert truth.shape == (120, 3)


def test_run_reports_both_solvers() -> None:
    report = run(2, 40, 1)
    assert report["nodes"] == 80 and report["edges"] == 79 + 40
    for name in ("scanflow", "scipy_least_squares"):
        assert set(report[name]) == {"wall_s", "cost", "rms_error_m"}
