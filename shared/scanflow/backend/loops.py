"""Loop closure: recognise a place seen before and measure the robot's pose relative to it.

For a new keyframe k the candidates are earlier keyframes j within `search_radius_m` of it by the
current estimates and at least `min_travel_m` back along the path (nearer ones are already tied
to k through the chain of keyframes). A candidate's submap is keyframes j-w .. j+w (those before
k) drawn into j's frame at their current relative poses, free space included (a small
MatchingMap). Scan k is
searched on it by branch and bound over +-linear_m / +-angular_deg around the estimated
relative pose, and the best pose is refined with `method` (Cartographer's constraint builder).
The closure is kept when the refined match passes the front end's checks, scores at least
`min_score`, and no distinct pose of the window scores within `ambiguity_ratio` of the best (a
corridor or a look-alike room). The measurement T_j^-1 T_k and its covariance become a robust
edge of the pose graph, which can still out-vote a wrong one.
"""

from __future__ import annotations

import copy
import math
from collections import OrderedDict
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from scanflow.config import BackendSettings
from scanflow.frontend.acceptance import AcceptanceLimits, rejection_reason
from scanflow.geometry import Pose2D, compose_arrays
from scanflow.maps.matching_map import MatchingMap
from scanflow.maps.occupancy import OccupancyGrid, OccupancyParams, RayBatch
from scanflow.matching import match
from scanflow.matching.csm import found_a_pose

SUBMAPS_KEPT = 64  # candidate submaps cached between keyframes (a few MB)


@dataclass(frozen=True, eq=False)
class ScanNode:
    """A keyframe as the back end keeps it: its scan in the robot's frame at `stamp_s`."""

    stamp_s: float
    points: NDArray[np.float64]
    no_return: NDArray[np.float64]
    mount: Pose2D


@dataclass(frozen=True, eq=False)
class LoopClosure:
    """Keyframe `newer` seen from keyframe `older`: T_older^-1 T_newer = measurement."""

    older: int
    newer: int
    measurement: Pose2D
    covariance: NDArray[np.float64]
    score: float


def keyframe_rays(
    nodes: list[ScanNode], poses: NDArray[np.float64], max_range_m: float
) -> RayBatch:
    """Every keyframe's beams in the map, at its pose (rows x, y, theta): the floats the front
    end's `insert_scan` computes for each, with numpy called once for all of them."""
    placed = [Pose2D.from_array(pose) for pose in poses]
    sensors = [pose * node.mount for pose, node in zip(placed, nodes, strict=True)]
    mounts = np.array([(n.mount.x, n.mount.y) for n in nodes], dtype=np.float64).reshape(-1, 2)
    frames = np.array(
        [(math.cos(p.theta), math.sin(p.theta), p.x, p.y) for p in placed], dtype=np.float64
    ).reshape(-1, 4)

    def in_map(
        arrays: list[NDArray[np.float64]], reach_m: float
    ) -> tuple[NDArray[np.float64], NDArray[np.int64]]:
        """The finite points (robot frame) within `reach_m` of their sensor, in the map."""
        points = np.concatenate([np.zeros((0, 2)), *(a.reshape(-1, 2) for a in arrays)])
        owner = np.repeat(np.arange(len(arrays)), [a.size // 2 for a in arrays])
        keep = np.isfinite(points).all(axis=1)
        if math.isfinite(reach_m):
            m = mounts[owner]
            keep &= np.hypot(points[:, 0] - m[:, 0], points[:, 1] - m[:, 1]) <= reach_m
        points, owner = points[keep], owner[keep]
        c, s, x, y = frames[owner].T
        world = np.empty_like(points)
        world[:, 0] = c * points[:, 0] - s * points[:, 1] + x  # as Pose2D.transform_points
        world[:, 1] = s * points[:, 0] + c * points[:, 1] + y
        starts = np.searchsorted(owner, np.arange(len(arrays) + 1))
        return world, starts

    hits, hit_starts = in_map([n.points for n in nodes], max_range_m)
    misses, miss_starts = in_map([n.no_return for n in nodes], math.inf)
    origins = np.array([(p.x, p.y) for p in sensors], dtype=np.float64).reshape(-1, 2)
    return RayBatch(origins, hits, hit_starts, misses, miss_starts)


def draw_keyframes(
    nodes: list[ScanNode], poses: NDArray[np.float64], params: OccupancyParams,
    base: OccupancyGrid | None = None,
) -> MatchingMap:
    """A new map of `nodes` inserted at `poses` (rows x, y, theta), free space included, on a
    copy of `base` (a prior map) or on nothing: a candidate's submap, and the back end's whole
    map. The same map, bit for bit, as the front end's inserts of the same scans one at a
    time."""
    grid = OccupancyGrid(params) if base is None else copy.deepcopy(base)
    grid.insert_scans(keyframe_rays(nodes, poses, params.max_range_m))
    return MatchingMap(grid)


def loop_candidates(
    poses: NDArray[np.float64], travelled_m: NDArray[np.float64], k: int,
    settings: BackendSettings,
) -> list[int]:
    """Keyframes j < k within search_radius_m of k and min_travel_m back along the path,
    nearest first, at most max_candidates, each from a different stretch of the path (their
    submaps would overlap otherwise)."""
    older = np.flatnonzero(travelled_m[:k] <= travelled_m[k] - settings.min_travel_m)
    if len(older) == 0:
        return []
    distance = np.hypot(poses[older, 0] - poses[k, 0], poses[older, 1] - poses[k, 1])
    near = older[distance <= settings.search_radius_m]
    chosen: list[int] = []
    for j in near[np.argsort(distance[distance <= settings.search_radius_m], kind="stable")]:
        if all(abs(travelled_m[j] - travelled_m[c]) > settings.min_travel_m for c in chosen):
            chosen.append(int(j))
        if len(chosen) == settings.max_candidates:
            break
    return chosen


class LoopDetector:
    """Finds and measures loop closures for new keyframes (see the module docstring)."""

    def __init__(self, settings: BackendSettings, params: OccupancyParams) -> None:
        self.settings = settings
        self.params = params
        self._limits = AcceptanceLimits(
            max_correction_m=settings.linear_m,
            max_correction_rad=math.radians(settings.angular_deg),
            min_score=settings.min_score,
            max_position_std_m=settings.max_position_std_m,
            max_heading_std_rad=math.radians(settings.max_heading_std_deg),
            accept_degenerate=False,
        )
        self._submaps: OrderedDict[int, MatchingMap] = OrderedDict()

    def forget_submaps(self) -> None:
        """Drop cached submaps (the keyframes' relative poses changed)."""
        self._submaps.clear()

    def submap(self, nodes: list[ScanNode], poses: NDArray[np.float64], j: int) -> MatchingMap:
        """Keyframes j-w .. j+w (w = submap_half_nodes; those that exist) drawn in keyframe j's
        frame at their current poses; cached until `forget_submaps`."""
        cached = self._submaps.get(j)
        if cached is not None:
            self._submaps.move_to_end(j)
            return cached
        w = self.settings.submap_half_nodes
        window = slice(max(0, j - w), min(len(nodes), j + w + 1))
        in_j = compose_arrays(Pose2D.from_array(poses[j]).inverse().to_array(), poses[window])
        submap = draw_keyframes(nodes[window], in_j, self.params)
        self._submaps[j] = submap
        if len(self._submaps) > SUBMAPS_KEPT:
            self._submaps.popitem(last=False)
        return submap

    def verify(
        self, nodes: list[ScanNode], poses: NDArray[np.float64], j: int, k: int
    ) -> LoopClosure | str:
        """Match keyframe k on keyframe j's submap: the closure, or why there is none."""
        s = self.settings
        guess = Pose2D.from_array(poses[j]).inverse() * Pose2D.from_array(poses[k])
        # Keyframes before k only: k's own scan in the window (j within w of k, the odometer
        # run up by culled inserts) would match itself at the guess, a closure out of nothing.
        submap = self.submap(nodes[:k], poses, j)
        points = nodes[k].points
        coarse = match(
            points, submap, guess, method="csm", linear_m=s.linear_m,
            angular_rad=math.radians(s.angular_deg), resolution_m=self.params.resolution_m,
            # A rival under ambiguity_ratio x the best changes nothing: the search prunes it.
            candidates=2, suppress_m=s.rival_distance_m,
            suppress_rad=math.radians(s.rival_angle_deg), candidate_min_ratio=s.ambiguity_ratio,
        )
        # A corridor's search goes on: its rivals along the corridor make it ambiguous, and
        # the fine match must pass without accept_degenerate.
        if not found_a_pose(coarse):
            return f"search: {coarse.message}"
        scores = coarse.extra["candidate_scores"]
        rival = scores[1] / scores[0] if len(scores) > 1 and scores[0] > 0 else 0.0
        if rival >= s.ambiguity_ratio:
            return f"ambiguous: a distinct pose scores {rival:.2f} x the best"
        fine = match(points, submap, coarse.pose, method=s.method)
        reason = rejection_reason(fine, guess, self._limits)
        if reason:
            return reason
        return LoopClosure(j, k, fine.pose, fine.covariance, fine.score)
