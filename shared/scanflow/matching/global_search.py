"""Global localisation: where on a whole map is the robot, with no initial guess at all.

Branch and bound (the `csm` search) over the map's entire extent and every heading, on a
coarse level of the map's likelihood pyramid (cells 2**level times the grid's: the bound prunes
a window of tens of metres in about a second), keeping the few best distinct optima; each is
refined with a local method on the full-resolution pyramid and the best refined score wins
(Cartographer's global localisation, with Olson's candidate list). Symmetric places (two
identical rooms) give two poses that explain the scan equally well: when a distinct runner-up
scores within `ambiguity_ratio` of the best, the result is AMBIGUOUS, never a silent guess.
A candidate whose refinement failed (the scan ill-conditioned there, say) has no refined score
to compare: when its search score is >= `ambiguity_ratio` x the winner's own search score,
the result is AMBIGUOUS too (a short-range lidar seeing two pillars' corners was otherwise
localised OK 180 deg off: its true pose refined ill_conditioned, leaving no rival).
Behind `match(source, a_map, method="global", **options)` too (the guess is not used), so a
match request can ask where a scan lies on a robot's map.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from scanflow.geometry import Pose2D
from scanflow.maps.matching_map import MatchingMap
from scanflow.maps.maxpool import SCORE_SCALE
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
    MAX_SEARCH_LENGTH_M,
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


@dataclass(frozen=True)
class _Optimum:
    """One distinct optimum of the coarse search: its pose, its score there (the share of the
    scan's points on the coarse field, 0..1) and its refinement."""

    coarse: Pose2D
    coarse_score: float
    refined: MatchResult


def _distinct(a: Pose2D, b: Pose2D, suppress_m: float, suppress_rad: float) -> bool:
    d = a.relative_to(b)
    return d.translation_norm() > suppress_m or abs(d.theta) > suppress_rad


def _refined_optima(
    optima: list[_Optimum], suppress_m: float, suppress_rad: float
) -> list[_Optimum]:
    """The optima that refined OK, one per refined pose, best refined score first."""
    good: list[_Optimum] = []
    for o in sorted((o for o in optima if o.refined.ok), key=lambda o: -o.refined.score):
        if all(_distinct(o.refined.pose, g.refined.pose, suppress_m, suppress_rad) for g in good):
            good.append(o)
    return good


def _rivalry(
    good: list[_Optimum], optima: list[_Optimum], ratio: float, suppress_m: float,
    suppress_rad: float,
) -> str:
    """Why the best refined optimum `good[0]` does not settle the pose, or "" when it does:
    a distinct refined optimum scores >= `ratio` x its refined score; or an optimum whose
    refinement failed (the scan ill-conditioned there, say), distinct from it both where the
    search put it and where the refinement stopped, scored >= `ratio` x its coarse score in the
    search. Nothing then tells the two places apart but the search's own score."""
    best = good[0]
    if len(good) > 1 and good[1].refined.score >= ratio * best.refined.score:
        first, second = best.refined, good[1].refined
        return (
            f"{first.pose} scores {first.score:.3f} and {second.pose} {second.score:.3f} "
            f"(>= {ratio} x the best)"
        )
    unrefined = [
        o for o in optima
        if not o.refined.ok and o.coarse_score >= ratio * best.coarse_score
        and all(
            _distinct(pose, best.refined.pose, suppress_m, suppress_rad)
            for pose in (o.coarse, o.refined.pose)
        )
    ]
    if not unrefined:
        return ""
    rival = max(unrefined, key=lambda o: o.coarse_score)
    return (
        f"{best.refined.pose} scored {best.coarse_score:.3f} in the search and {rival.coarse} "
        f"{rival.coarse_score:.3f} (>= {ratio} x the best's), which did not refine with "
        f"{rival.refined.method} ({rival.refined.status}: {rival.refined.message})"
    )


def _search(
    source: NDArray[np.float64], target: MatchingMap, refine: str, level: int, candidates: int,
    suppress_m: float, suppress_rad: float,
) -> list[_Optimum]:
    """Up to `candidates` distinct optima of the branch and bound over the whole map and every
    heading on pyramid level `level`, best first, each refined with `refine`."""
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
    optima: list[_Optimum] = []
    for k, ix, iy, score in found:
        pose = Pose2D(centre.x + ix * res, centre.y + iy * res, float(cand.angles_rad[k]))
        refined = match(source, target, pose, method=refine)
        optima.append(_Optimum(pose, score / (SCORE_SCALE * len(source)), refined))
    return optima


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
    refined candidate scores >= ambiguity_ratio x the best, or a distinct candidate that did not
    refine scored >= ambiguity_ratio x the best's search score (pose is the best, not to be
    trusted); otherwise the status says why (too few points, empty map, no candidate refined).
    extra["candidates"] / ["candidate_scores"]: the distinct refined optima, best first, with
    their refined scores; extra["coarse_candidates"] / ["coarse_scores"] / ["coarse_statuses"]:
    every optimum of the search, best first, with its search score (the share of the points on
    the coarse field) and the status its refinement ended with.
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
    # Beyond these the search's step counts overflowed deep inside (a fuzzing audit).
    require_at_most(MAX_SEARCH_LENGTH_M, suppress_m=suppress_m)
    require_at_most(2 * math.pi, suppress_rad=suppress_rad)
    t0 = time.perf_counter()
    source = as_points(points, "points")
    method = f"{GLOBAL_METHOD}+{refine}"
    if len(source) < 3:
        return failed(method, MatchStatus.TOO_FEW_POINTS, Pose2D(), f"{len(source)} points")
    if target.is_empty:
        return failed(method, MatchStatus.EMPTY_MAP, Pose2D(), "the map has nothing in it")
    optima = _search(source, target, refine, level, candidates, suppress_m, suppress_rad)
    good = _refined_optima(optima, suppress_m, suppress_rad)
    elapsed = time.perf_counter() - t0
    if not good:
        first = optima[0].refined
        return replace(
            first, method=method, time_s=elapsed,
            message=f"no candidate of the global search refined with {refine}: {first.message}",
        )
    best = good[0].refined
    extra = {
        "candidates": [o.refined.pose for o in good],
        "candidate_scores": [o.refined.score for o in good],
        "coarse_candidates": [o.coarse for o in optima],
        "coarse_scores": [o.coarse_score for o in optima],
        "coarse_statuses": [o.refined.status for o in optima],
    }
    result = replace(best, method=method, time_s=elapsed, extra={**best.extra, **extra})
    rivalry = _rivalry(good, optima, ambiguity_ratio, suppress_m, suppress_rad)
    if rivalry:
        return replace(
            result, status=MatchStatus.AMBIGUOUS, converged=False,
            message=f"ambiguous: {rivalry}",
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
