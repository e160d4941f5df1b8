"""Graph SLAM around the front end: keyframes become pose-graph nodes, loop closures robust
edges, and the optimised graph redraws the map the front end tracks on.

    mapper = Mapper(frontend, BackendSettings(loop_closure=True))
    out = frontend.process(points, stamp_s, odom_pose, seq, no_return, mount)
    step = mapper.add(out, points, no_return, mount)   # after every scan -> MapperStep
    mapper.finish()                                     # last optimisation, final map
    mapper.trajectory()                                 # every scan's corrected pose, (N, 3)

Each scan the front end inserts is a keyframe: a node whose edge to the previous keyframe is
the front end's motion between them (std `keyframe_std_*`). Each keyframe is checked for loop
closures (`scanflow.backend.loops`). A closure enters the graph, as a robust edge, once a closure
of another of the last `confirm_keyframes` keyframes to the same place implies the same
correction of the estimates (within `confirm_m` / `confirm_deg`): a wrong closure seldom agrees
with another. After `optimise_every` keyframes with a new closure the graph is optimised, and
when that moves a keyframe more than `redraw_shift_*` against the front end's map, the map is
redrawn from all keyframes at their optimised poses and the front end carries on in it
(`Frontend.redraw`). A scan that is not a keyframe keeps its pose relative to the keyframe it
hangs from (the last one), so it follows that keyframe's correction. With `cull_m` set, an
insert the front end tracked within `cull_m` / `cull_deg` of a keyframe already drawn is not
made a keyframe: it and the scans after it hang from that keyframe, and the next keyframe is
linked to it. A parked robot, or one going over ground it mapped, then adds no keyframes, so
the graph, the redraws and the kept scans grow with the ground covered, not with the time.
On a prior map (`prior`: the front end localises on it and extends it) the keyframes are drawn
on the prior map, which stays as it was, and the graph stays in its frame (keyframe 0 is held
where the front end put it): the keyframes made while tracking on the prior map tie the graph
to it, and the closures with them pull back what drifted where the robot left it.
When the front end is put at a pose from outside (an operator's, `relocated()`), the motion to
the next keyframe is not measured: its edge is a weak link that the loop closures can move. A
run can be carried on from its keyframes at the poses they are drawn at (`SavedRun`: what a
restarted matcher gets back from the map server).

Memory: the keyframes' points (16 bytes per return), 40 bytes per scan and 8 per culled insert.
"""

from __future__ import annotations

import copy
import math
from array import array
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from scanflow.backend.loops import (
    LoopClosure,
    LoopDetector,
    ScanNode,
    draw_keyframes,
    loop_candidates,
)
from scanflow.backend.pose_graph import OptimiseReport, PoseGraph, grown
from scanflow.config import BackendSettings
from scanflow.frontend.tracker import Frontend, FrontendOutput, FrontendStatus, occupancy_params
from scanflow.geometry import IDENTITY, Pose2D, compose_arrays, normalize_angles, relative_arrays
from scanflow.maps.matching_map import MatchingMap
from scanflow.maps.occupancy import OccupancyGrid


@dataclass(frozen=True, eq=False)
class MapperStep:
    """What the back end did with one scan."""

    node: int | None  # the keyframe's index, None when the scan is not one
    closures: tuple[LoopClosure, ...] = ()
    optimised: OptimiseReport | None = None
    # Set when the map was redrawn: T_new_old, the front end's frame change.
    correction: Pose2D | None = None
    # Set when the front end inserted the scan but the back end culled it as a keyframe: the
    # keyframe it hangs from.
    culled_to: int | None = None

    @property
    def redrawn(self) -> bool:
        """True when the map was redrawn this step (`correction` is set)."""
        return self.correction is not None


@dataclass(frozen=True, eq=False)
class SavedRun:
    """A run to carry on: its keyframes with their seqs, at the poses they are drawn at in the
    map the front end resumes on, and every scan's stamp and pose so far."""

    nodes: list[ScanNode]
    seqs: list[int]
    poses: NDArray[np.float64]  # (K, 3)
    stamps_s: NDArray[np.float64]  # (N,)
    path: NDArray[np.float64]  # (N, 3)


@dataclass
class _Waiting:
    """A recent closure, the correction of the estimates it implies, and whether it is in the
    graph (it enters once another recent closure agrees with it)."""

    closure: LoopClosure
    correction: Pose2D
    entered: bool


def _rotated(covariance: NDArray[np.float64], theta: float) -> NDArray[np.float64]:
    """A relative pose's covariance in the frame of a measurement turned by `theta`."""
    c, s = math.cos(theta), math.sin(theta)
    j = np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]])
    return j @ covariance @ j.T


class Mapper:
    """Keyframes, loop closures and the pose graph of one robot (see the module docstring)."""

    def __init__(
        self, frontend: Frontend, settings: BackendSettings, saved: SavedRun | None = None,
        prior: OccupancyGrid | None = None,
    ) -> None:
        """`frontend` starts from an empty map, or from `prior` (a prior map it localises
        on and extends), or from the map of `saved`'s keyframes (on `prior`, if any), to carry
        on a run (a restarted matcher). With a prior map the back end draws its keyframes on
        it: the front end, tracking on the prior map, ties the keyframes to it, and the loop
        closures between keyframes correct the drift where it left the prior map."""
        if saved is None and prior is None and not frontend.map.is_empty:
            raise ValueError(
                "the front end already has a map (a prior map?): give it to the back end too "
                "(`prior`), which draws its keyframes on it"
            )
        self.frontend = frontend
        self.settings = settings
        self.params = occupancy_params(frontend.settings)
        self.prior = None if prior is None else copy.deepcopy(prior)  # redraws start from it
        self.graph = PoseGraph()
        self.nodes: list[ScanNode] = []
        self.closures: list[LoopClosure] = []
        self.detector = LoopDetector(settings, self.params)
        # Keyframes in the front end's current map frame, x y theta (rows in use: the graph's).
        self._drawn = np.zeros((0, 3))
        self._anchor = -1  # the keyframe the robot hangs from now (the last, unless culled)
        self._culled_at: Pose2D | None = None  # the last insert, when it was culled
        self._since_m = 0.0  # the distance over culled inserts since the last keyframe
        self._travelled_m: list[float] = []
        self.keyframe_seqs: list[int] = []  # per keyframe: its scan's seq
        self.culled_seqs = array("q")  # the seqs of inserts culled as keyframes (8 bytes each)
        self.resumed_keyframes = 0  # how many keyframes came from a saved run (no culled seqs do)
        self._scan_stamps = array("d")  # per scan: its stamp
        self._scan_node = array("q")  # per scan: the keyframe it hangs from (-1: none yet)
        self._scan_offset = array("d")  # per scan: x, y, theta relative to that keyframe
        self._waiting: list[_Waiting] = []  # recent closures, entered or waiting for another
        self._entered_at = -1  # the last keyframe whose search put a closure in the graph
        self._searched_at = -1  # the last keyframe searched for closures
        self._pending = 0  # keyframes since the last optimisation
        self._unoptimised = False
        self._relocated = False  # the front end was put somewhere since the last keyframe
        if saved is not None:
            self._resume(saved)

    def add(
        self,
        out: FrontendOutput,
        points_m: ArrayLike,
        no_return_m: ArrayLike | None = None,
        mount: Pose2D = IDENTITY,
    ) -> MapperStep:
        """Take the front end's output for one scan (with the points it processed)."""
        if not out.inserted:
            self._record_scan(out.stamp_s, out.pose)
            return MapperStep(None)
        near = self._held(out)
        if near is not None:
            self._since_m += (self._last_insert().inverse() * out.pose).translation_norm()
            self._anchor, self._culled_at = near, out.pose
            self.culled_seqs.append(out.seq)
            self._record_scan(out.stamp_s, out.pose)
            return MapperStep(None, culled_to=near)
        node = self._add_node(out, points_m, no_return_m, mount)
        self._record_scan(out.stamp_s, out.pose)  # before an optimisation moves the map's frame
        closures = tuple(self._close_loops(node))
        self._unoptimised |= bool(closures)
        self._pending += 1
        if self._unoptimised and self._pending >= self.settings.optimise_every:
            return MapperStep(node, closures, *self._optimise())
        return MapperStep(node, closures)

    def relocated(self) -> None:
        """The front end was put at a pose from outside (`Frontend.set_pose`): the next
        keyframe's edge to the last one becomes a weak link (std `relocated_std_*`)."""
        self._relocated = bool(self.nodes)

    def finish(self) -> MapperStep:
        """Optimise once more if a closure came since the last optimisation, and redraw the
        map from the optimised keyframes if that moved any (call once the log has ended)."""
        if not self._unoptimised:
            return MapperStep(None)
        return MapperStep(None, (), *self._optimise())

    def trajectory(self) -> NDArray[np.float64]:
        """Every scan's pose (x, y, theta), in the optimised graph's frame."""
        if not self._scan_node:
            return np.zeros((0, 3))
        offsets = self._offset_rows()
        if self.graph.node_count == 0:
            return offsets
        anchors = self.graph.poses[np.array(self._scan_node, dtype=np.int64)]
        return compose_arrays(anchors, offsets)

    def drawn_pose(self, k: int) -> Pose2D:
        """Where keyframe `k` is drawn in the front end's current map."""
        return Pose2D.from_array(self._drawn_rows()[k])

    def drawn_poses(self) -> NDArray[np.float64]:
        """Every keyframe's pose in the front end's current map, (K, 3) (a copy)."""
        return self._drawn_rows().copy()

    def _drawn_rows(self) -> NDArray[np.float64]:
        """Every keyframe's drawn pose, (K, 3)."""
        return self._drawn[: self.graph.node_count]

    def stamps_s(self) -> NDArray[np.float64]:
        """Every scan's stamp, in the order of `trajectory()`."""
        return np.array(self._scan_stamps, dtype=np.float64)

    def _offset_rows(self) -> NDArray[np.float64]:
        """Every scan's pose relative to its keyframe, (N, 3) (a copy: the store can grow)."""
        return np.array(self._scan_offset, dtype=np.float64).reshape(-1, 3)

    def draw_map(self) -> MatchingMap:
        """A new map of every keyframe at its optimised pose (on the prior map, if any)."""
        return draw_keyframes(self.nodes, self.graph.poses, self.params, self.prior)

    def _add_node(
        self, out: FrontendOutput, points_m: ArrayLike, no_return_m: ArrayLike | None,
        mount: Pose2D,
    ) -> int:
        points = np.array(points_m, dtype=np.float64).reshape(-1, 2)
        misses = np.zeros((0, 2)) if no_return_m is None else np.array(no_return_m, np.float64)
        self.nodes.append(ScanNode(out.stamp_s, points, misses.reshape(-1, 2), mount))
        self.keyframe_seqs.append(out.seq)
        return self._chain(out.pose)

    def _chain(self, pose: Pose2D) -> int:
        """The graph node of the newest keyframe, at `pose` in the front end's map, linked to
        the keyframe before by the motion between them."""
        if self.graph.node_count == 0:
            index = self.graph.add_node(pose)
            self._travelled_m.append(0.0)
            # Scans before the first keyframe hang from it.
            first = pose.inverse().to_array()
            if self._scan_node:
                rebased = compose_arrays(first, self._offset_rows())
                self._scan_offset = array("d", rebased.ravel().tolist())
            self._scan_node = array("q", bytes(8 * len(self._scan_node)))
        else:
            # Linked to the keyframe it hangs from: the last one, or the one an insert was
            # culled to (the front end tracked on it since).
            anchor = self._anchor
            motion = self.drawn_pose(anchor).inverse() * pose
            step = motion if self._culled_at is None else self._culled_at.inverse() * pose
            index = self.graph.add_node(self.graph.pose(anchor) * motion)
            self.graph.add_edge(anchor, index, motion, self._keyframe_information(motion))
            self._relocated = False
            self._travelled_m.append(
                self._travelled_m[-1] + self._since_m + step.translation_norm()
            )
        self._drawn = grown(self._drawn, index)
        self._drawn[index] = (pose.x, pose.y, pose.theta)
        self._anchor, self._culled_at, self._since_m = index, None, 0.0
        return index

    def _last_insert(self) -> Pose2D:
        """The pose of the front end's last insert, in its current map frame."""
        return self.drawn_pose(-1) if self._culled_at is None else self._culled_at

    def _held(self, out: FrontendOutput) -> int | None:
        """The keyframe drawn nearest the inserted scan when it lies within cull_m / cull_deg
        of it and the front end tracked the scan on its map; None: the scan is a keyframe."""
        s = self.settings
        if (
            s.cull_m <= 0.0 or self.graph.node_count == 0 or self._relocated
            or out.status is not FrontendStatus.TRACKED
        ):
            return None
        drawn = self._drawn_rows()
        distance = np.hypot(drawn[:, 0] - out.pose.x, drawn[:, 1] - out.pose.y)
        near = np.flatnonzero(distance <= s.cull_m)
        turn = np.abs(normalize_angles(drawn[near, 2] - out.pose.theta))
        near = near[turn <= math.radians(s.cull_deg)]
        return int(near[np.argmin(distance[near])]) if near.size else None

    def _resume(self, saved: SavedRun) -> None:
        """Keyframes chained at their saved poses (the closures that placed them are in those
        poses; the chain keeps them together), every earlier scan hung from the last keyframe
        at or before it."""
        stamps = np.asarray(saved.stamps_s, dtype=np.float64)
        path = np.asarray(saved.path, dtype=np.float64)
        if path.shape != (len(stamps), 3):
            raise ValueError(
                f"saved.path must have shape ({len(stamps)}, 3), a pose per stamp, got "
                f"{path.shape}"
            )
        self.resumed_keyframes = len(saved.seqs)
        for node, seq, pose in zip(saved.nodes, saved.seqs, saved.poses, strict=True):
            self.nodes.append(node)
            self.keyframe_seqs.append(int(seq))
            self._chain(Pose2D.from_array(pose))
        if self.nodes:
            keyframe_stamps = np.array([n.stamp_s for n in self.nodes])
            nodes = np.maximum(np.searchsorted(keyframe_stamps, stamps, side="right") - 1, 0)
            offsets = relative_arrays(np.asarray(saved.poses)[nodes], path)
        else:
            nodes, offsets = np.full(len(stamps), -1), path
        self._scan_stamps = array("d", stamps.tolist())
        self._scan_node = array("q", nodes.tolist())
        self._scan_offset = array("d", np.asarray(offsets, dtype=np.float64).ravel().tolist())

    def _keyframe_information(self, motion: Pose2D) -> NDArray[np.float64]:
        s = self.settings
        if self._relocated:
            return np.diag([s.relocated_std_m**-2] * 2 + [math.radians(s.relocated_std_deg) ** -2])
        std_m = s.keyframe_std_m + s.keyframe_std_per_m * motion.translation_norm()
        std_rad = math.radians(s.keyframe_std_deg) + s.keyframe_std_deg_per_deg * abs(motion.theta)
        return np.diag([std_m**-2, std_m**-2, std_rad**-2])

    def _close_loops(self, k: int) -> list[LoopClosure]:
        """Verified closures of keyframe k, each entering the graph once another one of the
        last `confirm_keyframes` keyframes implies the same correction (a wrong closure rarely
        agrees with another). While closures keep entering (a revisit), only every
        `busy_search_every`-th keyframe is searched: its neighbours would say the same."""
        s = self.settings
        self._waiting = [w for w in self._waiting if w.closure.newer >= k - s.confirm_keyframes]
        busy = self._entered_at >= 0 and k - self._entered_at <= s.confirm_keyframes
        if busy and k - self._searched_at < s.busy_search_every:
            return []
        self._searched_at = k
        poses, travelled = self.graph.poses, np.asarray(self._travelled_m)
        added: list[LoopClosure] = []
        for j in loop_candidates(poses, travelled, k, s):
            closure = self.detector.verify(self.nodes, poses, j, k)
            if isinstance(closure, str):
                continue
            estimate = Pose2D.from_array(poses[closure.older]).inverse() * Pose2D.from_array(
                poses[k]
            )
            correction = estimate.inverse() * closure.measurement
            if s.confirm_keyframes == 0:
                added.append(self._add_closure(closure))
                continue
            agreeing = [w for w in self._waiting if self._agree(w, closure, correction)]
            for waiting in agreeing:
                if not waiting.entered:
                    added.append(self._add_closure(waiting.closure))
                    waiting.entered = True
            if agreeing:
                added.append(self._add_closure(closure))
            self._waiting.append(_Waiting(closure, correction, entered=bool(agreeing)))
        if added:
            self._entered_at = k
        return added

    def _agree(self, waiting: _Waiting, closure: LoopClosure, correction: Pose2D) -> bool:
        """Two closures of nearby keyframes to nearby places that imply the same correction."""
        s = self.settings
        other, other_correction = waiting.closure, waiting.correction
        if other.newer == closure.newer:
            return False
        if abs(other.older - closure.older) > 2 * s.submap_half_nodes + 1:
            return False
        # Each correction is in its own keyframe's frame: carried over to this keyframe's by
        # the motion between them, so a turn between the two changes nothing.
        motion = self.graph.pose(closure.newer).relative_to(self.graph.pose(other.newer))
        gap = (motion.inverse() * other_correction * motion).relative_to(correction)
        return gap.translation_norm() <= s.confirm_m and abs(gap.theta) <= math.radians(
            s.confirm_deg
        )

    def _add_closure(self, closure: LoopClosure) -> LoopClosure:
        s = self.settings
        floor = np.diag(
            [s.loop_min_std_m**2, s.loop_min_std_m**2, math.radians(s.loop_min_std_deg) ** 2]
        )
        covariance = _rotated(closure.covariance + floor, closure.measurement.theta)
        information = np.linalg.inv(0.5 * (covariance + covariance.T))
        self.graph.add_edge(
            closure.older, closure.newer, closure.measurement, information, robust=True
        )
        self.closures.append(closure)
        return closure

    def _optimise(self) -> tuple[OptimiseReport, Pose2D | None]:
        """Optimise the graph; redraw the front end's map if a keyframe moved against it."""
        report = self.graph.optimise(robust_scale=self.settings.robust_scale)
        self._pending = 0
        self._unoptimised = False
        self._waiting = []  # their corrections were against the old estimates
        self.detector.forget_submaps()
        optimised = self.graph.poses
        # T_graph_map on the keyframe the robot hangs from (the newest, unless culled to another)
        anchor = self._anchor
        correction = Pose2D.from_array(optimised[anchor]) * self.drawn_pose(anchor).inverse()
        moved = compose_arrays(
            np.array([[correction.x, correction.y, correction.theta]]), self._drawn_rows()
        )
        shift = moved - optimised
        shift_m = float(np.max(np.hypot(shift[:, 0], shift[:, 1])))
        shift_rad = float(np.max(np.abs(normalize_angles(shift[:, 2]))))
        s = self.settings
        if shift_m < s.redraw_shift_m and shift_rad < math.radians(s.redraw_shift_deg):
            return report, None
        self.frontend.redraw(self.draw_map(), correction)
        self._drawn = optimised
        if self._culled_at is not None:
            self._culled_at = correction * self._culled_at
        return report, correction

    def _record_scan(self, stamp_s: float, pose: Pose2D) -> None:
        node = self._anchor
        self._scan_stamps.append(stamp_s)
        anchor = self.drawn_pose(node) if node >= 0 else IDENTITY
        self._scan_node.append(node)
        self._scan_offset.extend((anchor.inverse() * pose).to_array().tolist())
