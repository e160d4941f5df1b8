"""RecentScores: when a passing match's score is far enough below the recent ones to recheck."""

from __future__ import annotations

import math
import statistics

import pytest
from hypothesis import given
from hypothesis import strategies as st
from scanflow.frontend.recheck import MIN_SCORES, WINDOW, RecentScores

scores = st.floats(0.0, 1.0, allow_nan=False)


def test_no_score_is_low_before_min_count_scores_are_known() -> None:
    recent = RecentScores(window=10, min_count=3)
    for s in (0.9, 0.95):
        recent.add(s)
        assert not recent.is_low(0.1, 0.8)
    recent.add(1.0)
    assert recent.median() == 0.95
    assert recent.is_low(0.75, 0.8) and not recent.is_low(0.77, 0.8)


def test_ratio_zero_turns_rechecks_off_and_a_nan_score_is_low() -> None:
    recent = RecentScores()
    for _ in range(MIN_SCORES):
        recent.add(0.9)
    assert not recent.is_low(0.0, 0.0)
    assert recent.is_low(math.nan, 0.5)


def test_non_finite_scores_are_not_recorded_and_old_ones_leave_the_window() -> None:
    recent = RecentScores(window=3, min_count=1)
    assert math.isnan(recent.median()) and len(recent) == 0
    for s in (0.5, math.nan, math.inf, -math.inf):
        recent.add(s)
    assert len(recent) == 1 and recent.median() == 0.5
    for s in (0.1, 0.9, 0.9):
        recent.add(s)
    assert len(recent) == 3 and recent.median() == 0.9  # 0.5 has left the window


@pytest.mark.parametrize(("window", "min_count"), [(5, 0), (5, 6)])
def test_bad_sizes_are_named(window: int, min_count: int) -> None:
    with pytest.raises(ValueError, match="min_count <= window"):
        RecentScores(window, min_count)


@given(st.lists(scores, max_size=3 * WINDOW), scores, st.floats(0.01, 1.0))
def test_low_means_below_ratio_times_the_median_of_the_last_window(
    history: list[float], score: float, ratio: float
) -> None:
    recent = RecentScores()
    for s in history:
        recent.add(s)
    last = history[-WINDOW:]
    expected = len(last) >= MIN_SCORES and score < ratio * statistics.median(last)
    assert recent.is_low(score, ratio) is expected
