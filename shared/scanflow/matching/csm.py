"""Correlative scan matching (`csm`, `csm_exhaustive`): a search over an (x, y, theta) window
around the guess, against a point set or a map.

The search (candidates, branch and bound, Olson's covariance) is `csm_search`; this module
checks the options, sizes the window, turns the best candidates into poses and judges them
(overlap, conditioning along the scan's surfaces) before returning a MatchResult.
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
from numpy.typing import NDArray

from scanflow.geometry import Pose2D
from scanflow.maps.maxpool import SCORE_SCALE, MaxPoolStack
from scanflow.matching.api import MatchResult, MatchStatus, Target, failed, match, register_method
from scanflow.matching.checks import surface_conditioning, surfaces_of
from scanflow.matching.csm_search import (
    MAX_SEARCH_LENGTH_M,
    MAX_TOP_CANDIDATES,
    build_candidates,
    check_search_size,
    default_angular_step_rad,
    olson_covariance,
    reach_m,
    search_top,
    stack_depth,
    window_steps,
)
from scanflow.matching.field_cost import MIN_POINTS, check_inputs, points_field
from scanflow.matching.inputs import (
    MatchInputError,
    require_at_most,
    require_in,
    require_non_negative,
    require_positive,
)


def check_window_options(
    linear_m: float,
    angular_rad: float,
    resolution_m: float,
    angular_resolution_rad: float | None,
    sigma_m: float | None,
    candidates: int,
    suppress_m: float,
    suppress_rad: float,
    candidate_min_ratio: float,
) -> None:
    """MatchInputError naming the first option of `csm` that is non-finite or out of range."""
    require_positive(
        linear_m=linear_m, angular_rad=angular_rad, resolution_m=resolution_m,
        angular_resolution_rad=angular_resolution_rad, sigma_m=sigma_m,
    )
    require_non_negative(suppress_m=suppress_m, suppress_rad=suppress_rad)
    # Beyond these a search's cell and step counts overflowed deep inside (a fuzzing audit).
    require_at_most(MAX_SEARCH_LENGTH_M, resolution_m=resolution_m, sigma_m=sigma_m,
                    suppress_m=suppress_m)
    require_at_most(2 * math.pi, angular_resolution_rad=angular_resolution_rad,
                    suppress_rad=suppress_rad)
    require_in(0.0, 1.0, candidate_min_ratio=candidate_min_ratio)
    if not (isinstance(candidates, int | np.integer) and 1 <= candidates <= MAX_TOP_CANDIDATES):
        raise MatchInputError(
            f"candidates must be a count in 1..{MAX_TOP_CANDIDATES}, got {candidates!r}"
        )


# A pose however well its points constrain it; a search's may also lie on its window's edge.
CONDITIONED = frozenset({MatchStatus.OK, MatchStatus.DEGENERATE, MatchStatus.ILL_CONDITIONED})
SEARCHED = CONDITIONED | {MatchStatus.STEP_LIMIT}


def found_a_pose(result: MatchResult) -> bool:
    """Whether a search found a best pose, however well its points constrain it (OK, or the
    conditioning it reports), or where it lies (STEP_LIMIT: on its window's edge): a refinement
    may start there, and its own checks judge the end. One that found nothing (no overlap, too
    few points, an empty map) gives no start."""
    return result.status in SEARCHED


def window_edge(
    ix: int, iy: int, step: int, half_cells: int, half_steps: int, angular_rad: float
) -> str:
    """Why the best pose, at cell offset (ix, iy) and angle step `step`, lies on the search
    window's edge, where the optimum may lie beyond it ("" when inside; a window of no width
    in a dimension searches none there, and one of every heading has no angular edge): csm
    said ok 3 deg off at its last angle (a fuzzing audit)."""
    edges = []
    if half_cells > 0 and max(abs(ix), abs(iy)) >= half_cells:
        edges.append(f"cell offset ({ix}, {iy}) of +-{half_cells} (widen linear_m)")
    if 0 < half_steps <= abs(step) and angular_rad < math.pi:
        edges.append(f"angle step {step} of +-{half_steps} (widen angular_rad)")
    if not edges:
        return ""
    return f"best pose on the search window's edge: {', '.join(edges)}"


def correlative_match(
    method: str,
    source: NDArray[np.float64],
    target: Target,
    guess: Pose2D,
    exhaustive: bool,
    linear_m: float,
    angular_rad: float,
    resolution_m: float,
    angular_resolution_rad: float | None,
    sigma_m: float | None,
    refine: str | None,
    candidates: int = 1,
    suppress_m: float = 0.0,
    suppress_rad: float = 0.0,
    candidate_min_ratio: float = 0.0,
) -> MatchResult:
    """Shared body of `csm` and `csm_exhaustive`; extra["candidates"] lists the distinct optima."""
    check_window_options(
        linear_m, angular_rad, resolution_m, angular_resolution_rad, sigma_m, candidates,
        suppress_m, suppress_rad, candidate_min_ratio,
    )
    bad = check_inputs(method, source, target, guess)
    if bad is not None:
        return bad
    if hasattr(target, "likelihood_field"):
        field = target.likelihood_field(0)
    else:
        points = np.asarray(target)
        if len(points) < MIN_POINTS:
            return failed(
                method, MatchStatus.TOO_FEW_POINTS, guess,
                f"target has {len(points)} points, need >= {MIN_POINTS}",
            )
        field = points_field(points, resolution_m, sigma_m or resolution_m)
    res = field.spec.resolution_m
    step_rad = angular_resolution_rad or default_angular_step_rad(
        source, res, reach_m(field.spec, guess, linear_m)
    )
    half_cells, half_steps = window_steps(res, linear_m, angular_rad, step_rad)
    check_search_size(
        half_cells, half_steps, len(source), "linear_m",
        "angular_rad / angular_resolution_rad" if angular_resolution_rad else "angular_rad",
    )
    depth = stack_depth(half_cells)
    # A map keeps its stack current incrementally (the same levels as a rebuild from its field).
    stack = (
        target.maxpool_stack(depth)
        if hasattr(target, "maxpool_stack")
        else MaxPoolStack.from_values(field.spec, field.values, depth)
    )
    cand = build_candidates(source, stack, guess, linear_m, angular_rad, step_rad)
    found = search_top(
        cand, exhaustive, candidates, math.floor(suppress_m / res + 1e-9),
        math.floor(suppress_rad / step_rad + 1e-9), candidate_min_ratio,
    )
    k, ix, iy, score = found[0]
    if score <= 0:
        return failed(method, MatchStatus.NO_OVERLAP, guess, "no candidate puts a point on the map")
    poses = [Pose2D(guess.x + c[1] * res, guess.y + c[2] * res, float(cand.angles_rad[c[0]]))
             for c in found]
    matched = stack.lookup(0, cand.rows[k] + iy, cand.cols[k] + ix) > 0
    status, weak, message = surface_conditioning(
        source, matched, poses[0], surfaces=surfaces_of(target)
    )
    edge = window_edge(ix, iy, k - half_steps, half_cells, half_steps, angular_rad)
    if status is MatchStatus.OK and edge:  # (along a corridor's axis the edge is expected)
        status, message = MatchStatus.STEP_LIMIT, edge
    pose = poses[0]
    result = MatchResult(
        pose=pose,
        covariance=olson_covariance(cand, k, ix, iy, step_rad),
        score=score / (SCORE_SCALE * len(source)),
        iterations=1,
        converged=True,
        status=status,
        method=method,
        message=message,
        weak_direction=weak,
        inliers=int(np.count_nonzero(matched)),
        extra={
            "cell_offset": (ix, iy),
            "angle_step": k - cand.half_steps,
            "angular_step_rad": step_rad,
            "angles": len(cand.angles_rad),
            "candidates": poses,
            "candidate_scores": [c[3] / (SCORE_SCALE * len(source)) for c in found],
            "lattice_pose": Pose2D(guess.x + ix * res, guess.y + iy * res,
                                   float(cand.angles_rad[k])),
        },
    )
    if refine is None:
        return result
    fine = match(source, target, pose, method=refine, levels=1)
    return replace(
        fine,
        method=f"{method}+{refine}",
        extra={**fine.extra, "csm_pose": pose, "csm_score": result.score},
    )


@register_method("csm")
def match_csm(
    source: NDArray[np.float64],
    target: Target,
    guess: Pose2D,
    *,
    linear_m: float = 1.0,
    angular_rad: float = math.radians(30.0),
    resolution_m: float = 0.05,
    angular_resolution_rad: float | None = None,
    sigma_m: float | None = None,
    refine: str | None = None,
    exhaustive: bool = False,
    candidates: int = 1,
    suppress_m: float = 0.25,
    suppress_rad: float = math.radians(5.0),
    candidate_min_ratio: float = 0.0,
) -> MatchResult:
    """Branch-and-bound correlative search (exhaustive=True scores every candidate instead).

    extra["candidates"] lists up to `candidates` distinct optima, best first: each the best pose
    outside +-suppress_m (x and y) / +-suppress_rad boxes around the earlier ones, scoring at
    least candidate_min_ratio x the best.
    """
    name = "csm_exhaustive" if exhaustive else "csm"
    return correlative_match(
        name,
        source,
        target,
        guess,
        exhaustive,
        linear_m,
        angular_rad,
        resolution_m,
        angular_resolution_rad,
        sigma_m,
        refine,
        candidates,
        suppress_m,
        suppress_rad,
        candidate_min_ratio,
    )


@register_method("csm_exhaustive", forwards_to=[match_csm])
def match_csm_exhaustive(
    source: NDArray[np.float64], target: Target, guess: Pose2D, **options: object
) -> MatchResult:
    """The reference search: every candidate of the window scored."""
    return match_csm(source, target, guess, **{**options, "exhaustive": True})
