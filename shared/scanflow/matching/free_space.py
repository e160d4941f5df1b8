"""Free-space test of an alignment: source points where the target scan saw through.

A target given as points is a scan in its own sensor frame, so each of its returns also says
that the beam's path from the origin up to it was free. At a right pose the source's points lie
on or behind the target's surfaces, except on what moved between the scans; in a wrong basin
whole walls of the source land in space the target saw as free. Only bearings where the target
has returns on both sides (within BRACKET_STEPS beam steps) are tested: a gap (no return, an
occlusion edge) says nothing. A point conflicts when it is nearer than both bracketing returns
by more than the margin (the smaller of two neighbouring ranges, so a depth edge between two
beams is no conflict).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numba import njit
from numpy.typing import NDArray

# A tested bearing needs a target return at most this many beam steps away on each side.
BRACKET_STEPS = 1.5


@dataclass(frozen=True)
class FreeSpaceTest:
    """How many moved source points the target's returns bracket, and how many lie in front."""

    tested: int
    conflicts: int

    @property
    def share(self) -> float:
        """Conflicting share of the tested points (0 when none was tested)."""
        return self.conflicts / self.tested if self.tested else 0.0


def free_space_test(
    moved: NDArray[np.float64], target: NDArray[np.float64], margin_m: float
) -> FreeSpaceTest:
    """Count source points (already in the target frame) in the target scan's free space."""
    if not margin_m >= 0.0:
        raise ValueError(f"free-space margin_m must be >= 0, got {margin_m}")
    if len(target) < 2 or len(moved) == 0:
        return FreeSpaceTest(0, 0)
    bearings = np.arctan2(target[:, 1], target[:, 0])
    order = np.argsort(bearings)  # numpy's: which of two returns on one bearing comes first
    tested, conflicts = _free_space_counts(
        np.ascontiguousarray(moved, dtype=np.float64), bearings[order],
        np.hypot(target[order, 0], target[order, 1]), margin_m,
    )
    return FreeSpaceTest(int(tested), int(conflicts))


@njit(cache=True)
def _free_space_counts(moved, bearings, ranges, margin_m):  # type: ignore[no-untyped-def]
    """(tested, conflicting) source points against the target's returns sorted by bearing:
    `free_space_test` in one compiled pass."""
    reach = BRACKET_STEPS * np.median(np.diff(bearings))
    tested = conflicts = 0
    for i in range(len(moved)):
        at = math.atan2(moved[i, 1], moved[i, 0])
        hi = min(max(np.searchsorted(bearings, at), 1), len(bearings) - 1)
        lo = hi - 1
        if abs(bearings[lo] - at) <= reach and abs(bearings[hi] - at) <= reach:
            tested += 1
            if math.hypot(moved[i, 0], moved[i, 1]) < min(ranges[lo], ranges[hi]) - margin_m:
                conflicts += 1
    return tested, conflicts
