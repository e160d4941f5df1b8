"""Method "gn+plicp": Gauss-Newton on the map's field for the basin, point-to-line for the pose.

`gn` converges from far (coarse to fine over the field pyramid), but its optimum is only as
sharp as the field around the scan: where the map ends (a wall seen for the first time, the
far side of a turn), the field's tail pulls the scan's new points towards the known ends,
along the walls. On the simulator with perfect odometry that costs 0.21 deg (std) per match
against 0.03 deg on a complete map (bench.map_edge), and the front end drifts by it
(BENCHMARKS.md, "Front end"). Point-to-line residuals have no such pull: a point past a
wall's end pairs with the wall's line and is moved only across it. So from gn's pose, `plicp`
runs against the map's mean hit points around the scan (`MatchingMap.hit_means_near`, within
the gate), and its pose is kept only when it agrees with gn's (within agree_m / agree_rad):
gn stays the judge of the basin. Where plicp finds the scan degenerate (a corridor), its
correction is kept across the weak direction only; along it, gn's pose stands. Status, score
and covariance are gn's (the front end's acceptance limits are set on gn's); the fine step
moves the pose by at most agree_m / agree_rad. Measured in BENCHMARKS.md, "Front end": far
less drift on the simulator, intel and freiburg-079, but less robust than gn on the aces log.
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
from numpy.typing import NDArray

from scanflow.geometry import IDENTITY, Pose2D
from scanflow.matching.api import MatchResult, MatchStatus, register_method, target_points
from scanflow.matching.checks import weak_length_m, without_weak_direction
from scanflow.matching.correspondence import thin_dense_target
from scanflow.matching.gn import match_gn
from scanflow.matching.inputs import require_at_most, require_positive
from scanflow.matching.plicp import match_plicp

MAX_GATE_M = 5.0  # the fine step's reach from gn's pose (1 km: a MemoryError from its lookup)


def fine_target(target: object, moved: NDArray[np.float64], gate_m: float) -> NDArray[np.float64]:
    """The target points plicp refines on: a map's mean hits near the moved scan (within the
    gate; one per cell, never dense), else the points themselves, thinned where dense in their
    own frame (`thin_dense_target`; plicp would thin them as seen from gn's pose)."""
    near = getattr(target, "hit_means_near", None)
    return near(moved, gate_m) if near is not None else thin_dense_target(target_points(target))


@register_method("gn+plicp", forwards_to=[match_gn])
def match_gn_plicp(
    source: NDArray[np.float64],
    target: object,
    guess: Pose2D,
    *,
    gate_m: float = 0.2,
    min_gate_m: float = 0.05,
    agree_m: float = 0.1,
    agree_rad: float = math.radians(1.0),
    **gn_options: float,
) -> MatchResult:
    """gn from `guess`, then plicp from gn's pose on the target within `gate_m` (see the
    module docstring); `extra["fine_step"]` says whether the fine pose was kept and why not."""
    require_positive(gate_m=gate_m, min_gate_m=min_gate_m, agree_m=agree_m, agree_rad=agree_rad)
    require_at_most(gate_m, min_gate_m=min_gate_m)
    require_at_most(MAX_GATE_M, gate_m=gate_m)
    coarse = match_gn(source, target, guess, **gn_options)
    if not coarse.ok:
        return replace(coarse, method="gn+plicp")
    # In the frame of gn's pose: plicp's rotation then turns about the robot, not about the
    # map's origin (which can be tens of metres away, where a turn is mostly a translation).
    near = fine_target(target, coarse.pose.transform_points(source), gate_m)
    fine = match_plicp(
        source, coarse.pose.inverse().transform_points(near), IDENTITY,
        max_correspondence_m=gate_m, min_correspondence_m=min_gate_m,
        # gn's pose passed the free-space test already; these are not one scan from its origin.
        max_free_space_share=1.0, thin_below_deg=0.0,
    )
    step, verdict = fine.pose, "kept"
    if fine.status is MatchStatus.DEGENERATE and fine.weak_direction is not None:
        weak = fine.weak_direction
        step = without_weak_direction(step, weak, weak_length_m(fine.extra, source))
        verdict = f"kept across the weak direction {np.round(weak, 3).tolist()}"
    elif not fine.ok:
        step, verdict = IDENTITY, f"not kept: plicp {fine.status}: {fine.message}"
    if step.translation_norm() > agree_m or abs(step.theta) > agree_rad:
        verdict = (
            f"not kept: it moves gn's pose by {step.translation_norm():.3f} m, "
            f"{math.degrees(step.theta):.2f} deg (agree_m {agree_m}, agree_rad {agree_rad:.4f})"
        )
        step = IDENTITY
    return replace(
        coarse,
        pose=coarse.pose * step,
        method="gn+plicp",
        iterations=coarse.iterations + fine.iterations,
        extra={**coarse.extra, "gn_pose": coarse.pose, "fine_step": verdict},
    )
