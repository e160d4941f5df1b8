"""Global localisation: where on a whole map is the robot, with no initial guess at all.

Branch and bound (the `csm` search) over the map's entire extent and every heading, on a
coarse level of the map's likelihood pyramid (cells 2**level times the grid's: the bound prunes
a window of tens of metres in about a second), keeping the few best distinct optima; each is
refined with a local method on the full-resolution pyramid and the best refined score wins
(Cartographer's global localisation, with Olson's candidate list). Symmetric places (two
identical rooms) give two poses that explain the scan equally well: when a distinct runner-up
scores within `ambiguity_ratio` of the best, the result is AMBIGUOUS, never a silent guess.
Behind `match(source, a_map, method="global", **options)` too (the guess is not used), so a
match request can ask where a scan lies on a robot's map.
"""

from __future__ import annotations

import math
import time
from dataclasses import replace
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from scanflow.geometry import Pose2D
from scanflow.maps.matching_map import MatchingMap
from scanflow.matching.api import (
    MatchInputError,
    MatchResult,
    MatchStatus,
    as_points,
    failed,
    match,
    register_method,
)
from scanflow.matching.csm_search import (
    MAX_TOP_CANDIDATES,
    build_candidates,
    check_search_size,
    default_angular_step_rad,
    reach_m,
    search_top,
    stack_depth,
    window_steps,
)
from scanflow.matching.field_cost import MAX_LEVELS
from scanflow.matching.inputs import require_at_most, require_in, require_positive
from scanflow.scan import LaserScan

GLOBAL_METHOD = "global"


def _distinct(a: Pose2D, b: Pose2D, suppress_m: float, suppress_rad: float) -> bool:
    d = a.relative_to(b)
    return d.translation_norm() > suppress_m or abs(d.theta) > suppress_rad


def localise_globally(
    points: LaserScan | ArrayLike,
    target: MatchingMap,
    *,
    refine: str = "gn",
    level: int = 1,
    candidates: int = 3,
    suppress_m: float = 0.5,
    suppress_rad: float = math.radians(10.0),
    ambiguity_ratio: float = 0.97,
) -> MatchResult:
    """The pose of `points` (robot frame) on `target` searched over the whole map and all
    headings (see the module docstring). OK: the best refined candidate; AMBIGUOUS: a distinct
    candidate scores >= ambiguity_ratio x the best (pose is the best, not to be trusted);
    otherwise the status says why (too few points, empty map, no candidate refined).
    extra["candidates"] / ["candidate_scores"]: the distinct refined optima, best first.
    A search larger than the caps of `scanflow.matching.csm` (a map too large for `level`), or
    an option out of its range, raises MatchInputError naming it."""
    # A level past the pyramids gn and lm may ask for ran for minutes or failed deep inside.
    require_in(0, MAX_LEVELS - 1, level=level)
    require_in(1, MAX_TOP_CANDIDATES, candidates=candidates)
    require_positive(ambiguity_ratio=ambiguity_ratio)
    require_at_most(1.0, ambiguity_ratio=ambiguity_ratio)
    for name, value in (("suppress_m", suppress_m), ("suppress_rad", suppress_rad)):
        if not (math.isfinite(value) and value >= 0.0):
            raise MatchInputError(f"{name} must be finite and >= 0, got {value}")
    t0 = time.perf_counter()
    source = as_points(points, "points")
    method = f"{GLOBAL_METHOD}+{refine}"
    if len(source) < 3:
        return failed(method, MatchStatus.TOO_FEW_POINTS, Pose2D(), f"{len(source)} points")
    if target.is_empty:
        return failed(method, MatchStatus.EMPTY_MAP, Pose2D(), "the map has nothing in it")
    spec = target.likelihood_field(level).spec
    res = spec.resolution_m
    width_m, height_m = spec.cols * res, spec.rows * res
    centre = Pose2D(spec.origin_x_m + width_m / 2, spec.origin_y_m + height_m / 2, 0.0)
    half_m = max(width_m, height_m) / 2
    step_rad = default_angular_step_rad(source, res, reach_m(spec, centre, half_m))
    half_cells, half_steps = window_steps(res, half_m, math.pi, step_rad)
    check_search_size(
        half_cells, half_steps, len(source), f"the map's extent at level={level}",
        "every heading",
    )
    stack = target.maxpool_stack(stack_depth(half_cells), level)
    cand = build_candidates(source, stack, centre, half_m, math.pi, step_rad)
    found = search_top(
        cand, False, candidates, math.floor(suppress_m / res + 1e-9),
        math.floor(suppress_rad / step_rad + 1e-9),
    )
    coarse = [
        Pose2D(centre.x + ix * res, centre.y + iy * res, float(cand.angles_rad[k]))
        for k, ix, iy, _score in found
    ]
    refined = [match(source, target, pose, method=refine) for pose in coarse]
    good: list[MatchResult] = []  # distinct refined optima, best first
    for r in sorted((r for r in refined if r.ok), key=lambda r: -r.score):
        if all(_distinct(r.pose, g.pose, suppress_m, suppress_rad) for g in good):
            good.append(r)
    elapsed = time.perf_counter() - t0
    if not good:
        first = refined[0]
        return replace(
            first, method=method, time_s=elapsed,
            message=f"no candidate of the global search refined with {refine}: {first.message}",
        )
    best = good[0]
    extra = {
        "candidates": [r.pose for r in good],
        "candidate_scores": [r.score for r in good],
        "coarse_candidates": coarse,
    }
    result = replace(best, method=method, time_s=elapsed, extra={**best.extra, **extra})
    if len(good) > 1 and good[1].score >= ambiguity_ratio * best.score:
        rival = good[1]
        return replace(
            result, status=MatchStatus.AMBIGUOUS, converged=False,
            message=(
                f"ambiguous: {best.pose} scores {best.score:.3f} and {rival.pose} "
                f"{rival.score:.3f} (>= {ambiguity_ratio} x the best)"
            ),
        )
    return result


@register_method(GLOBAL_METHOD, forwards_to=[localise_globally])
def match_global(
    source: NDArray[np.float64], target: object, guess: Pose2D, **options: Any
) -> MatchResult:
    """`localise_globally` as a `match()` method; `guess` is not used: the whole map is."""
    if not isinstance(target, MatchingMap):
        raise MatchInputError(
            f"method {GLOBAL_METHOD!r} searches a map: the target must be a MatchingMap, "
            f"got {type(target).__name__}"
        )
    return localise_globally(source, target, **options)
