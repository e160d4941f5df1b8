"""A point target read as one scan seen from its origin: which neighbouring points lie on one
surface, and the surface between them.

Beams a fixed angle apart sample a surface ever more sparsely with range (1 deg steps: every
17 cm at 10 m, every 0.5 m at 30 m, every 1.4 m at 80 m), so a rule in metres tuned indoors
breaks a far wall into loose points outdoors. Two points belong to one surface when their gap
is at most GAP_BASE_M + GAP_PER_RANGE * range (about 3.5 deg of arc; wider gaps are occlusion
edges). Field costs densify along such surfaces; line fits reach that far for a neighbour.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from scanflow.matching.inputs import MatchInputError

GAP_BASE_M = 0.05
GAP_PER_RANGE = 0.06
# Points densify_scan may add: a 168 km surface at 1 cm (a step of 1e-12 m asked for 198 TiB).
MAX_DENSE_POINTS = 2**24


def surface_gap_m(range_m: NDArray[np.float64]) -> NDArray[np.float64]:
    """The widest gap (m) between two points at `range_m` from the origin that one surface
    bridges."""
    return GAP_BASE_M + GAP_PER_RANGE * np.asarray(range_m, dtype=np.float64)


def densify_scan(
    points: NDArray[np.float64], step_m: float, option: str = "step_m"
) -> NDArray[np.float64]:
    """Add points every `step_m` between consecutive points that lie on one surface.

    A scan's far points are sparser than a field's sigma, which would leave bumps along
    walls (a false constraint along corridors). Gaps up to `surface_gap_m` of the nearer
    point's range are filled; larger ones are occlusion edges and stay open. More than
    MAX_DENSE_POINTS to add is a MatchInputError naming `option` (the step's name).
    """
    if len(points) < 2:
        return points
    a, b = points[:-1], points[1:]
    gap = np.hypot(*(b - a).T)
    max_gap = surface_gap_m(np.minimum(np.hypot(*a.T), np.hypot(*b.T)))
    n = np.where(gap < max_gap, np.maximum(np.ceil(gap / step_m).astype(np.int64) - 1, 0), 0)
    if not n.any():
        return points
    if n.sum() > MAX_DENSE_POINTS:
        raise MatchInputError(
            f"target too large to fill along its surfaces every {option} {step_m:g} m: "
            f"{n.sum()} points (at most {MAX_DENSE_POINTS})"
        )
    seg = np.repeat(np.arange(len(n)), n)
    f = (np.arange(len(seg)) - np.repeat(np.cumsum(n) - n, n) + 1) / np.repeat(n + 1, n)
    return np.vstack((points, a[seg] + f[:, None] * (b[seg] - a[seg])))
