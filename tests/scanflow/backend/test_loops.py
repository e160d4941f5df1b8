"""Loop closure: which keyframes are candidates, and what a closure measures."""

from __future__ import annotations

import math

import numpy as np
from scanflow.backend.loops import (
    LoopClosure,
    LoopDetector,
    ScanNode,
    draw_keyframes,
    keyframe_rays,
    loop_candidates,
)
from scanflow.config import BackendSettings
from scanflow.frontend import default_settings, occupancy_params
from scanflow.frontend.tracker import insert_scan
from scanflow.geometry import IDENTITY, Pose2D
from scanflow.maps.matching_map import MatchingMap
from scanflow.maps.occupancy import OccupancyGrid
from scanflow.sim import get_world, static_scan

SETTINGS = BackendSettings.model_construct(loop_closure=True)


def _nodes(drive) -> list[ScanNode]:  # type: ignore[no-untyped-def]
    return [ScanNode(0.1 * i, s, np.zeros((0, 2)), IDENTITY) for i, s in enumerate(drive.scans)]


def _travelled(poses: np.ndarray) -> np.ndarray:
    return np.concatenate(([0.0], np.cumsum(np.hypot(*np.diff(poses[:, :2], axis=0).T))))


def test_candidates_are_near_and_far_back_along_the_path() -> None:
    # A straight drive out and back: keyframe 20 returns to where 0..4 were.
    xs = np.concatenate((np.arange(0, 10.0, 1.0), np.arange(10.0, -0.5, -1.0)))
    poses = np.column_stack((xs, np.zeros_like(xs), np.zeros_like(xs)))
    travelled = _travelled(poses)
    k = len(xs) - 1  # at x = 0, 20 m along the path
    found = loop_candidates(poses, travelled, k, SETTINGS)
    assert found[0] == 0  # nearest first
    assert all(travelled[k] - travelled[j] >= SETTINGS.min_travel_m for j in found)
    assert all(abs(poses[j, 0] - poses[k, 0]) <= SETTINGS.search_radius_m for j in found)
    assert len(found) <= SETTINGS.max_candidates
    # Recent keyframes are never candidates, however near.
    assert loop_candidates(poses, travelled, 5, SETTINGS) == []


def test_candidates_come_from_different_stretches_of_the_path() -> None:
    # Three passes over the same spot: one candidate per earlier pass, not two from one.
    xs = np.tile(np.concatenate((np.arange(0, 10.0, 0.5), np.arange(10.0, 0.0, -0.5))), 3)
    poses = np.column_stack((xs, np.zeros_like(xs), np.zeros_like(xs)))
    travelled = _travelled(poses)
    settings = SETTINGS.model_copy(update={"max_candidates": 5})
    found = loop_candidates(poses, travelled, len(xs) - 1, settings)
    gaps = np.diff(np.sort(travelled[found]))
    assert len(found) >= 2
    assert np.all(gaps > settings.min_travel_m)


def test_a_revisit_is_measured_from_a_drifted_guess(drive) -> None:  # type: ignore[no-untyped-def]
    """Keyframe k back at the start, its estimate 0.6 m / 3 deg off: the closure gives the
    true relative pose to within 3 cm / 0.3 deg."""
    detector = LoopDetector(SETTINGS, occupancy_params(default_settings()))
    nodes = _nodes(drive)
    j, k = 5, 170
    truth = Pose2D.from_array(drive.truth[j]).inverse() * Pose2D.from_array(drive.truth[k])
    estimates = drive.truth.copy()
    estimates[k] = (Pose2D.from_array(drive.truth[k]) * Pose2D(0.5, -0.3, math.radians(3)))\
        .to_array()
    closure = detector.verify(nodes, estimates, j, k)
    assert isinstance(closure, LoopClosure), closure
    error = closure.measurement.relative_to(truth)
    assert error.translation_norm() < 0.03
    assert abs(math.degrees(error.theta)) < 0.3
    assert (closure.older, closure.newer) == (j, k)
    assert np.all(np.linalg.eigvalsh(closure.covariance) > 0)


def test_a_place_that_is_not_there_gives_a_reason(drive) -> None:  # type: ignore[no-untyped-def]
    """Keyframe k on the far side of the ring, claimed to be at keyframe j's place: no
    closure, and the reason is named."""
    detector = LoopDetector(SETTINGS, occupancy_params(default_settings()))
    nodes = _nodes(drive)
    estimates = drive.truth.copy()
    j, k = 5, 80
    estimates[k] = estimates[j]
    found = detector.verify(nodes, estimates, j, k)
    assert isinstance(found, str)
    assert found


def test_a_keyframe_is_not_matched_on_its_own_scan(drive) -> None:  # type: ignore[no-untyped-def]
    """Keyframe k, scanned in another world, claimed at keyframe j's place with k within j's
    submap window (as after culled inserts ran the odometer past min_travel_m): its own scan
    is not in the submap, so it closes no loop against itself (it did, scoring 0.77)."""
    detector = LoopDetector(SETTINGS, occupancy_params(default_settings()))
    angles = np.arange(360) * (2 * np.pi / 360)
    elsewhere = static_scan(get_world("rooms").segments, Pose2D(12.5, 6.0, 0.3), angles, 12.0,
                            0.01, np.random.default_rng(1))
    nodes = [*_nodes(drive)[:6], ScanNode(8.0, elsewhere, np.zeros((0, 2)), IDENTITY)]
    estimates = np.vstack((drive.truth[:6], drive.truth[5]))
    k = len(nodes) - 1
    for j in (2, 5):  # windows 0..7 and 0..10 reach k
        found = detector.verify(nodes, estimates, j, k)
        assert isinstance(found, str), found


def test_submaps_are_cached_until_forgotten(drive) -> None:  # type: ignore[no-untyped-def]
    detector = LoopDetector(SETTINGS, occupancy_params(default_settings()))
    nodes = _nodes(drive)
    first = detector.submap(nodes, drive.truth, 10)
    assert detector.submap(nodes, drive.truth, 10) is first
    detector.forget_submaps()
    assert detector.submap(nodes, drive.truth, 10) is not first


def test_keyframes_are_drawn_as_the_front_end_inserts_them_bit_for_bit(drive) -> None:  # type: ignore[no-untyped-def]
    """A redraw (all keyframes in one pass) equals the front end's inserts one at a time:
    sensor mounts, no-return beams, returns beyond the map's range and NaN rows (dropped)
    included."""
    params = occupancy_params(default_settings())
    rng = np.random.default_rng(5)
    nodes = []
    for i, scan in enumerate(drive.scans[:40]):
        far = scan[:5] * (params.max_range_m + 1.0) / np.hypot(*scan[:5].T)[:, None]
        misses = np.vstack((scan[5:9] * 3.0, np.full((i % 2, 2), np.nan))) if i % 3 else None
        mount = Pose2D(0.1 * (i % 2), -0.05, 0.02 * i)
        points = np.vstack((scan, far, np.full((i % 2, 2), np.nan)))
        nodes.append(ScanNode(0.1 * i, points, np.zeros((0, 2)) if misses is None else misses,
                              mount))
    poses = drive.drifted[:40] + rng.normal(0.0, 0.01, (40, 3))
    one_at_a_time = MatchingMap(OccupancyGrid(params))
    for node, pose in zip(nodes, poses, strict=True):
        insert_scan(one_at_a_time, node.points, Pose2D.from_array(pose), node.no_return,
                    node.mount)
    rays = keyframe_rays(nodes, poses, params.max_range_m)
    for k, (node, pose) in enumerate(zip(nodes, poses, strict=True)):
        at = Pose2D.from_array(pose)
        reach = np.hypot(node.points[:, 0] - node.mount.x, node.points[:, 1] - node.mount.y)
        hits = rays.hits[rays.hit_starts[k]:rays.hit_starts[k + 1]]
        want = at.transform_points(node.points[reach <= params.max_range_m])
        assert hits.tobytes() == want.tobytes()
        finite = np.isfinite(node.no_return).all(axis=1)
        misses = rays.misses[rays.miss_starts[k]:rays.miss_starts[k + 1]]
        assert misses.tobytes() == at.transform_points(node.no_return[finite]).tobytes()
    drawn = draw_keyframes(nodes, poses, params).grid
    want = one_at_a_time.grid
    assert drawn.extent == want.extent and drawn.revision == want.revision
    assert drawn.log_odds.tobytes() == want.log_odds.tobytes()
    assert drawn.observed.tobytes() == want.observed.tobytes()
    assert drawn.hit_sums.tobytes() == want.hit_sums.tobytes()


def test_a_corridor_with_no_end_in_view_is_ambiguous() -> None:
    """In a corridor longer than the sensor's reach every shift along it scores alike: the
    search finds a distinct rival within ambiguity_ratio of the best, and no closure comes."""
    walls = get_world("corridor").segments
    angles = np.radians(np.arange(-180.0, 180.0, 1.0))
    truth = np.array([(x, 1.0, 0.0) for x in np.arange(14.0, 26.0, 0.4)])
    nodes = [
        ScanNode(0.1 * i, static_scan(walls, Pose2D.from_array(p), angles, 6.0, 0.01), np.zeros(
            (0, 2)), IDENTITY)
        for i, p in enumerate(truth)
    ]
    detector = LoopDetector(SETTINGS, occupancy_params(default_settings()))
    found = detector.verify(nodes, truth, 10, 20)
    assert isinstance(found, str) and found.startswith("ambiguous: a distinct pose scores"), found
