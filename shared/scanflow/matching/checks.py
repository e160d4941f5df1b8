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
from typing import Protocol, runtime_checkable

import numpy as np
from numba import njit
from numpy.typing import ArrayLike, NDArray

from scanflow.geometry import Pose2D, angle_diff, normalize_angle
from scanflow.matching.api import MatchStatus
from scanflow.matching.correspondence import (
    GridIndex,
    TargetLines,
    grid_k_nearest,
    grid_nearest_all,
    grid_within_any,
    partner_reach_m,
    target_lines,
    thin_dense_target,
)
from scanflow.matching.surface import GAP_BASE_M, GAP_PER_RANGE

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
    points = np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 2)
    if used is None:
        used = np.ones(len(points), dtype=np.bool_)
    if len(used) != len(points):
        raise ValueError(f"used has {len(used)} flags for {len(points)} points")
    return float(_rms_spread(points, np.ascontiguousarray(used, dtype=np.bool_)))


@njit(cache=True)
def _rms_spread(points, used):  # type: ignore[no-untyped-def]
    # `characteristic_length_m` in one compiled pass (it runs on every match).
    if not np.any(used):
        used = np.ones(len(points), dtype=np.bool_)
    count = 0
    mx = 0.0
    my = 0.0
    for i in range(len(points)):
        if used[i]:
            count += 1
            mx += points[i, 0]
            my += points[i, 1]
    if count == 0:
        return 1.0
    mx /= count
    my /= count
    total = 0.0
    for i in range(len(points)):
        if used[i]:
            dx, dy = points[i, 0] - mx, points[i, 1] - my
            total += dx * dx + dy * dy
    return max(math.sqrt(total / count), 0.01)


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
    vals, weak = _scaled_eigen(np.ascontiguousarray(h), length_m)
    top = float(vals[-1])
    ratio = float(vals[0]) / top if top > 0.0 else 0.0
    return Conditioning(vals, (float(weak[0]), float(weak[1]), float(weak[2])), ratio)


@njit(cache=True)
def scaled_eigh(
    h: NDArray[np.float64], length_m: float
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """(eigenvalues, eigenvectors, scale) of the symmetric part of H with theta scaled by
    1 / `length_m` (scale: that diagonal), compiled for the kernels that analyse or solve
    with it."""
    scale = np.array([1.0, 1.0, 1.0 / length_m])
    hs = np.empty((3, 3))
    for a in range(3):
        for b in range(3):
            hs[a, b] = 0.5 * (h[a, b] + h[b, a]) * scale[a] * scale[b]
    vals, vecs = np.linalg.eigh(hs)
    return vals, vecs, scale


@njit(cache=True)
def _scaled_eigen(h, length_m):  # type: ignore[no-untyped-def]
    """Eigenvalues of H with theta scaled by 1 / `length_m`, and its weakest direction back in
    (x, y, theta), unit length, its largest component positive: one compiled call, as every
    match asks this two or three times."""
    vals, vecs, scale = scaled_eigh(h, length_m)
    weak = vecs[:, 0] * scale
    weak /= np.linalg.norm(weak)
    if weak[np.argmax(np.abs(weak))] < 0.0:
        weak = -weak
    return vals, weak


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


@runtime_checkable
class MapSurfaces(Protocol):
    """What `surface_conditioning` asks of a target: its surface points near some points, to
    fit the target's own surface lines through (a MatchingMap's cells' mean hit points, or a
    target scan's points: `ScanSurfaces`)."""

    def hit_means_near(self, points_world: ArrayLike, radius_m: float) -> NDArray[np.float64]:
        """(K, 2) surface points within `radius_m` of the points (some farther ones too)."""
        ...


# The smallest cell of `ScanSurfaces`' grid (a zero reach would ask for zero-width cells).
MIN_NEAR_CELL_M = 0.01


@dataclass(frozen=True, eq=False)
class ScanSurfaces:
    """A target given as points (a scan) as `MapSurfaces`: the target's own surfaces judge the
    source's isolated two-point lines (`surface_conditioning`). Unlike a map's, a scan's
    silence about a spot is no evidence (`surfaces_agree`' `unseen_agrees`)."""

    points: NDArray[np.float64]

    def hit_means_near(self, points_world: ArrayLike, radius_m: float) -> NDArray[np.float64]:
        """The target points within 2 x `radius_m` of any of the points: a patch of `radius_m`
        around the nearest one is then whole."""
        query = np.asarray(points_world, dtype=np.float64).reshape(-1, 2)
        if len(query) == 0 or len(self.points) == 0:
            return np.zeros((0, 2))
        # A bucket grid with cells as wide as the reach: each query visits at most 3 x 3 cells
        # (a dense target stays cheap, and no query-by-point table is ever held).
        reach_m = 2.0 * radius_m
        grid = GridIndex.build(self.points, max(reach_m, MIN_NEAR_CELL_M))
        return self.points[grid_within_any(grid.arrays, query, reach_m)]


def surfaces_of(target: object) -> MapSurfaces | None:
    """The surfaces of a match's target for `surface_conditioning`: a map's own, a point
    target's points (`ScanSurfaces`); None for anything else."""
    if isinstance(target, np.ndarray):  # first: a runtime protocol check costs ~10 us
        return ScanSurfaces(target)
    return target if isinstance(target, MapSurfaces) else None


# Neighbours of each matched point its normal is fitted to (see `surface_conditioning`).
NORMAL_NEIGHBOURS = 16
# Patches up to this far across (m) (see `surface_conditioning`).
NORMAL_RADIUS_M = 0.5
# A two-point line counts only when its partner's own patch, holding another point, runs
# within this angle of it (see `confirmed_patches`).
PARTNER_AGREEMENT_RAD = math.radians(30.0)


def angular_step_rad(points: NDArray[np.float64]) -> float:
    """The scan's angular increment: the median gap between the points' distinct bearings seen
    from the origin (0.0 for fewer than two)."""
    return float(_angular_step(np.ascontiguousarray(points, dtype=np.float64)))


@njit(cache=True)
def _angular_step(points):  # type: ignore[no-untyped-def]
    bearings = np.sort(np.arctan2(points[:, 1], points[:, 0]))
    gaps = np.diff(bearings)
    gaps = gaps[gaps > 1e-9]
    return np.median(gaps) if len(gaps) else 0.0


def unconfirmed_patches(
    grid: GridIndex, lines: TargetLines
) -> tuple[NDArray[np.bool_], NDArray[np.bool_]]:
    """Two masks over the `ok` lines: two-point lines whose partner's own patch holds another
    point yet runs more than PARTNER_AGREEMENT_RAD off them, and isolated pairs (two-point
    lines with no third point within either one's reach, `surface_gap_m`).

    Why: a two-point line runs between two beams. Where a lidar reports its bearings binned
    (RPLidar drivers: each sample in its 1-deg bin), two beams cast at nearly the same spot of
    a wall seen at a grazing angle come out one step apart across it, r x 1 deg (18 cm at
    10 m): a line facing the sensor, whose normal lies along the wall. One such pair outweighs
    a corridor's whole weak direction (its share there is ~1, against DEGENERATE_RATIO x the
    largest eigenvalue, ~0.6 for 360 beams); the simulated corridor's scans (360 beams, 0.3 deg
    bearing noise) held one to three. Next to a third point, its partner's wider patch gives
    it away. An isolated pair cannot be told from a small surface facing the sensor (aces has
    such pairs 20 m off through an opening: leaving them out flagged 7 more of its 439 next-scan
    plicp pairs, all within 5 cm), so only the target, a map or a scan, judges it
    (`surfaces_agree`)."""
    return _unconfirmed(grid.arrays, lines.normals, lines.neighbours, lines.ok, NORMAL_RADIUS_M,
                        GAP_BASE_M, GAP_PER_RANGE, math.cos(PARTNER_AGREEMENT_RAD))


@njit(cache=True)
def _unconfirmed(grid, normals, neighbours, ok, radius_m, gap_base_m, gap_per_range, agreement):  # type: ignore[no-untyped-def]
    points = grid[0]
    n = len(normals)
    reach = np.empty(n)
    sizes = np.zeros(n, dtype=np.int64)  # each patch's points (`neighbours` is -1 padded)
    for i in range(n):
        reach[i] = partner_reach_m(points[i, 0], points[i, 1], radius_m, gap_base_m,
                                   gap_per_range)
        while sizes[i] < neighbours.shape[1] and neighbours[i, sizes[i]] >= 0:
            sizes[i] += 1
    disagrees = np.zeros(n, dtype=np.bool_)
    isolated = np.zeros(n, dtype=np.bool_)
    best_d2 = np.empty(3)
    best_j = np.empty(3, dtype=np.int64)
    for i in range(n):
        if not ok[i] or sizes[i] != 2:
            continue
        j = neighbours[i, 1]
        if ok[j] and sizes[j] > 2:
            shared = abs(normals[i, 0] * normals[j, 0] + normals[i, 1] * normals[j, 1])
            disagrees[i] = shared < agreement
        alone = True
        for m in (i, j):
            if grid_k_nearest(grid, points[m, 0], points[m, 1], reach[m], best_d2, best_j) > 2:
                alone = False
        isolated[i] = alone
    return disagrees, isolated


# An isolated pair's flanking points (`flanked_pairs`): the nearest FLANK_CANDIDATES other
# points within FLANK_REACHES of its reach (`partner_reach_m`), and how far off their line it
# may lie: FLANK_NOISE_SIGMAS of its bearing noise (r x step / sqrt(12)), at least FLANK_MIN_M.
FLANK_CANDIDATES = 8
FLANK_REACHES = 3.0
FLANK_NOISE_SIGMAS = 2.0
FLANK_MIN_M = 0.03


def flanked_pairs(
    points: NDArray[np.float64], lines: TargetLines, isolated: NDArray[np.bool_],
    others: GridIndex, bearing_std_rad: float,
) -> NDArray[np.bool_]:
    """The isolated pairs (`unconfirmed_patches`) that lie on a wider surface of the same scan
    running across them: two of the nearest other points (`others`: every point of the scan,
    matched or not), one on either side, make a line that passes through the pair's midpoint
    within its bearing noise and runs more than PARTNER_AGREEMENT_RAD off the pair's line.

    Why: a beam cast off its reported angle (bearing noise, a binned driver) can land at the
    spot of a wall its neighbour hit, seen at a grazing angle from afar; the two come out a
    step apart across the beam, a pair facing the sensor whose normal lies along the wall, on
    the line through the wall's other, sparse points. On the simulated corridor (0.3 deg bearing
    noise) one such pair alone held the corridor's axis: gn ended 0.1-0.8 m along it, ok
    (BENCHMARKS.md, "Scan matching", thirty-fifth session). A small object facing the sensor
    (a tree trunk) sits in front of what is behind it, off that line."""
    return _flanked(points, lines.neighbours, isolated, others.arrays, bearing_std_rad,
                    FLANK_CANDIDATES, FLANK_REACHES, FLANK_NOISE_SIGMAS, FLANK_MIN_M,
                    math.cos(PARTNER_AGREEMENT_RAD))


@njit(cache=True)
def _flanked(  # type: ignore[no-untyped-def]
    points, neighbours, isolated, others, bearing_std_rad, candidates, reaches, sigmas, min_m,
    across,
):
    out = np.zeros(len(points), dtype=np.bool_)
    best_d2 = np.empty(candidates + 2)  # the pair's own two points are among the nearest
    best_j = np.empty(candidates + 2, dtype=np.int64)
    near = np.empty(candidates + 2, dtype=np.int64)
    flank = others[0]
    for i in range(len(points)):
        j = neighbours[i, 1]
        if not isolated[i] or j < 0 or out[i]:
            continue
        cx = 0.5 * (points[i, 0] + points[j, 0])
        cy = 0.5 * (points[i, 1] + points[j, 1])
        ux = points[j, 0] - points[i, 0]
        uy = points[j, 1] - points[i, 1]
        length = math.hypot(ux, uy)
        if length <= 0.0:
            continue
        ux /= length
        uy /= length
        r = math.hypot(cx, cy)
        reach = partner_reach_m(cx, cy, NORMAL_RADIUS_M, GAP_BASE_M, GAP_PER_RANGE)
        found = grid_k_nearest(others, cx, cy, reaches * reach, best_d2, best_j)
        count = 0
        for m in range(found):  # not the pair's own points
            q = best_j[m]
            if ((flank[q, 0] == points[i, 0] and flank[q, 1] == points[i, 1])
                    or (flank[q, 0] == points[j, 0] and flank[q, 1] == points[j, 1])):
                continue
            if count < candidates:
                near[count] = q
                count += 1
        tol = max(min_m, sigmas * r * bearing_std_rad)
        if _line_across(flank, near[:count], cx, cy, ux, uy, tol, across):
            out[i] = True
            out[j] = True
    return out & isolated


@njit(cache=True)
def _line_across(flank, near, cx, cy, ux, uy, tol, across):  # type: ignore[no-untyped-def]
    # Whether two of the points flank[near] lie on either side of (cx, cy) on a line passing
    # within tol of it and running across the unit direction (ux, uy) (|cos| < across).
    for a in range(len(near)):
        ax, ay = flank[near[a], 0], flank[near[a], 1]
        for b in range(a + 1, len(near)):
            vx, vy = flank[near[b], 0] - ax, flank[near[b], 1] - ay
            span = math.hypot(vx, vy)
            if span <= 0.0:
                continue
            vx /= span
            vy /= span
            t = ((cx - ax) * vx + (cy - ay) * vy) / span
            off = abs((cx - ax) * vy - (cy - ay) * vx)
            if 0.0 < t < 1.0 and off <= tol and abs(vx * ux + vy * uy) < across:
                return True
    return False


def faces_the_origin(lines: TargetLines) -> NDArray[np.bool_]:
    """Lines whose normal lies within PARTNER_AGREEMENT_RAD of the beam to their centre: what
    two beams on a small object (a tree trunk) or a binned lidar's two beams at one spot make,
    where a wall seen aslant by two beams at different ranges does not."""
    reach = np.maximum(np.hypot(lines.centres[:, 0], lines.centres[:, 1]), 1e-9)
    along_beam = np.abs(np.sum(lines.normals * lines.centres, axis=1)) / reach
    return along_beam >= math.cos(PARTNER_AGREEMENT_RAD)


def surfaces_agree(
    surfaces: MapSurfaces,
    points: NDArray[np.float64],
    normals: NDArray[np.float64],
    unseen_agrees: bool = False,
) -> NDArray[np.bool_]:
    """Whether the target's surface at each of `points` (target frame) runs as `normals` say,
    within PARTNER_AGREEMENT_RAD: the line fitted through the target's surface points around
    the nearest one (a map's mean hit points, a scan's points), as a scan's patch is fitted.
    Where the target holds no line-like patch within NORMAL_RADIUS_M: `unseen_agrees`.

    With `unseen_agrees` (a scan target, its points seen from its origin) the target's own
    two-point lines are judged too: one its neighbours contradict (`unconfirmed_patches`), or
    an isolated one facing its origin (`faces_the_origin`), is no evidence either way. On the
    simulated campus two beams on a far tree trunk made such lines in both scans, 30-40 deg
    apart (two chords of one trunk), and flagged 6-7 more good pairs of 239 for plicp and
    csm+plicp; an isolated pair along a wall seen aslant (the binned corridor's) still counts,
    as two beams at one spot cannot make it."""
    agrees = np.full(len(points), unseen_agrees, dtype=np.bool_)
    means = surfaces.hit_means_near(points, NORMAL_RADIUS_M) if len(points) else points
    if len(means) < 2:
        return agrees
    grid = GridIndex.build(means)
    nearest = grid_nearest_all(grid.arrays, points, np.full(len(points), NORMAL_RADIUS_M))
    found = nearest >= 0
    at = nearest[found]
    wanted = np.zeros(len(means), dtype=np.bool_)
    wanted[at] = True  # the lines asked about (and their partners), not every mean's
    lines = target_lines(grid, k=NORMAL_NEIGHBOURS, radius_m=NORMAL_RADIUS_M,
                         fit_radius_m=NORMAL_RADIUS_M, wanted=wanted)
    evidence = lines.ok
    if unseen_agrees:
        disagrees, isolated = unconfirmed_patches(grid, lines)
        evidence = evidence & ~disagrees & ~(isolated & faces_the_origin(lines))
    shared = np.abs(np.sum(lines.normals[at] * normals[found], axis=1))
    agrees[found] = np.where(evidence[at], shared >= math.cos(PARTNER_AGREEMENT_RAD),
                             unseen_agrees)
    return agrees


@njit(cache=True)
def _tilt_std(points, normals, centres, neighbours, ok, bearing_std_rad):  # type: ignore[no-untyped-def]
    std = np.zeros(len(points))
    ranges = np.empty(len(points))  # once per point, not once per patch it is in (16)
    for j in range(len(points)):
        ranges[j] = max(math.hypot(points[j, 0], points[j, 1]), 1e-9)
    for i in range(len(points)):
        if not ok[i]:
            continue
        nx, ny = normals[i, 0], normals[i, 1]
        extent = 0.0
        spread = 0.0
        for j in neighbours[i]:
            if j < 0:
                break
            px, py = points[j, 0], points[j, 1]
            along = (px - centres[i, 0]) * ny - (py - centres[i, 1]) * nx
            r = ranges[j]
            facing = (px * nx + py * ny) / r  # cos(beam, normal)
            variance = (r * bearing_std_rad) ** 2 * (1.0 - facing * facing)
            extent += along * along
            spread += along * along * variance
        std[i] = math.sqrt(spread) / extent if extent > 0.0 else math.inf
    return std


def normal_tilt_std(
    points: NDArray[np.float64], lines: TargetLines, bearing_std_rad: float
) -> NDArray[np.float64]:
    """Standard deviation (rad) of each patch's fitted normal from its points' bearing noise:
    r x `bearing_std_rad` across each beam, projected across the line (a wall seen at a grazing
    angle takes all of it, one facing the sensor none), propagated through the total-least-
    squares fit (var = sum s_j^2 sigma_j^2 / (sum s_j^2)^2, s_j a point's offset along the
    line); inf for a patch with no extent, 0 where not `ok`. Range noise is left out: the
    patches' 0.5 m already average it (`surface_conditioning`), and with it (1 cm) the floor
    flagged a good next-scan pair of intel (1 of 909), whose near wall's 16-point patches
    lean within it."""
    return _tilt_std(points, lines.normals, lines.centres, lines.neighbours, lines.ok,
                     bearing_std_rad)


def information_above_noise(
    points: NDArray[np.float64],
    normals: NDArray[np.float64],
    tilt_std: NDArray[np.float64],
    direction: NDArray[np.float64],
    length_m: float,
) -> float:
    """The points' information along `direction` (a unit vector in the metric of
    `analyse_hessian`, theta scaled by `length_m`), each point's share |J . d| shrunk by what
    a tilt of its normal by one `tilt_std` moves it (soft threshold): what is left is held by
    normals whose lean towards `direction` is above their noise."""
    return _information_above_noise(points, normals, tilt_std, direction, 1.0 / length_m)


@njit(cache=True)
def _information_above_noise(points, normals, tilt_std, direction, inv_length):  # type: ignore[no-untyped-def]
    total = 0.0
    for i in range(len(points)):
        nx, ny = normals[i, 0], normals[i, 1]
        px, py = points[i, 0], points[i, 1]
        share = abs(nx * direction[0] + ny * direction[1]
                    + (px * ny - py * nx) * inv_length * direction[2])
        lean = abs(ny * direction[0] - nx * direction[1]
                   + (-px * nx - py * ny) * inv_length * direction[2])
        left = share - tilt_std[i] * lean
        if left > 0.0:
            total += left * left
    return total


def surface_conditioning(
    source: NDArray[np.float64],
    matched: NDArray[np.bool_],
    pose: Pose2D,
    length_m: float | None = None,
    surfaces: MapSurfaces | None = None,
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
    optimum had slid 0.3-0.95 m along the corridor.

    Two guards against a lidar that reports its bearings binned (an RPLidar: each beam up to
    half a step off the angle the scan gives), where the corridor's ratio rose from 2e-4 to
    2e-3..6e-3 and gn slid 5-15 m along the simulated corridor (BENCHMARKS.md, "Front end"):
    - two-point lines that their neighbours contradict do not count (`unconfirmed_patches`),
      nor isolated ones on the line of a wider surface of the scan that runs across them
      (`flanked_pairs`), nor isolated ones that the target's surfaces (`surfaces`:
      `surfaces_of` the target) do not confirm: a map's must run along them, a scan's must
      not run across them (`surfaces_agree`); without `surfaces` the others count;
    - the weakest direction counts as constrained only by the information left once each
      normal's bearing noise is taken off (`information_above_noise`, `normal_tilt_std`): a
      bearing known to within the scan's angular step (std step / sqrt(12)). The scan cannot
      tell whether its bearings are binned, so this floor holds for every lidar; it only ever
      turns OK into DEGENERATE, along the direction the Hessian found weakest.
    Either alone left the front end sliding 2-6 m along that corridor; together 0.1-0.9 m over
    five seeds, while the real logs' next-scan pairs and tracking stayed as they were (one
    aces pair flagged more; BENCHMARKS.md, "Front end", 2026-11-28). Scan to scan on that
    corridor, the target scan's surfaces took csm+plicp's ok-yet-wrong pairs from 5.4 to
    0.8 % (BENCHMARKS.md, "Scan matching", thirty-second session)."""
    # A dense scan (3,000+ beams) is averaged per bearing bin first: its 16 nearest points lie
    # a few mm apart, where the range noise fails the flatness test (`thin_dense_target`).
    points = thin_dense_target(source[matched])
    hessian = np.zeros((3, 3))
    c, s = math.cos(pose.theta), math.sin(pose.theta)
    turn = np.array([[c, s], [-s, c]])  # row vectors times R^T: into the target frame
    lines, ok = None, np.zeros(len(points), dtype=np.bool_)
    bearing_std_rad = angular_step_rad(source) / math.sqrt(12.0)  # a bearing known to a step
    if len(points) >= 2:
        grid = GridIndex.build(points)
        lines = target_lines(grid, k=NORMAL_NEIGHBOURS, radius_m=NORMAL_RADIUS_M,
                             fit_radius_m=NORMAL_RADIUS_M, seen_from_origin=True)
        disagrees, isolated = unconfirmed_patches(grid, lines)
        if np.any(isolated):
            # Every point of the scan flanks, matched or not: a far wall's next beam may lie
            # beyond the target's view.
            others = grid if matched.all() else GridIndex.build(thin_dense_target(source))
            fake = flanked_pairs(points, lines, isolated, others, bearing_std_rad)
            disagrees, isolated = disagrees | fake, isolated & ~fake
        ok = lines.ok & ~disagrees
        if surfaces is not None and np.any(isolated):
            # A map has seen around its surfaces; one scan's view is sparse (a far tree trunk:
            # one beam on it), so only what it shows can contradict.
            ok[isolated] = surfaces_agree(
                surfaces, points[isolated] @ turn + [pose.x, pose.y],
                lines.normals[isolated] @ turn, unseen_agrees=isinstance(surfaces, ScanSurfaces),
            )
        moved, normals = points[ok] @ turn, lines.normals[ok] @ turn  # in the target frame
        hessian = line_hessian(moved, normals)
    # Rotation scaled by the spread of the points that carry the information (a glitch point
    # far off the target would otherwise make every rotation look unconstrained): the caller's
    # `length_m` when it judges in that metric too, so a weak direction keeps one metric.
    length_m = length_m or characteristic_length_m(points)
    cond = analyse_hessian(hessian, length_m)
    top = float(cond.eigenvalues[-1])
    weak = int(np.count_nonzero(cond.eigenvalues <= DEGENERATE_RATIO * top)) if top > 0 else 3
    ratio, above = cond.ratio, ""
    if weak == 0 and lines is not None:
        tilt = normal_tilt_std(points, lines, bearing_std_rad)
        direction = np.asarray(cond.weak_direction) * np.array([1.0, 1.0, length_m])
        ratio = information_above_noise(
            moved, normals, tilt[ok], direction / np.linalg.norm(direction), length_m
        ) / top
        weak, above = int(not ratio > DEGENERATE_RATIO), " above the normals' noise"
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
            f"ratio {ratio:.1e}{above}, e.g. a corridor): the surfaces under the matched points "
            "do not fix the pose along it",
        )
    return MatchStatus.OK, None, ""
