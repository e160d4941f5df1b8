"""One entry point for every scan matcher: `match(source, target, initial_guess, method=...)`.

Pose convention: the result `pose` is T_target_source, the motion that maps source points
into the target's frame (the target scan's frame for scan-to-scan, the map frame for
scan-to-map). `initial_guess` follows the same convention. Points are taken as given; a
`LaserScan` gives its valid endpoints in the robot's frame (through its `mount`), so two
mounted scans give the robot's motion, and a scan against a robot's map the robot's pose.
A point target is one scan seen from its frame's origin (a `LaserScan` target: from its
sensor): its returns also say that the beams' paths up to them were free, and the local
methods refuse (POOR_FIT) a converged pose that puts too much of the source in that free space,
a wrong basin (matching/trust.py). For a point set that is not one scan, pass
`max_free_space_share=1.0` to skip that check.

Each method lives in its own module and registers itself with `register_method`; this module
validates inputs once so methods can assume clean (N, 2) finite arrays (a `paired` method, svd,
gets the rows as given and drops a pair when either of its points is not finite), and options
whose names, types and finiteness fit the method's keyword parameters (`check_options`, from
scanflow.matching.inputs); the ranges that need a method's meaning it checks itself, with
`require_positive` and its kin.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from enum import StrEnum
from typing import Any, Protocol

import numpy as np
from numpy.typing import ArrayLike, NDArray

from scanflow.geometry import IDENTITY, Pose2D
from scanflow.matching.inputs import MatchInputError, OptionSpec, check_named, function_options
from scanflow.scan import LaserScan


class MatchStatus(StrEnum):
    """Why a match ended. Only OK means the pose can be trusted."""

    OK = "ok"
    TOO_FEW_POINTS = "too_few_points"
    ILL_CONDITIONED = "ill_conditioned"
    DEGENERATE = "degenerate"
    STEP_LIMIT = "step_limit"
    MAX_ITERATIONS = "max_iterations"
    DIVERGED = "diverged"
    EMPTY_MAP = "empty_map"
    NO_OVERLAP = "no_overlap"
    # Converged, but the aligned source contradicts the target: too many of its points lie
    # where the target scan saw free space (a wrong basin). See matching/trust.py.
    POOR_FIT = "poor_fit"
    # A global search found distinct poses that explain the scan about equally well.
    AMBIGUOUS = "ambiguous"


@dataclass(frozen=True, eq=False)
class MatchResult:
    """What a matcher found and how much to trust it."""

    pose: Pose2D
    covariance: NDArray[np.float64]
    score: float
    iterations: int
    converged: bool
    status: MatchStatus
    method: str
    message: str = ""
    weak_direction: tuple[float, float, float] | None = None
    inliers: int = 0
    time_s: float = 0.0
    extra: dict[str, Any] = field(default_factory=dict)

    @property
    def ok(self) -> bool:
        """True when the status is OK, the only one whose pose can be trusted."""
        return self.status is MatchStatus.OK


class MapTarget(Protocol):
    """What scan-to-map methods need from a map: see scanflow.maps."""

    def likelihood_field(self, level: int = 0) -> Any:
        """The map's `LikelihoodField` (scanflow.maps.field) at pyramid level `level` (cells
        2**level times the finest), what scan-to-map methods match to."""
        ...


Target = NDArray[np.float64] | MapTarget
MethodFn = Callable[..., MatchResult]
_METHODS: dict[str, MethodFn] = {}
_FORWARDS: dict[str, tuple[Callable[..., Any], ...]] = {}  # method -> where its **options go
_PAIRED: set[str] = set()  # methods with known correspondences: source[i] <-> target[i]
# method -> (its function, its options), built on first use
_OPTIONS: dict[str, tuple[MethodFn, dict[str, OptionSpec] | None]] = {}
# Point-to-line ICP: the most accurate local method measured here and well under 1.5 ms
# per match (BENCHMARKS.md, "Scan matching").
DEFAULT_METHOD = "plicp"


def register_method(
    name: str, *, forwards_to: Sequence[Callable[..., Any]] = (), paired: bool = False
) -> Callable[[MethodFn], MethodFn]:
    """Decorator: make a matcher available to `match(..., method=name)`.

    Its options are its keyword parameters with defaults (`check_options`); a method that
    passes `**options` on names the functions it passes them to in `forwards_to`, whose
    keyword parameters are then its options too. `paired`: source[i] and target[i] correspond
    (svd), so `match` keeps non-finite rows in place for the method to drop pairs jointly."""

    def deco(fn: MethodFn) -> MethodFn:
        _METHODS[name] = fn
        _FORWARDS[name] = tuple(forwards_to)
        _OPTIONS.pop(name, None)  # a method registered again (a test's) is read afresh
        if paired:
            _PAIRED.add(name)
        else:
            _PAIRED.discard(name)
        return fn

    return deco


def available_methods() -> list[str]:
    """Names of every registered method, sorted (importing the method modules first)."""
    _load_methods()
    return sorted(_METHODS)


def _load_methods() -> None:
    # Importing the package registers every method module.
    import scanflow.matching  # noqa: F401


def method_options(method: str) -> dict[str, OptionSpec] | None:
    """The options `method` takes, by name; None when it takes any name (`**options` passed
    on to functions nobody declared)."""
    _load_methods()
    fn = _METHODS[method]
    cached = _OPTIONS.get(method)
    if cached is not None and cached[0] is fn:
        return cached[1]
    specs, open_ended = function_options(fn)
    forwards = _FORWARDS.get(method, ())
    if forwards:  # its **options are theirs
        open_ended = False
        for receiver in forwards:
            more, more_open = function_options(receiver)
            specs = {**more, **specs}  # the method's own parameter wins
            open_ended = open_ended or more_open
    known = None if open_ended else specs  # None: nothing says which names it takes
    _OPTIONS[method] = (fn, known)
    return known


def check_options(method: str, options: dict[str, Any]) -> dict[str, Any]:
    """`options` checked against `method`'s options (`scanflow.matching.inputs.check_named`)."""
    return check_named(method, method_options(method), options)




def as_points(
    data: LaserScan | ArrayLike, name: str, keep_rows: bool = False
) -> NDArray[np.float64]:
    """Validated (N, 2) float64 points; a LaserScan gives its valid endpoints in the robot's
    frame (its `mount` applied). Drops non-finite rows, unless `keep_rows` (rows that pair
    with another array's by index, where the pair is to be dropped jointly).
    Always C-contiguous and writable (read-only arrays, as decoded from the wire, are copied):
    numba compiles each array type apart, so one type here means no compile on a service's
    first real scan after its warm-up."""
    if isinstance(data, LaserScan):
        return data.robot_points()
    try:
        p = np.asarray(data, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise MatchInputError(f"{name} is not a numeric array: {exc}") from exc
    if p.size == 0:
        return np.zeros((0, 2))
    if p.ndim != 2 or p.shape[1] != 2:
        raise MatchInputError(f"{name} must have shape (N, 2), got {p.shape}")
    finite = np.all(np.isfinite(p), axis=1)
    return np.require(p if keep_rows or finite.all() else p[finite], np.float64, ["C", "W"])


def as_pose(guess: Pose2D | ArrayLike | None) -> Pose2D:
    """The guess as a Pose2D (None: identity); MatchInputError unless 3 finite numbers."""
    if guess is None:
        return Pose2D()
    if isinstance(guess, Pose2D):
        return guess
    try:
        v = np.asarray(guess, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError) as exc:
        msg = f"initial_guess must be 3 numbers (x, y, theta), got {guess!r}"
        raise MatchInputError(msg) from exc
    if v.shape != (3,) or not np.all(np.isfinite(v)):
        raise MatchInputError(f"initial_guess must be 3 finite values (x, y, theta), got {v}")
    return Pose2D(*v)


def failed(
    method: str, status: MatchStatus, guess: Pose2D, message: str, iterations: int = 0
) -> MatchResult:
    """A result that carries no information: the guess, infinite covariance, the reason."""
    return MatchResult(
        pose=guess,
        covariance=np.diag([math.inf, math.inf, math.inf]),
        score=0.0,
        iterations=iterations,
        converged=False,
        status=status,
        method=method,
        message=message,
    )


def target_points(target: Any) -> NDArray[np.float64]:
    """The target as (M, 2) points: the array itself, or a map's `occupied_points()`."""
    if isinstance(target, np.ndarray):
        return target
    occupied = getattr(target, "occupied_points", None)
    if occupied is None:
        raise MatchInputError(
            f"target {type(target).__name__} is neither points nor a map with occupied_points()"
        )
    points = as_points(occupied(), "target.occupied_points()")
    return points if len(points) else np.zeros((0, 2))


def check_point_inputs(
    method: str,
    source: NDArray[np.float64],
    target: NDArray[np.float64],
    guess: Pose2D,
    min_points: int,
) -> MatchResult | None:
    """A failed result when either point set is too small to match (an empty map included)."""
    if len(target) == 0:
        return failed(method, MatchStatus.EMPTY_MAP, guess, "the target has no points")
    if len(source) < min_points or len(target) < min_points:
        return failed(
            method, MatchStatus.TOO_FEW_POINTS, guess,
            f"need >= {min_points} source and target points, got {len(source)} and {len(target)}",
        )
    return None


def match(
    source: LaserScan | ArrayLike,
    target: LaserScan | Target,
    initial_guess: Pose2D | ArrayLike | None = None,
    method: str = DEFAULT_METHOD,
    **options: Any,
) -> MatchResult:
    """Align `source` to `target` starting from `initial_guess`; see the module docstring."""
    _load_methods()
    fn = _METHODS.get(method)
    if fn is None:
        known = ", ".join(sorted(_METHODS))
        raise MatchInputError(f"unknown method {method!r}; available: {known}")
    options = check_options(method, options)
    guess = as_pose(initial_guess)
    paired = method in _PAIRED
    src = as_points(source, "source", keep_rows=paired)
    tgt: Any = target
    sensor = IDENTITY  # the frame the method runs in, in the target's: T_target_sensor
    if isinstance(target, LaserScan):
        # In the target scan's sensor frame, where its free space is seen from the origin.
        sensor, tgt = target.mount, target.points()
        guess = guess if sensor == IDENTITY else sensor.inverse() * guess
    elif not hasattr(target, "likelihood_field"):
        tgt = as_points(target, "target", keep_rows=paired)
    t0 = time.perf_counter()
    result = fn(src, tgt, guess, **options)
    result = result if sensor == IDENTITY else in_frame(sensor, result)
    return replace(result, time_s=time.perf_counter() - t0)


def in_frame(frame: Pose2D, result: MatchResult) -> MatchResult:
    """`result` (a pose in some frame b) re-expressed in frame a, `frame` being T_a_b: the pose
    left-multiplied, its covariance and weak direction rotated with it (J = diag(R, 1))."""
    jacobian = frame.frame_jacobian()
    weak = result.weak_direction
    if weak is not None:
        rotated = jacobian @ np.asarray(weak)
        weak = (float(rotated[0]), float(rotated[1]), float(rotated[2]))
    return replace(
        result,
        pose=frame * result.pose,
        covariance=jacobian @ result.covariance @ jacobian.T,
        weak_direction=weak,
    )
