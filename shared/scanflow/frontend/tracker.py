"""Scan-to-map tracking for one robot: predict, match against the robot's own map, check, insert.

`Frontend(settings).process(points_m, stamp_s, odom_pose, seq, no_return_m, mount)
-> FrontendOutput`, once per deskewed scan, in stamp order. `points_m` are the scan's valid
endpoints in the robot's frame at `stamp_s` (a `DeskewResult.points`); `no_return_m` its
no-return beams' endpoints there (`DeskewResult.no_return_points`), which only clear free space
when the scan is inserted (up to the map's `no_return_clear_m`) and are never matched; `mount`
is where the sensor sits on the robot (rays start there; default the robot's origin);
`odom_pose` is the wheel-odometry pose at `stamp_s` in the odometry frame, or None. Output poses
are the robot's, T_map_base.

Per scan:
1. predict: the odometry increment since the last scan composed onto the last estimate
   (a jump beyond the limits is ignored), else constant velocity, else the last pose;
2. match the points against the map from the prediction with `settings.method`; if the checks of
   `acceptance` fail and a fallback is set, a correlative search (`settings.fallback_method`)
   over +-fallback_linear_m / +-fallback_angular_deg, widened to 3 std of the prediction's
   uncertainty up to fallback_max_linear_m / _angular_deg (its correction allowed as far),
   seeds the method again (and its own
   optimum is used, at grid resolution, if that refinement fails the checks too; a degenerate
   search's optimum at the prediction's position along the corridor, `corridor_start`). A match that
   passes but scores below `recheck_ratio` x the median of the recent ones, or is the first of
   a run carried on across a gap (`carry_on`: searched over the widest window), is searched the
   same way, and the searched match replaces it when it scores `recheck_margin` higher;
3. accepted: the pose is the match, the map gets the scan when the motion filter allows it;
   rejected (or too few points): the pose is the prediction with its covariance grown by the
   motion since the last accepted match, the map is untouched, the status and message say why.
The first usable scan initialises the map at `initial_pose`. Given a prior map (`grid`) and
no `initial_pose`, the first usable scan is instead searched for over the whole map and every
heading (`scanflow.matching.global_search`): LOCALISED when found, else rejected until a scan
is; with `settings.global_after_rejections` = n, the same whole-map search runs after every n
rejected scans in a row (a kidnapped or lost robot). `settings.update_map` = False localises
on the prior map without changing it. The front end never raises for a bad scan; it reports it
and carries on. Memory: the map plus 32 bytes of trajectory per scan.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, replace
from enum import StrEnum

import numpy as np
from numpy.typing import ArrayLike, NDArray

from scanflow.config import MAX_GLOBAL_LEVEL, FrontendSettings
from scanflow.frontend.acceptance import AcceptanceLimits, rejection_reason
from scanflow.frontend.motion_filter import MotionFilter
from scanflow.frontend.prediction import MotionPredictor, Prediction
from scanflow.frontend.recheck import RecentScores
from scanflow.frontend.trajectory import TrajectoryStore
from scanflow.geometry import IDENTITY, Pose2D
from scanflow.maps.matching_map import MatchingMap
from scanflow.maps.occupancy import InsertResult, OccupancyGrid, OccupancyParams
from scanflow.matching import MatchResult, MatchStatus, match
from scanflow.matching.api import MatchInputError, as_points, failed
from scanflow.matching.checks import guess_position_along, weak_length_m
from scanflow.matching.csm import found_a_pose
from scanflow.matching.global_search import localise_globally
from scanflow.scan import MAX_ODOM_M


class FrontendStatus(StrEnum):
    """What the front end did with a scan. The first four (ACCEPTED) mean the pose is the
    estimate; all but INITIALISED come from a match."""

    INITIALISED = "initialised"
    LOCALISED = "localised"  # found by the whole-map search
    TRACKED = "tracked"
    RECOVERED = "recovered"
    REJECTED = "rejected"
    TOO_FEW_POINTS = "too_few_points"


ACCEPTED = frozenset({
    FrontendStatus.INITIALISED, FrontendStatus.LOCALISED, FrontendStatus.TRACKED,
    FrontendStatus.RECOVERED,
})


@dataclass(frozen=True, eq=False)
class FrontendOutput:
    """The front end's estimate for one scan (pose = T_map_base at `stamp_s`)."""

    seq: int
    stamp_s: float
    pose: Pose2D
    covariance: NDArray[np.float64]
    status: FrontendStatus
    method: str
    iterations: int
    score: float
    message: str
    inserted: bool
    prediction_source: str
    match_time_s: float = 0.0
    insert_time_s: float = 0.0
    rechecked: bool = False  # a passing match searched again; `status` says if it was replaced

    @property
    def accepted(self) -> bool:
        """True when `status` is in ACCEPTED (initialised, localised, tracked or recovered)."""
        return self.status in ACCEPTED

    def in_frame(self, correction: Pose2D) -> FrontendOutput:
        """The same estimate in another map frame (T_new_old = `correction`: the map was
        redrawn): the pose moved, the covariance's position block turned with it."""
        covariance = _turned(self.covariance, correction)
        return replace(self, pose=correction * self.pose, covariance=covariance)


def _turned(covariance: NDArray[np.float64], correction: Pose2D) -> NDArray[np.float64]:
    """`covariance` in the frame `correction` (T_new_old) leads to: its position block turned
    with the frame; "no information" (inf) stays as it is."""
    if not np.all(np.isfinite(covariance)):
        return covariance
    turn = correction.frame_jacobian()
    return turn @ covariance @ turn.T


@dataclass
class _Step:
    """One scan on its way through `Frontend.process`."""

    prediction: Prediction
    points: NDArray[np.float64]
    no_return: NDArray[np.float64]
    stamp_s: float
    odom_pose: Pose2D | None
    seq: int
    mount: Pose2D
    match_time_s: float = 0.0
    rechecked: bool = False
    bridged: bool = False  # the first scan of a run carried on across a gap (`carry_on`)


def insert_scan(
    matching_map: MatchingMap,
    points_m: ArrayLike,
    pose: Pose2D,
    no_return_m: ArrayLike | None = None,
    mount: Pose2D = IDENTITY,
) -> InsertResult:
    """Insert a scan's endpoints (robot frame) within the grid's max range of the sensor, and
    clear along its no-return beams (up to the grid's no_return_clear_m), the robot at `pose`
    (T_map_base) and the sensor at `mount` on it: the one insertion the front end and the map
    server both use."""
    points = as_points(points_m, "points_m")
    reach = np.hypot(points[:, 0] - mount.x, points[:, 1] - mount.y)
    in_range = reach <= matching_map.grid.params.max_range_m
    misses = None
    if no_return_m is not None:
        misses = pose.transform_points(as_points(no_return_m, "no_return_m"))
    origin = pose * mount
    return matching_map.update(
        pose.transform_points(points[in_range]), (origin.x, origin.y), no_return_endpoints=misses
    )


def corridor_start(coarse: MatchResult, guess: Pose2D, points: NDArray[np.float64]) -> MatchResult:
    """A search's DEGENERATE optimum moved to the guess's position along its corridor's axis
    (`guess_position_along`), heading kept; any other result as it is.

    Along a corridor the search's best peak lies anywhere in its window, and the refinement,
    DEGENERATE too, keeps its start's position there: on the simulated corridor with an RPLidar
    a search 0.84 m along it was refined and accepted, and the robot jumped by that much."""
    if coarse.status is not MatchStatus.DEGENERATE or coarse.weak_direction is None:
        return coarse
    along = guess_position_along(coarse.weak_direction, coarse.pose, guess,
                                 weak_length_m(coarse.extra, points))
    return coarse if along is None else replace(coarse, pose=along)


def default_settings() -> FrontendSettings:
    """The documented defaults, without reading the environment (library code never does)."""
    return FrontendSettings.model_construct()


def occupancy_params(settings: FrontendSettings) -> OccupancyParams:
    """The map's sensor model as the settings give it (the map server builds the same map)."""
    return OccupancyParams(
        resolution_m=settings.map_resolution_m, no_return_clear_m=settings.no_return_clear_m
    )


class Frontend:
    """Tracks one robot against its own growing map (see the module docstring)."""

    def __init__(
        self,
        settings: FrontendSettings | None = None,
        initial_pose: Pose2D | None = None,
        grid: OccupancyGrid | None = None,
    ) -> None:
        s = settings if settings is not None else default_settings()
        self.settings = s
        self.initial_pose = initial_pose or Pose2D()
        self.map = MatchingMap(grid if grid is not None else OccupancyGrid(occupancy_params(s)))
        if not s.update_map and self.map.is_empty:
            raise ValueError("update_map=False (localise only) needs a non-empty prior map")
        self.trajectory = TrajectoryStore()
        self._limits = AcceptanceLimits(
            max_correction_m=s.max_correction_m,
            max_correction_rad=math.radians(s.max_correction_deg),
            min_score=s.min_score,
            max_position_std_m=s.max_position_std_m,
            max_heading_std_rad=math.radians(s.max_heading_std_deg),
            accept_degenerate=s.accept_degenerate,
        )
        self._predictor = MotionPredictor(
            s.max_odom_step_m, math.radians(s.max_odom_step_deg), s.cv_horizon_s,
            s.max_odom_speed_mps, math.radians(s.max_odom_turn_rate_deg_s),
        )
        self._filter = MotionFilter(
            s.insert_min_distance_m, math.radians(s.insert_min_angle_deg), s.insert_max_interval_s
        )
        self._initialised = not self.map.is_empty
        # A prior map and no start: the first scan is searched for over the whole map.
        self._lost = self._initialised and initial_pose is None
        self._rejections = 0  # rejected scans in a row
        self._bridged = False  # carried on across a gap: checked by a wide search till accepted
        self._covariance = np.zeros((3, 3))
        self._scores = RecentScores()  # of the accepted matches by settings.method

    @property
    def pose(self) -> Pose2D | None:
        """The latest estimate, None before the first scan."""
        return self._predictor.last_pose

    def process(
        self,
        points_m: ArrayLike,
        stamp_s: float,
        odom_pose: Pose2D | None = None,
        seq: int = 0,
        no_return_m: ArrayLike | None = None,
        mount: Pose2D = IDENTITY,
    ) -> FrontendOutput:
        """Track one scan (see the module docstring); never raises for bad scan content.
        ValueError for a non-finite `stamp_s`, before anything is changed."""
        if not math.isfinite(stamp_s):
            raise ValueError(f"stamp_s must be finite, got {stamp_s!r}")
        points = as_points(points_m, "points_m")
        misses = np.zeros((0, 2)) if no_return_m is None else as_points(no_return_m, "no_return_m")
        unused = ""
        if odom_pose is not None and not max(abs(odom_pose.x), abs(odom_pose.y)) <= MAX_ODOM_M:
            # Its increments would overflow to inf (a fuzzing audit saw ValueError from here).
            unused, odom_pose = f"odometry pose {odom_pose} beyond +-{MAX_ODOM_M:g} m: unused", None
        prediction = self._predict(stamp_s, odom_pose)
        if unused:
            prediction = replace(prediction, message="; ".join(
                m for m in (unused, prediction.message) if m))
        step = _Step(prediction, points, misses, float(stamp_s), odom_pose, seq, mount,
                     bridged=self._bridged)
        if len(points) < self.settings.min_points:
            reason = f"{len(points)} valid points, need min_points={self.settings.min_points}"
            return self._finish(step, FrontendStatus.TOO_FEW_POINTS, None, reason)
        if not self._initialised:
            self._initialised = True
            return self._finish(step, FrontendStatus.INITIALISED, None, "map initialised")
        t0 = time.perf_counter()
        try:
            if self._lost or self._search_due():
                result, status, note = self._localise_globally(points)
            else:
                result, status, note = self._match(step)
        except MatchInputError as exc:  # e.g. a search over its caps for these points
            note = f"the match refused its input: {exc}"
            result = failed(self.settings.method, MatchStatus.STEP_LIMIT, prediction.pose, note)
            status = FrontendStatus.REJECTED
        step.match_time_s = time.perf_counter() - t0
        return self._finish(step, status, result, note)

    def _predict(self, stamp_s: float, odom_pose: Pose2D | None) -> Prediction:
        prediction = self._predictor.predict(stamp_s, odom_pose)
        if self._predictor.last_pose is None:
            return Prediction(self.initial_pose, Pose2D(), prediction.source, prediction.message)
        return prediction

    def _match(self, step: _Step) -> tuple[MatchResult, FrontendStatus, str]:
        """The local match, else the fallback search refined locally, with a note on why."""
        s = self.settings
        points, guess = step.points, step.prediction.pose
        result = match(points, self.map, guess, method=s.method)
        reason = rejection_reason(result, guess, self._limits)
        if not reason:
            return self._recheck(step, result)
        if not s.fallback_method:
            return result, FrontendStatus.REJECTED, reason
        found, status, note = self.relocalise(points, guess, self._uncertainty(step))
        if status is FrontendStatus.RECOVERED:
            return found, status, f"{note}: {reason}"
        # Rejected: the search's optimum when it found one, else the local match.
        return (found if found.ok else result), status, f"{reason}; {note}"

    def _recheck(
        self, step: _Step, result: MatchResult
    ) -> tuple[MatchResult, FrontendStatus, str]:
        """A passing match, TRACKED; unless it scores far below the recent ones (see
        `recheck`): then the fallback search's match when that scores recheck_margin higher
        (RECOVERED), else the match as it was, with a note of the search."""
        s = self.settings
        bridged = step.bridged
        if not (s.fallback_method and (bridged or self._scores.is_low(result.score,
                                                                      s.recheck_ratio))):
            return result, FrontendStatus.TRACKED, result.message
        step.rechecked = True
        low = (
            "predicted by the odometry across the gap the run was carried on over" if bridged
            else f"score {result.score:.3f} below {s.recheck_ratio} x the recent median "
            f"{self._scores.median():.3f}"
        )
        found, status, note = self.relocalise(
            step.points, step.prediction.pose, self._uncertainty(step)
        )
        if status is FrontendStatus.RECOVERED and found.score >= result.score + s.recheck_margin:
            return found, status, f"rechecked, {note} ({found.score:.3f}): {low}"
        kept = f"rechecked and kept: {low}; the search: {note} ({found.score:.3f})"
        return result, FrontendStatus.TRACKED, "; ".join(m for m in (result.message, kept) if m)

    def set_pose(
        self, pose: Pose2D, stamp_s: float | None = None, odom_pose: Pose2D | None = None
    ) -> None:
        """An operator's word for where the robot is (ROS's /initialpose): the next scan is
        matched from `pose` (before the first scan: the start). With `stamp_s` and `odom_pose`,
        where the robot was at that stamp and the odometry pose there (the scans since were
        lost): the next scan is matched from `pose` moved by the odometry since. No whole-map
        search is pending any more."""
        if not all(math.isfinite(v) for v in (pose.x, pose.y, pose.theta)):
            raise ValueError(f"pose must be finite, got {pose}")
        self._lost = False
        self._rejections = 0
        self._bridged = False  # the operator's word: the checks judge it as a prediction
        if stamp_s is not None and odom_pose is not None:
            self._predictor.restart(stamp_s, pose, odom_pose)
        elif self._predictor.last_pose is None:
            self.initial_pose = pose
        else:
            self._predictor.place(pose)

    def carry_on(self, stamp_s: float, pose: Pose2D, odom_pose: Pose2D) -> None:
        """Carry on a run from its last estimate, `pose` at `stamp_s` with the odometry pose
        `odom_pose` there (a restarted matcher resuming the map server's path): the next scan is
        predicted from it by the odometry since, however long this tracker was out, and its
        match checked by a search over the widest fallback window (the odometry may have
        drifted metres meanwhile), as a low-scoring match is."""
        if not all(math.isfinite(v) for v in (pose.x, pose.y, pose.theta)):
            raise ValueError(f"pose must be finite, got {pose}")
        self._predictor.update(stamp_s, pose, odom_pose)
        self._lost = False  # it has a pose: no whole-map search is pending
        self._bridged = True

    def redraw(self, matching_map: MatchingMap, correction: Pose2D) -> None:
        """Track on `matching_map` from now on: the map redrawn in another frame (T_new_old =
        `correction`), as the back end does after optimising its pose graph. The last pose, its
        uncertainty and the last insertion move with the frame; the odometry chain and velocity
        carry on. The trajectory already recorded stays in the frame it was estimated in."""
        self.map = matching_map
        self._predictor.move_frame(correction)
        self._filter.move_frame(correction)
        self._covariance = _turned(self._covariance, correction)

    def _search_due(self) -> bool:
        """After every `global_after_rejections` rejected scans in a row (each search costs
        about a second on a building's map, so a robot that stays lost does not pay it on
        every scan)."""
        n = self.settings.global_after_rejections
        return n > 0 and self._rejections > 0 and self._rejections % n == 0

    def _localise_globally(
        self, points: NDArray[np.float64]
    ) -> tuple[MatchResult, FrontendStatus, str]:
        """The whole-map search, refined with settings.method: LOCALISED if it passes the
        match checks (all but the correction from a prediction, which it has none of)."""
        s = self.settings
        found, too_large = None, ""
        for level in range(s.global_level, MAX_GLOBAL_LEVEL + 1):  # coarser if the map is large
            try:
                found = localise_globally(points, self.map, refine=s.method, level=level)
                break
            except MatchInputError as exc:  # over the search's caps at this level
                too_large = str(exc)
        if found is None:
            note = f"whole-map search: the map is too large even at level {MAX_GLOBAL_LEVEL}: "
            return (failed(s.method, MatchStatus.STEP_LIMIT, IDENTITY, too_large),
                    FrontendStatus.REJECTED, note + too_large)
        reason = rejection_reason(found, found.pose, self._limits)
        if reason:
            return found, FrontendStatus.REJECTED, f"whole-map search: {reason}"
        self._lost = False
        return found, FrontendStatus.LOCALISED, (
            f"localised by a whole-map search in {found.time_s:.2f} s"
        )

    def relocalise(
        self, points_m: ArrayLike, guess: Pose2D, uncertainty: ArrayLike | None = None
    ) -> tuple[MatchResult, FrontendStatus, str]:
        """Search the map around `guess` (settings.fallback_method over +-fallback_linear_m /
        +-fallback_angular_deg, widened to 3 std of `uncertainty`, the guess's 3x3 covariance,
        up to fallback_max_linear_m / _angular_deg), refine the best pose with settings.method,
        and check it against `guess` as a tracked match is, its correction allowed as far as
        the search reached: RECOVERED with the match, or REJECTED with why. The front end's own
        state is untouched. Needs a fallback method and a non-empty map."""
        s = self.settings
        if not s.fallback_method:
            raise ValueError("relocalise needs settings.fallback_method (it is '')")
        points = as_points(points_m, "points_m")
        own = self._search_window(None)
        linear_m, angular_rad = self._search_window(uncertainty)
        try:
            coarse = self._search(points, guess, linear_m, angular_rad)
        except MatchInputError:  # widened past the search's caps (many points reaching far)
            if (linear_m, angular_rad) == own:
                raise
            linear_m, angular_rad = own
            coarse = self._search(points, guess, linear_m, angular_rad)
        if not found_a_pose(coarse):  # a corridor's search still gives gn its start
            return coarse, FrontendStatus.REJECTED, f"fallback: {coarse.message}"
        coarse = corridor_start(coarse, guess, points)
        refined = match(points, self.map, coarse.pose, method=s.method)
        limits = replace(
            self._limits, max_correction_m=max(self._limits.max_correction_m, linear_m),
            max_correction_rad=max(self._limits.max_correction_rad, angular_rad),
        )
        widened = ""
        if (linear_m, angular_rad) != own:
            widened = f" over +-{linear_m:.2f} m, +-{math.degrees(angular_rad):.0f} deg"
        if not rejection_reason(refined, guess, limits):
            return refined, FrontendStatus.RECOVERED, f"recovered by {s.fallback_method}{widened}"
        # The search's own optimum (grid resolution) when refining it fails too.
        coarse_reason = rejection_reason(coarse, guess, limits)
        if coarse_reason:
            return coarse, FrontendStatus.REJECTED, f"after fallback: {coarse_reason}"
        return coarse, FrontendStatus.RECOVERED, (
            f"recovered by {s.fallback_method}{widened} alone ({s.method} refinement failed)"
        )

    def _search(
        self, points: NDArray[np.float64], guess: Pose2D, linear_m: float, angular_rad: float
    ) -> MatchResult:
        """The fallback search over +-linear_m / +-angular_rad around `guess`."""
        s = self.settings
        return match(points, self.map, guess, method=s.fallback_method, linear_m=linear_m,
                     angular_rad=angular_rad, resolution_m=s.map_resolution_m)

    def _search_window(self, uncertainty: ArrayLike | None) -> tuple[float, float]:
        """The fallback search's half-width (m) and half-angle (rad): the settings', widened
        to 3 std of `uncertainty` up to their maxima (an unknown direction: the maxima)."""
        s = self.settings
        linear_m, angular_rad = s.fallback_linear_m, math.radians(s.fallback_angular_deg)
        if uncertainty is None:
            return linear_m, angular_rad
        variances = np.nan_to_num(np.diag(np.asarray(uncertainty, dtype=float)), nan=np.inf)
        std_m = math.sqrt(max(float(variances[0]), float(variances[1]), 0.0))
        std_rad = math.sqrt(max(float(variances[2]), 0.0))
        return (
            max(linear_m, min(3.0 * std_m, s.fallback_max_linear_m)),
            max(angular_rad, min(3.0 * std_rad, math.radians(s.fallback_max_angular_deg))),
        )

    def _uncertainty(self, step: _Step) -> NDArray[np.float64]:
        """The prediction's covariance: the last estimate's, grown by the motion since (scans
        rejected in a row: wide); unknown (infinite) for the first scan of a run carried on
        across a gap, whose odometry drifts in ways its end points do not show (a loop
        driven while a matcher was out)."""
        if step.bridged:
            return np.diag([math.inf, math.inf, math.inf])
        return self._covariance + self._motion_noise(step.prediction.motion)

    def _finish(
        self, step: _Step, status: FrontendStatus, result: MatchResult | None, note: str
    ) -> FrontendOutput:
        """Adopt the match (accepted) or the prediction (rejected), insert if due, report."""
        if status in ACCEPTED:
            self._rejections = 0
            self._bridged = False
            pose = step.prediction.pose if result is None else result.pose
            self._covariance = np.zeros((3, 3)) if result is None else result.covariance
            if result is not None and result.method == self.settings.method:
                self._scores.add(result.score)
        else:
            # Too few points leave the count of rejections in a row as it is.
            self._rejections += status is FrontendStatus.REJECTED
            # The map is not touched; uncertainty grows with the motion since the last match.
            pose = step.prediction.pose
            self._covariance = self._covariance + self._motion_noise(step.prediction.motion)
        if status is FrontendStatus.LOCALISED:
            self._predictor.restart(step.stamp_s, pose, step.odom_pose)
        else:
            self._predictor.update(step.stamp_s, pose, step.odom_pose)
        self.trajectory.append(step.stamp_s, pose)
        inserted, insert_time_s = False, 0.0
        due = status in ACCEPTED and self.settings.update_map
        if due and self._filter.should_insert(step.stamp_s, pose):
            t0 = time.perf_counter()
            insert_scan(self.map, step.points, pose, step.no_return, step.mount)
            insert_time_s = time.perf_counter() - t0
            self._filter.mark_inserted(step.stamp_s, pose)
            inserted = True
        return FrontendOutput(
            seq=step.seq,
            stamp_s=step.stamp_s,
            pose=pose,
            covariance=self._covariance.copy(),
            status=status,
            method="" if result is None else result.method,
            iterations=0 if result is None else result.iterations,
            score=0.0 if result is None else result.score,
            message="; ".join(m for m in (step.prediction.message, note) if m),
            inserted=inserted,
            prediction_source=str(step.prediction.source),
            match_time_s=step.match_time_s,
            insert_time_s=insert_time_s,
            rechecked=step.rechecked,
        )

    def _motion_noise(self, motion: Pose2D) -> NDArray[np.float64]:
        s = self.settings
        std_m = max(s.prediction_floor_std_m, s.odom_noise_m_per_m * motion.translation_norm())
        std_rad = max(
            math.radians(s.prediction_floor_std_deg), s.odom_noise_rad_per_rad * abs(motion.theta)
        )
        return np.diag([std_m**2, std_m**2, std_rad**2])
