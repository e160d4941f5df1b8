"""When a match that passed every check still deserves a second look: it scored far below the
recent ones.

A local matcher started from a bad prediction can settle in a wrong basin that passes every
check of `acceptance`. On aces, run from its keyframe 13, `gn` ends a fast turn 17 deg wrong,
yet within the correction limits. Only its score gives it away: 0.43, where the recent matches
scored 0.95 (median). Such a match is searched again over the fallback window (see
`Frontend`), and the searched pose is taken only when it scores clearly higher. A low score
alone is no proof: a scan entering new ground scores low too, and the search then finds the
same pose. The score is compared with the robot's own recent matches, not with a fixed limit,
because what a good score is depends on the sensor and the place.
"""

from __future__ import annotations

import math
import statistics
from collections import deque

WINDOW = 20  # accepted matches whose scores make "recent"
MIN_SCORES = 5  # fewer than this: no recheck yet (the first scans after the start)


class RecentScores:
    """The scores of the last `window` accepted matches, and whether a new one is far below."""

    def __init__(self, window: int = WINDOW, min_count: int = MIN_SCORES) -> None:
        if not 1 <= min_count <= window:
            raise ValueError(f"need 1 <= min_count <= window, got {min_count} and {window}")
        self._scores: deque[float] = deque(maxlen=window)
        self._min_count = min_count

    def __len__(self) -> int:
        return len(self._scores)

    def add(self, score: float) -> None:
        """Record an accepted match's score (a non-finite one is not a score: ignored)."""
        if math.isfinite(score):
            self._scores.append(float(score))

    def median(self) -> float:
        """The median recent score (NaN before any)."""
        return statistics.median(self._scores) if self._scores else math.nan

    def is_low(self, score: float, ratio: float) -> bool:
        """True when `score` is below `ratio` x the recent median (or NaN) and enough scores
        are known; never for `ratio` <= 0 (rechecks off)."""
        if ratio <= 0.0 or len(self._scores) < self._min_count:
            return False
        return not score >= ratio * self.median()
