"""Gauss-Newton scan-to-map matching on a smooth likelihood field (Hector SLAM; seed 2, part 1).

Each iteration solves H dx = -g for the field cost (see field_cost), restricted to the
directions H constrains, and stops on a step small in BOTH translation and |rotation|. A step
larger than the limits ends the match with STEP_LIMIT (the linearisation cannot be trusted that
far), a cost rising well above its level start with DIVERGED. On the finest level J takes the
field's slope across the surface each source point lies on (field_cost's docstring): the
sampled field's ripple along walls no longer pulls the pose along them.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from scanflow.geometry import Pose2D
from scanflow.maps.field import LikelihoodField
from scanflow.matching.api import MatchResult, MatchStatus, register_method
from scanflow.matching.field_cost import (
    MAX_LEVELS,
    LevelOutcome,
    converged_step,
    level_tolerances,
    linearise,
    matched_length_m,
    out_of_iterations,
    run_coarse_to_fine,
    solve_well_determined,
)
from scanflow.matching.inputs import (
    require_in,
    require_iterations,
    require_non_negative,
    require_positive,
)
from scanflow.matching.trust import fit_checked


@register_method("gn")
@fit_checked
def match_gn(
    source: NDArray[np.float64],
    target: object,
    guess: Pose2D,
    *,
    levels: int = 3,
    resolution_m: float = 0.05,
    sigma_m: float = 0.1,
    max_iterations: int = 30,
    translation_tol_m: float = 1e-3,
    rotation_tol_rad: float = 1e-3,
    max_step_m: float = 0.5,
    max_step_rad: float = 0.35,
) -> MatchResult:
    """Hector-style Gauss-Newton, coarse to fine over `levels` fields (cell size x2 per level)."""
    require_in(1, MAX_LEVELS, levels=levels)
    require_positive(
        resolution_m=resolution_m, sigma_m=sigma_m, max_step_m=max_step_m, max_step_rad=max_step_rad
    )
    require_iterations(max_iterations)
    require_non_negative(translation_tol_m=translation_tol_m, rotation_tol_rad=rotation_tol_rad)

    def solve_level(
        field: LikelihoodField,
        points: NDArray[np.float64],
        normals: NDArray[np.float64],
        pose: NDArray[np.float64],
        finest: bool,
    ) -> LevelOutcome:
        t_tol, r_tol = level_tolerances(finest, translation_tol_m, rotation_tol_rad)
        length_m = matched_length_m(field, points, pose)  # far points off the field: none
        lin = linearise(field, points, pose, normals)
        for it in range(1, max_iterations + 1):
            step = solve_well_determined(lin.hessian, -lin.gradient, length_m)
            if step is None and it > 1:
                # Landed where the bilinear field is flat around the points: a stationary point.
                return LevelOutcome(pose, it, None)
            if step is None:
                return LevelOutcome(
                    pose, it, MatchStatus.ILL_CONDITIONED, "H constrains fewer than two directions"
                )
            if math.hypot(step[0], step[1]) > max_step_m or abs(step[2]) > max_step_rad:
                return LevelOutcome(
                    pose,
                    it,
                    MatchStatus.STEP_LIMIT,
                    f"step {np.round(step, 4).tolist()} exceeds the limits "
                    f"({max_step_m} m, {max_step_rad} rad)",
                )
            # Linearised at the trial pose: an accepted step needs no second pass.
            trial = linearise(field, points, pose + step, normals)
            # Bilinear fields have kinks at the cell centres: halve a step that overshoots one.
            while trial.cost > lin.cost and not converged_step(step, t_tol, r_tol):
                step = 0.5 * step
                trial = linearise(field, points, pose + step, normals)
            if trial.cost <= lin.cost:
                pose, lin = pose + step, trial
            if converged_step(step, t_tol, r_tol):
                return LevelOutcome(pose, it, None)
        return out_of_iterations(pose, max_iterations, finest)

    return run_coarse_to_fine(
        "gn", source, target, guess, solve_level, levels, resolution_m, sigma_m,
        across_surfaces=True,
    )
