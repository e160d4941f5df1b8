"""Method "csm+plicp": correlative search for the basin, point-to-line ICP for the fine pose.

Local matchers fail once the initial error leaves their basin (tens of cm, a few degrees);
branch-and-bound correlative search (`csm`) finds the global optimum of the window on a
likelihood grid at grid resolution, and `plicp` then refines it to sub-centimetre precision.
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
from numpy.typing import NDArray

from scanflow.geometry import Pose2D
from scanflow.matching.api import MatchResult, register_method
from scanflow.matching.csm import match_csm
from scanflow.matching.plicp import match_plicp


@register_method("csm+plicp")
def match_csm_plicp(
    source: NDArray[np.float64],
    target: object,
    guess: Pose2D,
    *,
    linear_m: float = 0.5,
    angular_rad: float = math.radians(20.0),
    resolution_m: float = 0.05,
    **plicp_options: float,
) -> MatchResult:
    """Search +-linear_m / +-angular_rad around `guess` with csm, then refine with plicp."""
    coarse = match_csm(
        source, target, guess, linear_m=linear_m, angular_rad=angular_rad,
        resolution_m=resolution_m,
    )
    if not coarse.ok:
        return replace(coarse, method="csm+plicp")
    fine = match_plicp(source, target, coarse.pose, **plicp_options)
    return replace(
        fine,
        method="csm+plicp",
        iterations=fine.iterations + coarse.iterations,
        extra={**fine.extra, "csm_pose": coarse.pose, "csm_score": coarse.score},
    )
