"""bench.csm: branch and bound equals exhaustive, the timed figures' arithmetic, csm accuracy."""

from __future__ import annotations

import json
import math
import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from scanflow.geometry import Pose2D
from scanflow.io.carmen import load_keyframes
from scanflow.matching import match

from bench import csm
from bench.csm import WINDOW, existing_log, run, search_times
from bench.data import corrected_log

LOG = corrected_log("intel")
needs_log = pytest.mark.skipif(not LOG.exists(), reason=f"real log {LOG} not available")


def spread_pairs(count: int) -> list[tuple[int, int]]:
    """The consecutive keyframe pairs the benchmark promises: `count` pairs spread over the log,
    every ((n - 1) // count)-th from the first."""
    n = len(load_keyframes(LOG))
    step = (n - 1) // count
    return [(k * step, k * step + 1) for k in range(count)]


def within(error: Pose2D, t_m: float, r_deg: float) -> bool:
    return error.translation_norm() <= t_m and abs(error.theta) <= math.radians(r_deg)


@needs_log
def test_branch_and_bound_equals_exhaustive_on_every_pair_and_csm_is_scored_on_the_truth() -> None:
    report = run(LOG, 3)
    assert report["log"] == LOG.name and report["pairs"] == 3
    assert report["bnb_equals_exhaustive"] == 3
    for key in ("search_bnb_ms_median", "search_exhaustive_ms_median", "match_bnb_ms_median",
                "match_exhaustive_ms_median", "search_speedup_median", "match_speedup_median"):
        assert math.isfinite(report[key]) and report[key] > 0, key
    for method in ("csm", "csm_gn"):
        tight, loose = report[f"{method}_success_5cm_0.5deg"], report[f"{method}_success_10cm_1deg"]
        assert 0.0 <= tight <= loose <= 1.0
    # The same figure from the corrected poses directly: truth = a^-1 b, error = truth^-1 estimate.
    frames = load_keyframes(LOG)
    ok = []
    for i, j in spread_pairs(3):
        a, b = frames[i], frames[j]
        guess = a.odom_pose.inverse() * b.odom_pose
        truth = a.true_pose.inverse() * b.true_pose
        for method, refine in (("csm", None), ("csm_gn", "gn")):
            pose = match(b.scan.robot_points(), a.scan.robot_points(), guess, method="csm",
                         refine=refine, **WINDOW).pose
            error = truth.inverse() * pose
            ok.append((method, within(error, 0.05, 0.5), within(error, 0.10, 1.0)))
    for method in ("csm", "csm_gn"):
        tight = np.mean([t for m, t, _ in ok if m == method])
        loose = np.mean([lo for m, _, lo in ok if m == method])
        assert report[f"{method}_success_5cm_0.5deg"] == pytest.approx(tight), method
        assert report[f"{method}_success_10cm_1deg"] == pytest.approx(loose), method


@needs_log
def test_success_rates_are_the_shares_of_pairs_within_each_tolerance_of_the_truth(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """A matcher that answers the truth times a chosen error per pair: csm off by 0.7, 0, 0.7 and
    1.5 deg (one pair within 5 cm / 0.5 deg, three within 10 cm / 1 deg); csm+gn by 7, 3, 12
    and 3 cm."""
    frames = load_keyframes(LOG)
    pairs = spread_pairs(4)
    truth_of = {frames[j].scan.robot_points().tobytes(): frames[i].true_pose.inverse()
                * frames[j].true_pose for i, j in pairs}
    order = [frames[j].scan.robot_points().tobytes() for _, j in pairs]
    csm_off = [Pose2D(0, 0, math.radians(d)) for d in (0.7, 0.0, 0.7, 1.5)]
    gn_off = [Pose2D(d, 0, 0) for d in (0.07, 0.03, 0.12, 0.03)]

    def answer(src, tgt, guess, method: str, refine: str | None = None, **window):  # type: ignore[no-untyped-def]
        key = src.tobytes() if isinstance(src, np.ndarray) else None
        if key not in truth_of:  # the warm-up call
            return match(src, tgt, guess, method=method, refine=refine, **window)
        k = order.index(key)
        error = gn_off[k] if refine == "gn" else csm_off[k]
        return SimpleNamespace(pose=truth_of[key] * error, score=1.0)

    monkeypatch.setattr(csm, "match", answer)
    report = run(LOG, 4)
    assert report["pairs"] == report["bnb_equals_exhaustive"] == 4
    assert (report["csm_success_5cm_0.5deg"], report["csm_success_10cm_1deg"]) == (0.25, 0.75)
    assert (report["csm_gn_success_5cm_0.5deg"], report["csm_gn_success_10cm_1deg"]) == (0.5, 0.75)


@needs_log
def test_a_search_that_differs_from_the_exhaustive_optimum_is_counted(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    real = csm.search

    def off_by_one(cand, exhaustive: bool):  # type: ignore[no-untyped-def]
        k, ix, iy, score = real(cand, exhaustive)
        return (k, ix + 1, iy, score) if exhaustive else (k, ix, iy, score)

    frames = load_keyframes(LOG)
    a, b = frames[0], frames[1]
    guess = b.odom_pose.relative_to(a.odom_pose)
    t_bnb, t_exh, same = search_times(b.scan.robot_points(), a.scan.robot_points(), guess)
    assert same and t_bnb > 0 and t_exh > 0
    monkeypatch.setattr(csm, "search", off_by_one)
    assert run(LOG, 2)["bnb_equals_exhaustive"] == 0


@needs_log
def test_times_are_milliseconds_of_each_step_and_speedups_are_exhaustive_over_bnb(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """A fake clock that only the steps timed move, by a fixed cost each: the medians and
    speedups come out as those costs exactly. Branch and bound's search pays for its max-pool
    stack, neither search for the likelihood field they share."""
    now = [0.0]
    search_cost = {False: 1e-3, True: 40e-3}  # exhaustive?
    match_cost = {"csm": 2e-3, "csm_exhaustive": 42e-3}
    real_search, real_match, real_field = csm.search, csm.match, csm.points_field
    real_stack = csm.MaxPoolStack.from_values

    def costed_field(*args, **kwargs):  # type: ignore[no-untyped-def]
        now[0] += 100e-3
        return real_field(*args, **kwargs)

    def costed_stack(*args, **kwargs):  # type: ignore[no-untyped-def]
        now[0] += 0.5e-3
        return real_stack(*args, **kwargs)

    def costed_search(cand, exhaustive: bool):  # type: ignore[no-untyped-def]
        now[0] += search_cost[exhaustive]
        return real_search(cand, exhaustive)

    def costed_match(*args, method: str, **kwargs):  # type: ignore[no-untyped-def]
        if kwargs.get("refine") is None:
            now[0] += match_cost[method]
        return real_match(*args, method=method, **kwargs)

    monkeypatch.setattr(csm, "clock", lambda: now[0])
    monkeypatch.setattr(csm, "search", costed_search)
    monkeypatch.setattr(csm, "match", costed_match)
    monkeypatch.setattr(csm, "points_field", costed_field)
    monkeypatch.setattr(csm, "MaxPoolStack", SimpleNamespace(from_values=costed_stack))
    report = run(LOG, 2)
    assert report["search_bnb_ms_median"] == pytest.approx(1.5)
    assert report["search_exhaustive_ms_median"] == pytest.approx(40.0)
    assert report["search_speedup_median"] == pytest.approx(40.0 / 1.5)
    assert report["match_bnb_ms_median"] == pytest.approx(2.0)
    assert report["match_exhaustive_ms_median"] == pytest.approx(42.0)
    assert report["match_speedup_median"] == pytest.approx(21.0)


@needs_log
def test_the_command_line_times_cpu_on_request_and_prints_json(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    monkeypatch.setattr(csm, "clock", csm.clock)  # main sets the module's clock: restored after
    monkeypatch.setattr(sys, "argv", ["bench.csm", "--data", str(LOG), "--pairs", "2", "--cpu",
                                      "--json"])
    csm.main()
    report = json.loads(capsys.readouterr().out)
    assert report["clock"] == "cpu" and report["pairs"] == report["bnb_equals_exhaustive"] == 2


def test_a_missing_log_is_named(tmp_path: Path) -> None:
    missing = tmp_path / "nowhere.log.gz"
    with pytest.raises(SystemExit, match=r"log not found: .*nowhere\.log\.gz"):
        existing_log(missing)
    assert existing_log(tmp_path) == tmp_path
