"""Conditioning of a 2D match: is the pose observable from these points, and if not, which way?

The Hessian mixes metres and radians, so the rotation axis is scaled by a characteristic length
(the RMS radius of the points) before the eigen-analysis; the weak direction is reported back in
(x, y, theta) as a unit 3-vector. Corridors show up as one tiny translational eigenvalue.
`surface_conditioning` asks it of the surfaces under the matched points themselves, apart from
any method's weights and fitted normals.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from scanflow.geometry import Pose2D, angle_diff, normalize_angle
from scanflow.matching.api import MatchStatus
from scanflow.matching.correspondence import GridIndex, target_lines, thin_dense_target

# Ratio of smallest to largest scaled eigenvalue below which a direction counts as unconstrained.
DEGENERATE_RATIO = 2e-3


@dataclass(frozen=True)
class Conditioning:
    """Eigen-analysis of a scaled 3x3 Hessian."""

    eigenvalues: NDArray[np.float64]
    weak_direction: tuple[float, float, float]
    ratio: float

    @property
    def degenerate(self) -> bool:
        """True when `ratio` is not above DEGENERATE_RATIO: some direction is unconstrained."""
        return not self.ratio > DEGENERATE_RATIO


def characteristic_length_m(
    points: NDArray[np.float64], used: NDArray[np.bool_] | None = None
) -> float:
    """RMS distance of the points (those `used`, when any are) from their centroid (>= 1 cm),
    the scale for rotations: the spread of the points that carry the information, as a far
    unmatched point (a doorway onto a long hall) would make every rotation look weak."""
    if used is not None and np.any(used):
        points = points[used]
    if len(points) == 0:
        return 1.0
    c = points - points.mean(axis=0)
    return max(float(np.sqrt(np.mean(np.sum(c * c, axis=1)))), 0.01)


def weak_length_m(extra: dict[str, object], source: NDArray[np.float64]) -> float:
    """The rotation scale a result's weak direction was found with (`extra["length_m"]`, set
    by the method that judged it), else the source's spread: undo or keep it in that metric."""
    length_m = extra.get("length_m")
    return float(length_m) if isinstance(length_m, float) else characteristic_length_m(source)


def analyse_hessian(hessian: NDArray[np.float64], length_m: float) -> Conditioning:
    """Eigenvalues and weakest direction of H with theta scaled by `length_m`."""
    h = np.asarray(hessian, dtype=np.float64)
    if h.shape != (3, 3) or not np.all(np.isfinite(h)):
        return Conditioning(np.zeros(3), (1.0, 0.0, 0.0), 0.0)
    scale = np.array([1.0, 1.0, 1.0 / length_m])
    hs = h * np.outer(scale, scale)
    vals, vecs = np.linalg.eigh(0.5 * (hs + hs.T))
    top = float(vals[-1])
    ratio = float(vals[0]) / top if top > 0.0 else 0.0
    weak = vecs[:, 0] * scale
    weak /= np.linalg.norm(weak)
    if weak[np.argmax(np.abs(weak))] < 0.0:
        weak = -weak
    return Conditioning(vals, (float(weak[0]), float(weak[1]), float(weak[2])), ratio)


def line_hessian(points: NDArray[np.float64], normals: NDArray[np.float64]) -> NDArray[np.float64]:
    """Point-to-line Hessian sum_i J_i^T J_i, J_i = [n_x, n_y, p x n] (unit residual weights)."""
    cross = points[:, 0] * normals[:, 1] - points[:, 1] * normals[:, 0]
    j = np.column_stack((normals, cross))
    return j.T @ j


def without_weak_direction(
    step: Pose2D, weak: tuple[float, float, float], length_m: float
) -> Pose2D:
    """`step` (x, y, theta) with its component along `weak` removed, in the metric of
    `analyse_hessian` (theta scaled by `length_m`), where `weak` was found."""
    scale = np.array([1.0, 1.0, length_m])
    d = step.to_array() * scale
    w = np.asarray(weak, dtype=np.float64) * scale
    w /= np.linalg.norm(w)
    return Pose2D.from_array((d - d.dot(w) * w) / scale)


def guess_along(
    weak: tuple[float, float, float], pose: Pose2D, guess: Pose2D, length_m: float
) -> Pose2D:
    """`pose` with its (x, y, theta) parameters moved to the guess's along `weak` and kept
    across it (`without_weak_direction` of the offset from the guess, headings the short way)."""
    offset = Pose2D(pose.x - guess.x, pose.y - guess.y, angle_diff(pose.theta, guess.theta))
    kept = without_weak_direction(offset, weak, length_m)
    return Pose2D(guess.x + kept.x, guess.y + kept.y, normalize_angle(guess.theta + kept.theta))


# Largest share of rotation (theta scaled by the points' spread) in a weak direction that
# `guess_position_along` still takes for a corridor's axis.
CORRIDOR_MAX_ROTATION_SHARE = 0.5


def guess_position_along(
    weak: tuple[float, float, float], pose: Pose2D, guess: Pose2D, length_m: float
) -> Pose2D | None:
    """`pose` moved to the guess's position along the translation axis of `weak`, its heading
    kept; None when `weak` is mostly a rotation (more than CORRIDOR_MAX_ROTATION_SHARE of it,
    theta scaled by `length_m`), where no corridor axis is defined.

    Unlike `guess_along`, the guess's heading never enters: a prediction several degrees off
    (odometry over a long step) has that error along any weak direction with a rotation in it,
    and `guess_along` turned it into tens of cm of position error (intel from every other
    keyframe: 0.3 m and 1.6 deg at one scan, 22 m by the end; BENCHMARKS.md, "Front end")."""
    scaled = np.array([weak[0], weak[1], weak[2] * length_m])
    if not abs(scaled[2]) < CORRIDOR_MAX_ROTATION_SHARE * float(np.linalg.norm(scaled)):
        return None
    axis = scaled[:2] / math.hypot(scaled[0], scaled[1])
    shift = float(axis @ np.array([guess.x - pose.x, guess.y - pose.y]))
    return Pose2D(pose.x + shift * axis[0], pose.y + shift * axis[1], pose.theta)


# Neighbours of each matched point its normal is fitted to (see `surface_conditioning`).
NORMAL_NEIGHBOURS = 16


def surface_conditioning(
    source: NDArray[np.float64],
    matched: NDArray[np.bool_],
    pose: Pose2D,
    length_m: float | None = None,
) -> tuple[MatchStatus, tuple[float, float, float] | None, str]:
    """OK, DEGENERATE (with the weak direction) or ILL_CONDITIONED for a pose matched from the
    source points `matched` (csm's optimum, an ICP's pairs), from the geometry of those points.

    A point on a surface pins the pose only across that surface, not along it. So the points'
    information is the point-to-line Hessian sum J^T J, J = [n, p x n] (n: the normal of the
    line fitted through the point's neighbours in the source over patches up to 0.5 m, turned
    into the target frame), analysed as `analyse_hessian` does (DEGENERATE_RATIO, rotation
    scaled by the points' spread). Why patches this wide, and not the method's own Hessian:
    over a few cm (a near wall's dense points) or a far wall's two points, range noise tilts the
    normals enough to fake a constraint along a corridor (ratio 2.5e-3 with 1 cm noise at 6 m
    range; 2.8e-4 over 0.5 m), and an ICP's robust weights hide how few points hold a direction.
    For csm, why not the score distribution: Olson's covariance samples +-3 cells and steps, so
    a flat direction tops out at ~2 cells of std, and real corridor scans reach 1.8 (intel),
    no margin; a quadratic fit of the scores had negative curvature on most real scans (the
    peak is not quadratic over +-3 cells). Measured on the next-scan pairs of intel, aces and
    freiburg-079: csm had 6 of 6138 flagged, all intel corridor scans, 5 of them where its
    optimum had slid 0.3-0.95 m along the corridor."""
    # A dense scan (3,000+ beams) is averaged per bearing bin first: its 16 nearest points lie
    # a few mm apart, where the range noise fails the flatness test (`thin_dense_target`).
    points = thin_dense_target(source[matched])
    hessian = np.zeros((3, 3))
    if len(points) >= 2:
        lines = target_lines(GridIndex.build(points), k=NORMAL_NEIGHBOURS, radius_m=0.5,
                             fit_radius_m=0.5, seen_from_origin=True)
        c, s = math.cos(pose.theta), math.sin(pose.theta)
        turn = np.array([[c, s], [-s, c]])  # row vectors times R^T: into the target frame
        hessian = line_hessian(points[lines.ok] @ turn, lines.normals[lines.ok] @ turn)
    # Rotation scaled by the spread of the points that carry the information (a glitch point
    # far off the target would otherwise make every rotation look unconstrained): the caller's
    # `length_m` when it judges in that metric too, so a weak direction keeps one metric.
    cond = analyse_hessian(hessian, length_m or characteristic_length_m(points))
    top = float(cond.eigenvalues[-1])
    weak = int(np.count_nonzero(cond.eigenvalues <= DEGENERATE_RATIO * top)) if top > 0 else 3
    if weak >= 2:
        return (
            MatchStatus.ILL_CONDITIONED, None,
            f"the {len(points)} matched points constrain fewer than two directions "
            f"(too few line-like patches among them: e.g. all at one spot)",
        )
    if weak == 1:
        return (
            MatchStatus.DEGENERATE, cond.weak_direction,
            f"unconstrained along {np.round(cond.weak_direction, 3).tolist()} (eigenvalue "
            f"ratio {cond.ratio:.1e}, e.g. a corridor): the surfaces under the matched points "
            "do not fix the pose along it",
        )
    return MatchStatus.OK, None, ""
