"""Levenberg-Marquardt scan-to-map matching on the likelihood-field cost (seed 2, part 2).

Solves (H + mu D) h = -g with D = diag(H) (Marquardt's scaling: metres and radians damp alike
and mu is dimensionless, starting at tau) and updates mu by the gain ratio
rho = actual / predicted decrease (Nielsen's rule: mu *= max(1/3, 1 - (2 rho - 1)^3) on
success, mu *= nu, nu *= 2 on failure). Steps that raise the cost are rejected, so the cost
never increases.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from scanflow.geometry import Pose2D
from scanflow.maps.field import LikelihoodField
from scanflow.matching.api import MatchResult, MatchStatus, register_method
from scanflow.matching.field_cost import (
    MAX_LEVELS,
    LevelOutcome,
    converged_step,
    field_cost,
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

GN_LIKE_MU = 1e-2


@register_method("lm")
@fit_checked
def match_lm(
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
    tau: float = 1e-3,
) -> MatchResult:
    """Levenberg-Marquardt, coarse to fine over `levels` fields (cell size doubles per level)."""
    require_in(1, MAX_LEVELS, levels=levels)
    require_positive(resolution_m=resolution_m, sigma_m=sigma_m, tau=tau)
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
        if solve_well_determined(lin.hessian, lin.gradient, length_m) is None:
            return LevelOutcome(
                pose, 1, MatchStatus.ILL_CONDITIONED, "H constrains fewer than two directions"
            )
        damping = np.maximum(np.diag(lin.hessian), 1e-9 * np.max(np.diag(lin.hessian)))
        damping_matrix = np.diag(damping)  # fixed for the level: only mu changes
        mu, nu, rejected = tau, 2.0, False
        for it in range(1, max_iterations + 1):
            # Unconstrained directions (a corridor's axis) get no step, as in gn.
            step = solve_well_determined(
                lin.hessian + mu * damping_matrix, -lin.gradient, length_m
            )
            small = step is None or converged_step(step, t_tol, r_tol)
            # A small step ends the level when LM is close to Gauss-Newton or cannot improve;
            # under heavy damping it only means mu is still large.
            if small and (mu <= GN_LIKE_MU or rejected):
                return LevelOutcome(pose, it, None)
            if step is None:
                break
            # Costs are sum r^2 = 2F; the predicted decrease of 2F is h^T (mu D h - g).
            predicted = float(step @ (mu * damping * step - lin.gradient))
            actual = lin.cost - field_cost(field, points, pose + step)
            rho = actual / predicted if predicted > 0 else -1.0
            if rho > 0:
                pose = pose + step
                lin = linearise(field, points, pose, normals)
                mu *= max(1.0 / 3.0, 1.0 - (2.0 * rho - 1.0) ** 3)
                nu, rejected = 2.0, False
            else:
                mu *= nu
                nu, rejected = 2.0 * nu, True
        return out_of_iterations(pose, max_iterations, finest)

    return run_coarse_to_fine(
        "lm", source, target, guess, solve_level, levels, resolution_m, sigma_m
    )
