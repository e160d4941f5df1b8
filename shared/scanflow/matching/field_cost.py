"""The Hector cost sum_i (1 - M(T p_i))^2 on a likelihood field, shared by `gn` and `lm`.

Residual r_i = 1 - M(S_i(pose)), S_i the source point moved by the pose; its Jacobian is
-grad M(S_i) * dS_i/dpose with dS/dpose = [[1, 0, -s x - c y], [0, 1, c x - s y]] (seed 2,
part 1). The pose is updated additively in (x, y, theta). Both methods run coarse to fine over
a likelihood-field pyramid and end with the same checks, so that machinery lives here too.

The field's slope is trusted only across the surface a point lies on: where the source point's
neighbours in its own scan make a line, grad M is projected onto that line's normal before it
enters J. Along a straight wall the true field is flat; its sampled copy (cell means, bilinear
interpolation) ripples there, and hundreds of wall points summed that ripple into a pull along
the walls that moved the optimum and tilted the heading (BENCHMARKS.md, "Scan matching", the
thirty-sixth session). Points with no line (corners, clutter) keep the whole gradient, and so
do the coarse levels: far from the optimum a blurred field's slope along a wall still points
the way (projected there too, gn started 1 m / 30 deg off found the truth on 9 % of simulated
pairs instead of 54 %). So does a finest level whose H, so taken, would leave a direction
barely constrained (a corridor's axis: its normals' noise then sent steps past the limit, and
the front end on a corridor seen by a lidar with binned bearings from 0.06 to 0.38 m ATE).
`gn` takes the slope so on its finest level; `lm` keeps the whole gradient, since its gain
ratio weighs the model's predicted decrease against the true cost's, and a projected model
under-predicts it wherever the ripple slopes.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numba import njit
from numpy.typing import NDArray

from scanflow.geometry import Pose2D
from scanflow.maps.field import LikelihoodField, field_from_means
from scanflow.maps.grid import GridSpec
from scanflow.matching.api import MatchResult, MatchStatus, failed
from scanflow.matching.checks import (
    DEGENERATE_RATIO,
    MapSurfaces,
    analyse_hessian,
    characteristic_length_m,
    guess_along,
    guess_position_along,
    scaled_eigh,
    surface_conditioning,
    surfaces_of,
)
from scanflow.matching.correspondence import surface_normals
from scanflow.matching.covariance import least_squares_covariance
from scanflow.matching.inputs import require_grid_cells
from scanflow.matching.surface import densify_scan

MIN_POINTS = 10
# Coarse-to-fine levels, cell size x2 per level: 16 levels make a 5 cm cell 1.6 km.
MAX_LEVELS = 16
# The coarse levels may lead into a worse basin: a final fine-level cost this many times the
# initial one means the match ran away from the guess.
DIVERGENCE_RATIO = 1.5
# Point fields end where exp(-d^2 / 2 sigma^2) ~ 3e-4, as maps' fields do.
CUTOFF_SIGMAS = 4.0
COARSE_TOLERANCE_FACTOR = 10.0
# A point counts as matched within 2 sigma of the field's surface (value exp(-2)): a far wall's
# points 4 sigma off still slope the field, but do not pin the pose (`assess_field_match`).
MATCHED_VALUE = math.exp(-0.5 * 2.0**2)
# The finest level takes the field's slope across the surfaces only where H so taken keeps
# every direction this far above degenerate (`finest_normals`).
PINNED_RATIO = 10.0 * DEGENERATE_RATIO


@dataclass(frozen=True)
class FieldLinearisation:
    """Cost, Gauss-Newton Hessian J^T J and gradient J^T r of the field cost at one pose (J with
    each point's field slope taken across its surface: module docstring)."""

    cost: float
    hessian: NDArray[np.float64]
    gradient: NDArray[np.float64]
    hits: int


@dataclass(frozen=True)
class LevelOutcome:
    """Where one pyramid level's iterations ended and, if they failed, why."""

    pose: NDArray[np.float64]
    iterations: int
    status: MatchStatus | None
    message: str = ""


def out_of_iterations(pose: NDArray[np.float64], max_iterations: int, finest: bool) -> LevelOutcome:
    """A level that used all its iterations: a failure on the finest level, fine on a coarse
    one (the next level goes on from its pose)."""
    if finest:
        return LevelOutcome(
            pose, max_iterations, MatchStatus.MAX_ITERATIONS,
            f"no convergence in {max_iterations} iterations",
        )
    return LevelOutcome(pose, max_iterations, None)


LevelSolver = Callable[  # (field, source points, their normals, pose, whether finest)
    [LikelihoodField, NDArray[np.float64], NDArray[np.float64], NDArray[np.float64], bool],
    LevelOutcome,
]


def moved_points(points: NDArray[np.float64], pose: NDArray[np.float64]) -> NDArray[np.float64]:
    """Source points moved by the (x, y, theta) pose vector."""
    c, s = math.cos(pose[2]), math.sin(pose[2])
    out = np.empty_like(points)
    out[:, 0] = c * points[:, 0] - s * points[:, 1] + pose[0]
    out[:, 1] = s * points[:, 0] + c * points[:, 1] + pose[1]
    return out


def matched_mask(
    field: LikelihoodField, points: NDArray[np.float64], pose: NDArray[np.float64]
) -> NDArray[np.bool_]:
    """Which points, moved by `pose`, lie on the field (value at least MATCHED_VALUE)."""
    sampled = np.zeros(len(points))
    _run_kernel(field, points, pose, False, sampled=sampled)
    return sampled >= MATCHED_VALUE


def matched_length_m(
    field: LikelihoodField, points: NDArray[np.float64], pose: NDArray[np.float64]
) -> float:
    """The scale for rotations: the spread of the points on the field at `pose` (all of them
    when none is). Far points off it carry nothing: one return 3 km away made every rotation
    look unconstrained over all the points, so gn and lm never turned, and said ok."""
    return characteristic_length_m(points, matched_mask(field, points, pose))


@njit(cache=True)
def _accumulate(values, origin, resolution_m, points, normals, pose, with_jacobian, sampled):  # type: ignore[no-untyped-def]
    """One pass over the points: cost, hits and (optionally) J^T J and J^T r; each point's
    field value into `sampled` (when it has a place for each).

    Bilinear value and gradient as in LikelihoodField.sample (points whose interpolation square
    leaves the grid have value 0 and no gradient), without per-call numpy temporaries: at a few
    hundred points numpy's dispatch overhead, not arithmetic, dominated the cost. In J the
    gradient is projected onto the point's normal (source frame, turned by the pose); a zero
    normal keeps it whole.
    """
    rows, cols = values.shape
    c, s = math.cos(pose[2]), math.sin(pose[2])
    inv_res = 1.0 / resolution_m
    keep = sampled.shape[0] == points.shape[0]
    cost, hits = 0.0, 0
    hessian = np.zeros((3, 3))
    gradient = np.zeros(3)
    for i in range(points.shape[0]):
        px, py = points[i, 0], points[i, 1]
        fc = (c * px - s * py + pose[0] - origin[0]) * inv_res - 0.5
        fr = (s * px + c * py + pose[1] - origin[1]) * inv_res - 0.5
        r0, c0 = math.floor(fr), math.floor(fc)
        value = gx = gy = 0.0
        if 0 <= r0 < rows - 1 and 0 <= c0 < cols - 1:
            fr -= r0
            fc -= c0
            v00, v01 = values[r0, c0], values[r0, c0 + 1]
            v10, v11 = values[r0 + 1, c0], values[r0 + 1, c0 + 1]
            value = (1 - fr) * ((1 - fc) * v00 + fc * v01) + fr * ((1 - fc) * v10 + fc * v11)
            gx = ((1 - fr) * (v01 - v00) + fr * (v11 - v10)) * inv_res
            gy = ((1 - fc) * (v10 - v00) + fc * (v11 - v01)) * inv_res
        if keep:
            sampled[i] = value
        r = 1.0 - value
        cost += r * r
        if value != 0.0:
            hits += 1
        if with_jacobian:
            nx = c * normals[i, 0] - s * normals[i, 1]
            ny = s * normals[i, 0] + c * normals[i, 1]
            if nx != 0.0 or ny != 0.0:
                across = gx * nx + gy * ny
                gx, gy = across * nx, across * ny
            j = (-gx, -gy, -(gx * (-s * px - c * py) + gy * (c * px - s * py)))
            for a in range(3):
                gradient[a] += j[a] * r
                for b in range(3):
                    hessian[a, b] += j[a] * j[b]
    return cost, hits, hessian, gradient


_NOWHERE = np.zeros(0)  # `_accumulate`'s `sampled` when the values are not wanted


def _run_kernel(
    field: LikelihoodField,
    points: NDArray[np.float64],
    pose: NDArray[np.float64],
    with_jacobian: bool,
    normals: NDArray[np.float64] | None = None,
    sampled: NDArray[np.float64] | None = None,
) -> tuple[float, int, NDArray[np.float64], NDArray[np.float64]]:
    spec = field.spec
    if spec.rows < 2 or spec.cols < 2:  # no interpolation square fits: nothing is inside
        return float(len(points)), 0, np.zeros((3, 3)), np.zeros(3)  # (`sampled` stays 0)
    return _accumulate(
        field.values,
        np.array([spec.origin_x_m, spec.origin_y_m]),
        spec.resolution_m,
        points,
        np.zeros_like(points) if normals is None else normals,
        np.asarray(pose, dtype=np.float64),
        with_jacobian,
        _NOWHERE if sampled is None else sampled,
    )


def field_cost(
    field: LikelihoodField, points: NDArray[np.float64], pose: NDArray[np.float64]
) -> float:
    """sum_i (1 - M(T p_i))^2: what gn and lm minimise."""
    return float(_run_kernel(field, points, pose, False)[0])


def field_hits(
    field: LikelihoodField, points: NDArray[np.float64], pose: NDArray[np.float64]
) -> int:
    """How many moved points land where the field is non-zero."""
    return int(_run_kernel(field, points, pose, False)[1])


def linearise(
    field: LikelihoodField,
    points: NDArray[np.float64],
    pose: NDArray[np.float64],
    normals: NDArray[np.float64] | None = None,
) -> FieldLinearisation:
    """Cost, H = J^T J and g = J^T r at `pose` (step: H dx = -g); with `normals` (one per point,
    zero where it has none; `surface_normals`) the field's slope is taken across each surface."""
    if normals is not None and normals.shape != points.shape:
        raise ValueError(f"normals must have shape {points.shape}, got {normals.shape}")
    cost, hits, hessian, gradient = _run_kernel(field, points, pose, True, normals)
    return FieldLinearisation(float(cost), hessian, gradient, int(hits))


def field_pyramid(
    target: object, levels: int, resolution_m: float, sigma_m: float
) -> list[LikelihoodField]:
    """Likelihood fields from coarse to fine: a map's own pyramid, or one built from points.

    Level k of a point target has cell size and sigma scaled by 2**k, widening the basin of
    convergence at the coarse levels while the finest level keeps the accuracy.
    """
    if levels < 1:
        raise ValueError(f"levels must be >= 1, got {levels}")
    if hasattr(target, "likelihood_pyramid"):
        fields = list(target.likelihood_pyramid(levels))
    else:
        # Densified once at the finest step: dense enough for every coarser level too.
        dense = densify_scan(np.asarray(target, dtype=np.float64), resolution_m, "resolution_m")
        fields = [
            dense_points_field(dense, resolution_m * 2**k, sigma_m * 2**k) for k in range(levels)
        ]
    return sorted(fields, key=lambda f: -f.spec.resolution_m)


def points_field(
    points: NDArray[np.float64], resolution_m: float, sigma_m: float
) -> LikelihoodField:
    """Field exp(-d^2 / 2 sigma^2) with d measured to the nearest cell's mean point, not its centre.

    Snapping walls to cell centres biases the optimum by up to half a cell; keeping each
    cell's mean point makes the field's ridge follow the points to sub-cell accuracy.
    """
    return dense_points_field(
        densify_scan(points, resolution_m, "resolution_m"), resolution_m, sigma_m
    )


def dense_points_field(
    points: NDArray[np.float64], resolution_m: float, sigma_m: float
) -> LikelihoodField:
    """`points_field` of points already densified at `resolution_m` or finer.

    The field is cut off at CUTOFF_SIGMAS (as maps' fields are), so only a band around the
    points is computed, whatever their bounding box; a box over MAX_GRID_CELLS (a far glitch
    point, an option out of scale) is a MatchInputError before anything is allocated.
    """
    cutoff_m = CUTOFF_SIGMAS * sigma_m
    spec = GridSpec.covering(points, resolution_m, cutoff_m + 2.0 * resolution_m)
    require_grid_cells(
        spec.rows, spec.cols, f"a field of resolution_m {resolution_m:g}, sigma_m {sigma_m:g}"
    )
    cells = spec.world_to_cell(points)
    _, cell_of_point = np.unique(cells[:, 0] * spec.cols + cells[:, 1], return_inverse=True)
    count = np.bincount(cell_of_point)
    means = np.column_stack(
        (
            np.bincount(cell_of_point, points[:, 0]) / count,
            np.bincount(cell_of_point, points[:, 1]) / count,
        )
    )
    values = field_from_means(
        spec.shape, spec.world_to_continuous(means), resolution_m, sigma_m, cutoff_m
    )
    return LikelihoodField(spec, values, sigma_m)


def is_empty_target(target: object) -> bool:
    """True for a point set with no points or a map whose field holds nothing."""
    if hasattr(target, "likelihood_field"):
        return bool(target.likelihood_field(0).is_empty)
    return len(np.asarray(target)) == 0


def converged_step(
    step: NDArray[np.float64], translation_tol_m: float, rotation_tol_rad: float
) -> bool:
    """Both the translation and the |rotation| of a step are below their tolerances."""
    return math.hypot(step[0], step[1]) < translation_tol_m and abs(step[2]) < rotation_tol_rad


def level_tolerances(
    finest: bool, translation_tol_m: float, rotation_tol_rad: float
) -> tuple[float, float]:
    """Convergence tolerances of a pyramid level: coarse levels only have to land in the
    finer level's basin (sigma-wide), so they stop COARSE_TOLERANCE_FACTOR times earlier."""
    factor = 1.0 if finest else COARSE_TOLERANCE_FACTOR
    return factor * translation_tol_m, factor * rotation_tol_rad


@njit(cache=True)
def _solve_kernel(hessian, rhs, length_m, ratio):  # type: ignore[no-untyped-def]
    """(ok, step): see solve_well_determined (compiled: called once or twice per iteration)."""
    step = np.zeros(3)
    if not np.all(np.isfinite(hessian)):
        return False, step
    vals, vecs, scale = scaled_eigh(hessian, length_m)
    if vals[2] <= 0.0:
        return False, step
    kept = 0
    for k in range(3):
        if vals[k] > ratio * vals[2]:
            kept += 1
            coef = 0.0
            for a in range(3):
                coef += vecs[a, k] * scale[a] * rhs[a]
            for a in range(3):
                step[a] += vecs[a, k] * coef / vals[k]
    return kept >= 2, step * scale


def solve_well_determined(
    hessian: NDArray[np.float64], rhs: NDArray[np.float64], length_m: float
) -> NDArray[np.float64] | None:
    """H^-1 rhs restricted to the directions H constrains (eigenvalues scaled by the point spread).

    A corridor leaves one direction unconstrained: the step is zero along it instead of
    arbitrary. Returns None when fewer than two directions are constrained (ill-conditioned).
    """
    ok, step = _solve_kernel(
        np.asarray(hessian, dtype=np.float64),
        np.asarray(rhs, dtype=np.float64),
        float(length_m),
        DEGENERATE_RATIO,
    )
    return step if ok else None


def check_inputs(
    method: str, source: NDArray[np.float64], target: object, guess: Pose2D
) -> MatchResult | None:
    """TOO_FEW_POINTS or EMPTY_MAP result when there is nothing to match, else None."""
    if len(source) < MIN_POINTS:
        return failed(
            method,
            MatchStatus.TOO_FEW_POINTS,
            guess,
            f"source has {len(source)} points, need >= {MIN_POINTS}",
        )
    if is_empty_target(target):
        return failed(method, MatchStatus.EMPTY_MAP, guess, "target holds no points")
    return None


def finest_normals(
    field: LikelihoodField, source: NDArray[np.float64], pose: NDArray[np.float64]
) -> NDArray[np.float64]:
    """The source's `surface_normals` for the finest level when, with the slope taken across
    the surfaces, H at `pose` still pins every direction down (scaled eigenvalue ratio at least
    PINNED_RATIO); else zero normals, the whole gradient. Along a corridor the projected H
    leaves the axis barely constrained, and its noise sent steps past the limit (module
    docstring)."""
    normals = surface_normals(source)
    hessian = linearise(field, source, pose, normals).hessian
    pinned = analyse_hessian(hessian, matched_length_m(field, source, pose)).ratio >= PINNED_RATIO
    return normals if pinned else np.zeros_like(source)


def run_coarse_to_fine(
    method: str,
    source: NDArray[np.float64],
    target: object,
    guess: Pose2D,
    solve_level: LevelSolver,
    levels: int,
    resolution_m: float,
    sigma_m: float,
    across_surfaces: bool = False,
) -> MatchResult:
    """Validate, build the pyramid, run `solve_level` per level (coarse first), assess. With
    `across_surfaces` the finest level's solver and the assessment get `finest_normals` (the
    field's slope taken across each surface where that still pins the pose: module docstring);
    coarser levels, and every level without it, get zero normals (the whole gradient)."""
    bad = check_inputs(method, source, target, guess)
    if bad is not None:
        return bad
    pyramid = field_pyramid(target, levels, resolution_m, sigma_m)
    normals = np.zeros_like(source)  # the whole gradient, until the finest level
    pose = guess.to_array()
    start_cost = field_cost(pyramid[-1], source, pose)
    total = 0
    for index, field in enumerate(pyramid):
        if field_hits(field, source, pose) < MIN_POINTS:
            return failed(
                method,
                MatchStatus.NO_OVERLAP,
                guess,
                f"fewer than {MIN_POINTS} points fall on the field at level {index}",
                total,
            )
        finest = index == len(pyramid) - 1
        if finest and across_surfaces:
            normals = finest_normals(field, source, pose)
        outcome = solve_level(field, source, normals, pose, finest)
        total += outcome.iterations
        if outcome.status is not None:
            return failed(method, outcome.status, guess, outcome.message, total)
        pose = outcome.pose
    end_cost = field_cost(pyramid[-1], source, pose)
    if end_cost > DIVERGENCE_RATIO * start_cost:
        return failed(
            method,
            MatchStatus.DIVERGED,
            guess,
            f"fine-level cost rose from {start_cost:.3g} to {end_cost:.3g}",
            total,
        )
    scan = not hasattr(target, "likelihood_pyramid")
    return assess_field_match(
        method, pyramid[-1], source, pose, total, guess, scan, surfaces_of(target), normals
    )


def assess_field_match(
    method: str,
    field: LikelihoodField,
    source: NDArray[np.float64],
    pose: NDArray[np.float64],
    iterations: int,
    guess: Pose2D,
    scan_target: bool = False,
    surfaces: MapSurfaces | None = None,
    normals: NDArray[np.float64] | None = None,
) -> MatchResult:
    """Covariance sigma^2 H^-1 and the conditioning checks at the final pose on the finest field;
    a DEGENERATE pose keeps the guess's value along its weak direction (against a map, from the
    surfaces: its position along a corridor's axis only).

    The field's own Hessian is asked first, then the surfaces under the points within 2 sigma
    of the field (`surface_conditioning`, as icp, plicp and csm do): a field also slopes where
    its samples end or thin out, which fakes a constraint along a corridor. Against a scan
    (`scan_target`), gn said OK on 76 % of the simulated corridor's pairs, 45 % while 0.5 m off
    along it; the weak direction then takes the guess's value (`guess_along`). Against the
    front end's map, gn slid 7 m along that corridor over a run; there only a corridor's axis
    takes the guess's position, the heading stays the match's (`guess_position_along`): the
    front end's predictions can be degrees off in heading, which `guess_along` turned into
    position error (BENCHMARKS.md, "Front end"). `surfaces`: the target's (`surfaces_of`),
    which judge the source's isolated two-point lines (`surface_conditioning`). `normals`: the
    source's (`linearise`), so that H holds only what the surfaces carry.
    """
    # Rotation scaled by the spread of the points on the field: far ones off it carry nothing.
    matched = matched_mask(field, source, pose)
    length_m = characteristic_length_m(source, matched)
    lin = linearise(field, source, pose, normals)
    cond = analyse_hessian(lin.hessian, length_m)
    at = Pose2D.from_array(pose)
    kept: Pose2D | None = None
    weak: tuple[float, float, float] | None
    if cond.degenerate:
        status, weak = MatchStatus.DEGENERATE, cond.weak_direction
        message = f"one direction unconstrained (eigenvalue ratio {cond.ratio:.2e})"
        kept = guess_along(weak, at, guess, length_m)
    else:
        status, weak, message = surface_conditioning(source, matched, at, length_m, surfaces)
        if weak is not None:
            keep = guess_along if scan_target else guess_position_along
            kept = keep(weak, at, guess, length_m)
            if kept is None:  # not a corridor: the field's Hessian decides, as for a turn
                status, weak, message = MatchStatus.OK, None, ""
    if kept is not None:
        pose = kept.to_array()
        lin = linearise(field, source, pose, normals)
    return MatchResult(
        pose=Pose2D.from_array(pose),
        covariance=least_squares_covariance(lin.hessian, lin.cost, lin.hits),
        score=1.0 - lin.cost / len(source),
        iterations=iterations,
        converged=True,
        status=status,
        method=method,
        message=message,
        weak_direction=weak,
        inliers=lin.hits,
        extra={} if weak is None else {"length_m": length_m},  # weak's rotation scale
    )
