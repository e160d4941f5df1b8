"""Whole-map search: found anywhere with no guess, ambiguity reported, bad input named."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scanflow.frontend import insert_scan
from scanflow.geometry import Pose2D
from scanflow.maps.matching_map import MatchingMap
from scanflow.maps.occupancy import OccupancyGrid, OccupancyParams
from scanflow.matching import MatchInputError, MatchStatus, available_methods, match
from scanflow.matching.global_search import localise_globally
from scanflow.sim import get_world, static_scan

# Map frame turned against the world, so walls do not lie along cell boundaries.
MAP_FROM_WORLD = Pose2D(0.37, -0.21, 0.4)


def cast(
    segments: np.ndarray, pose: Pose2D, noise_m: float = 0.0, seed: int = 0, beams: int = 360
) -> np.ndarray:
    """Endpoints (robot frame) of a full-circle scan from `pose` (world), 12 m range."""
    angles = np.arange(beams) * (2 * math.pi / beams)
    return static_scan(segments, pose, angles, 12.0, noise_m, np.random.default_rng(seed))


def mapped(segments: np.ndarray, poses: list[Pose2D]) -> MatchingMap:
    """A 5 cm map of `segments` from full-circle scans taken at `poses` (world frame)."""
    world = MatchingMap(OccupancyGrid(OccupancyParams(resolution_m=0.05)))
    for pose in poses:
        insert_scan(world, cast(segments, pose), MAP_FROM_WORLD * pose)
    return world


@pytest.fixture(scope="module")
def rooms_map() -> MatchingMap:
    stops = [Pose2D(float(x), float(y), 0.0) for x, y in get_world("rooms").waypoints]
    return mapped(get_world("rooms").segments, stops)


def random_pose_near(waypoints: np.ndarray, rng: np.random.Generator) -> Pose2D:
    x, y = waypoints[rng.integers(len(waypoints))] + rng.uniform(-1.0, 1.0, 2)
    return Pose2D(float(x), float(y), float(rng.uniform(-math.pi, math.pi)))


def is_near(estimate: Pose2D, truth: Pose2D) -> bool:
    error = estimate.relative_to(MAP_FROM_WORLD * truth)
    return error.translation_norm() < 0.05 and abs(error.theta) < math.radians(1.0)


@pytest.mark.parametrize("seed", range(4))
def test_a_scan_anywhere_in_an_asymmetric_room_is_found_without_a_guess(room, seed):
    world = mapped(room, [Pose2D(0.0, 0.0, 0.0), Pose2D(-2.5, -1.5, 0.0), Pose2D(2.5, 2.0, 0.0)])
    rng = np.random.default_rng(seed)
    truth = Pose2D(float(rng.uniform(-3.0, 0.5)), float(rng.uniform(-0.8, 2.5)),
                   float(rng.uniform(-math.pi, math.pi)))
    found = localise_globally(cast(room, truth, noise_m=0.01, seed=seed), world)
    assert found.status is MatchStatus.OK, found.message
    assert is_near(found.pose, truth)
    assert found.method == "global+gn" and found.time_s > 0
    assert found.extra["candidates"][0] == found.pose


@pytest.mark.parametrize("seed", range(8))
def test_in_six_alike_rooms_it_is_right_or_says_ambiguous_never_silently_wrong(rooms_map, seed):
    rng = np.random.default_rng(seed)
    truth = random_pose_near(get_world("rooms").waypoints, rng)
    found = localise_globally(cast(get_world("rooms").segments, truth, 0.01, seed), rooms_map)
    if found.ok:
        assert is_near(found.pose, truth)
    else:  # the true pose is among the rivals it names
        assert found.status is MatchStatus.AMBIGUOUS, found.message
        assert any(is_near(pose, truth) for pose in found.extra["candidates"])


def test_a_symmetric_room_is_ambiguous_not_a_silent_guess():
    # A bare 6 m x 4 m box looks the same turned by 180 degrees about its centre.
    box = np.array([[0, 0, 6, 0], [6, 0, 6, 4], [6, 4, 0, 4], [0, 4, 0, 0]], dtype=np.float64)
    world = mapped(box, [Pose2D(3.0, 2.0, 0.0), Pose2D(1.5, 1.0, 0.0), Pose2D(4.5, 3.0, 0.0)])
    scan = cast(box, Pose2D(2.0, 1.5, 0.3))
    found = localise_globally(scan, world)
    assert found.status is MatchStatus.AMBIGUOUS and not found.ok
    assert "ambiguous" in found.message
    first, second = found.extra["candidates"][:2]
    centre = MAP_FROM_WORLD * Pose2D(3.0, 2.0, 0.0)
    # The two answers are each other's half-turn about the box's centre.
    half_turn = centre * Pose2D(0.0, 0.0, math.pi) * centre.inverse()
    gap = (half_turn * first).relative_to(second)
    assert gap.translation_norm() < 0.1 and abs(gap.theta) < math.radians(2.0)


def test_with_a_strict_enough_bar_the_same_room_is_not_ambiguous():
    box = np.array([[0, 0, 6, 0], [6, 0, 6, 4], [6, 4, 0, 4], [0, 4, 0, 0]], dtype=np.float64)
    world = mapped(box, [Pose2D(3.0, 2.0, 0.0)])
    found = localise_globally(cast(box, Pose2D(2.0, 1.5, 0.3)), world, candidates=1)
    assert found.status is MatchStatus.OK  # one candidate: no rival to compare with


def pillar(x: float, y: float, half_m: float = 0.2) -> list[tuple[float, float, float, float]]:
    """The four walls of a square pillar centred on (x, y)."""
    c = [(x - half_m, y - half_m), (x + half_m, y - half_m), (x + half_m, y + half_m),
         (x - half_m, y + half_m)]
    return [(*c[i], *c[(i + 1) % 4]) for i in range(4)]


def test_a_rival_that_did_not_refine_but_scores_as_high_in_the_search_is_ambiguous():
    """Two pillars 8 m apart, a short-range lidar (Hokuyo URG-04LX: 682 beams over 240 deg,
    5.6 m) between them: the scan is two small corners, and a half turn about the pillars'
    midpoint nearly swaps them. The true pose is the search's best optimum but refines
    ill_conditioned; the half turn refines OK, so it was returned OK, 180 deg off, with no
    rival (the simulator's campus, BENCHMARKS.md "Short-range lidars outdoors")."""
    pillars = np.array(pillar(-4.0, 0.0) + pillar(4.0, 0.0), dtype=np.float64)
    angles = np.linspace(-math.radians(120.0), math.radians(120.0), 682)
    world = MatchingMap(OccupancyGrid(OccupancyParams(resolution_m=0.05)))
    start, truth = Pose2D(1.0, 2.75, -math.pi / 2), Pose2D(1.0, 0.8, -math.pi / 2)
    insert_scan(world, static_scan(pillars, start, angles, 5.6), MAP_FROM_WORLD * start)
    found = localise_globally(static_scan(pillars, truth, angles, 5.6), world)
    assert found.status is MatchStatus.AMBIGUOUS and not found.ok, found.message
    assert "did not refine" in found.message
    # The winner is the half turn; the true pose is the search's best, named with its status.
    error = found.pose.relative_to(MAP_FROM_WORLD * truth)
    assert abs(abs(error.theta) - math.pi) < math.radians(5.0)
    assert found.extra["candidates"] == [found.pose]
    coarse, statuses = found.extra["coarse_candidates"], found.extra["coarse_statuses"]
    scores = found.extra["coarse_scores"]
    assert len(coarse) == len(statuses) == len(scores) and scores == sorted(scores, reverse=True)
    near = coarse[0].relative_to(MAP_FROM_WORLD * truth)
    assert near.translation_norm() < 0.2 and abs(near.theta) < math.radians(3.0)
    assert statuses[0] is MatchStatus.ILL_CONDITIONED


def test_bad_input_gets_a_status_or_a_named_error(rooms_map):
    empty = MatchingMap(OccupancyGrid(OccupancyParams()))
    scan = cast(get_world("rooms").segments, Pose2D(2.5, 2.0, 0.0))
    assert localise_globally(scan, empty).status is MatchStatus.EMPTY_MAP
    assert localise_globally(scan[:2], rooms_map).status is MatchStatus.TOO_FEW_POINTS
    with pytest.raises(MatchInputError, match="ambiguity_ratio"):
        localise_globally(scan, rooms_map, ambiguity_ratio=1.5)
    with pytest.raises(MatchInputError, match="level"):
        localise_globally(scan, rooms_map, level=-1)
    with pytest.raises(MatchInputError, match="candidates"):  # used to hang
        localise_globally(scan, rooms_map, candidates=10**7)
    with pytest.raises(MatchInputError, match="suppress_m"):  # used to raise OverflowError
        localise_globally(scan, rooms_map, suppress_m=math.inf)
    with pytest.raises(MatchInputError, match="suppress_m must be <= 1000"):  # numba's error
        localise_globally(scan, rooms_map, suppress_m=1e300)


@pytest.mark.parametrize(
    ("option", "value"),
    [
        ("level", -1),  # a plain ValueError
        ("level", 64),  # numba's TypingError from the map's pyramid
        ("level", 1100),  # OverflowError
        ("level", 40),  # ran for minutes
        ("candidates", 0),
        ("ambiguity_ratio", 0.0),
        ("ambiguity_ratio", 1.5),
    ],
)
def test_an_option_out_of_its_range_is_a_match_input_error_naming_it(rooms_map, option, value):
    """Through `match`, as docs/matching.md promises: never an error from deep inside, nor a hang
    (a pyramid level at most MAX_LEVELS - 1, as gn's and lm's `levels`)."""
    scan = cast(get_world("rooms").segments, Pose2D(2.5, 2.0, 0.0))
    with pytest.raises(MatchInputError, match=rf"^option {option} must be"):
        match(scan, rooms_map, method="global", **{option: value})


def test_a_far_source_or_a_glitch_point_keeps_the_search_bounded(rooms_map):
    """Coordinates ~1e6 m used to ask for 230 GiB of angles; one return at 20 km for ~400k."""
    scan = cast(get_world("rooms").segments, Pose2D(2.5, 2.0, 0.0))
    assert localise_globally(scan + 1e6, rooms_map).status is MatchStatus.NO_OVERLAP
    found = localise_globally(np.vstack([scan, [[2e4, 0.0]]]), rooms_map)
    assert is_near(found.pose, Pose2D(2.5, 2.0, 0.0))


def test_match_runs_the_search_by_name_and_refuses_a_point_target(room):
    world = mapped(room, [Pose2D(0.0, 0.0, 0.0)])
    truth = Pose2D(-1.0, 1.2, 2.0)
    scan = cast(room, truth)
    found = match(scan, world, Pose2D(3.0, -2.0, -1.0), method="global")  # the guess is unused
    assert found.ok and is_near(found.pose, truth) and found.method == "global+gn"
    assert "global" in available_methods()
    with pytest.raises(MatchInputError, match="must be a MatchingMap"):
        match(scan, scan, method="global")
