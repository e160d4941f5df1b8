"""Front end on a prior map: start found over the whole map, localise-only, a kidnapped robot;
`FrontendStart` reading the settings' map once."""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
import pytest
from numpy.typing import NDArray
from scanflow.config import FrontendSettings
from scanflow.frontend import Frontend, FrontendStatus, insert_scan
from scanflow.frontend.prior import FrontendStart, PriorMapError, load_prior_map
from scanflow.geometry import Pose2D
from scanflow.maps.export import save_map
from scanflow.maps.matching_map import MatchingMap
from scanflow.maps.occupancy import OccupancyGrid, OccupancyParams
from scanflow.sim import get_world

Scanner = Callable[[Pose2D], NDArray[np.float64]]
MAP_FROM_WORLD = Pose2D(0.41, -0.17, 0.35)  # walls off the cell lattice
# A pillar-flanked stretch of the middle rooms: unambiguous, unlike most of the alike rooms.
START = Pose2D(7.0, 2.6, 0.4)
KIDNAPPED_TO = Pose2D(11.6, 5.3, -2.0)


def prior_grid(scan_at: Scanner) -> OccupancyGrid:
    """The rooms world mapped from its waypoints at their true poses (map frame)."""
    world = MatchingMap(OccupancyGrid(OccupancyParams(resolution_m=0.05)))
    for x, y in get_world("rooms").waypoints:
        at = Pose2D(float(x), float(y), 0.0)
        insert_scan(world, scan_at(at), MAP_FROM_WORLD * at)
    return world.grid


def path_from(start: Pose2D, count: int) -> list[Pose2D]:
    return [start * Pose2D(0.05 * i, 0.0, math.radians(1.0) * i) for i in range(count)]


def near(estimate: Pose2D, world_pose: Pose2D, metres: float = 0.05) -> bool:
    error = estimate.relative_to(MAP_FROM_WORLD * world_pose)
    return error.translation_norm() < metres and abs(error.theta) < math.radians(1.0)


def test_without_a_start_the_first_scan_is_found_on_the_prior_map(
    settings: FrontendSettings, scan_at: Scanner
) -> None:
    frontend = Frontend(settings, grid=prior_grid(scan_at))
    truth = path_from(START, 6)
    outs = [frontend.process(scan_at(p), 0.1 * i, None, i) for i, p in enumerate(truth)]
    assert outs[0].status is FrontendStatus.LOCALISED, outs[0].message
    assert "whole-map search" in outs[0].message and outs[0].method == "global+gn"
    assert all(o.status is FrontendStatus.TRACKED for o in outs[1:])
    assert all(near(o.pose, p) for o, p in zip(outs, truth, strict=True))


def test_a_given_start_skips_the_search(settings: FrontendSettings, scan_at: Scanner) -> None:
    frontend = Frontend(settings, initial_pose=MAP_FROM_WORLD * START, grid=prior_grid(scan_at))
    out = frontend.process(scan_at(START), 0.0)
    assert out.status is FrontendStatus.TRACKED and near(out.pose, START)


def test_localise_only_leaves_the_prior_map_as_it_was(
    settings: FrontendSettings, scan_at: Scanner
) -> None:
    grid = prior_grid(scan_at)
    revision = grid.revision
    frontend = Frontend(settings.model_copy(update={"update_map": False}), grid=grid)
    path = path_from(START, 8)
    outs = [frontend.process(scan_at(p), 1.0 * i, None, i) for i, p in enumerate(path)]
    assert all(o.accepted and not o.inserted for o in outs)
    assert frontend.map.revision == revision
    mapping = Frontend(settings, grid=prior_grid(scan_at))
    assert any(mapping.process(scan_at(p), 1.0 * i).inserted for i, p in enumerate(path[:3]))
    with pytest.raises(ValueError, match="update_map"):
        Frontend(settings.model_copy(update={"update_map": False}))


def test_a_kidnapped_robot_is_found_again_after_n_rejections(
    settings: FrontendSettings, scan_at: Scanner
) -> None:
    grid = prior_grid(scan_at)
    # No local fallback search: it could latch on to a look-alike pose near the old one.
    kidnap = settings.model_copy(update={"global_after_rejections": 2, "fallback_method": ""})
    frontend = Frontend(kidnap, initial_pose=MAP_FROM_WORLD * START, grid=grid)
    for i, p in enumerate(path_from(START, 3)):
        assert frontend.process(scan_at(p), 0.1 * i, None, i).status is FrontendStatus.TRACKED
    # Carried off to another room with no odometry to tell: the local search fails twice.
    away = path_from(KIDNAPPED_TO, 4)
    outs = [frontend.process(scan_at(p), 1.0 + 0.1 * i, None, 3 + i) for i, p in enumerate(away)]
    assert [o.status for o in outs[:2]] == [FrontendStatus.REJECTED] * 2
    assert outs[2].status is FrontendStatus.LOCALISED and near(outs[2].pose, away[2])
    assert outs[3].status is FrontendStatus.TRACKED and near(outs[3].pose, away[3])
    # Lost for good (a map of elsewhere): a search every second rejection, not on every scan.
    lost = Frontend(kidnap, initial_pose=MAP_FROM_WORLD * START, grid=prior_grid(scan_at))
    far_away = [np.column_stack((np.full(40, 30.0), np.linspace(-5.0, 5.0, 40)))] * 6
    outs = [lost.process(points, 0.1 * i, None, i) for i, points in enumerate(far_away)]
    searched = ["whole-map search" in o.message for o in outs]
    assert searched == [False, False, True, False, True, False]
    assert all(o.status is FrontendStatus.REJECTED for o in outs)
    # Without the setting it stays lost.
    never = kidnap.model_copy(update={"global_after_rejections": 0})
    stays = Frontend(never, initial_pose=MAP_FROM_WORLD * START, grid=prior_grid(scan_at))
    stays.process(scan_at(START), 0.0)
    lost = [stays.process(scan_at(p), 1.0 + 0.1 * i, None, 1 + i) for i, p in enumerate(away)]
    assert all(o.status is FrontendStatus.REJECTED for o in lost)


def test_frontend_start_reads_the_prior_map_once_and_hands_out_copies(
    tmp_path, settings: FrontendSettings, scan_at: Scanner
) -> None:
    grid = prior_grid(scan_at)
    path = save_map(grid, tmp_path / "office.npz")
    given = settings.model_copy(update={"prior_map": str(path), "initial_pose": [1.0, 2.0, 90.0]})
    start = FrontendStart(given)
    path.unlink()  # read at start-up: later robots do not need the file
    first, second = start.grid(), start.grid()
    assert start.pose == Pose2D(1.0, 2.0, math.pi / 2)
    np.testing.assert_array_equal(first.log_odds, grid.log_odds)
    assert first is not second and not np.shares_memory(first.log_odds, second.log_odds)
    none = FrontendStart(settings)
    assert none.pose is None and none.grid() is None
    yaml = save_map(grid, tmp_path / "office.yaml")  # the map_server form loads too
    assert load_prior_map(settings.model_copy(update={"prior_map": str(yaml)})) is not None


@pytest.mark.parametrize(
    ("content", "named"),
    [(None, "no file"), (b"not a map", "prior_map"), ("empty", "no occupied cell")],
)
def test_a_bad_prior_map_is_named(tmp_path, settings: FrontendSettings, content, named) -> None:
    path = tmp_path / "bad.npz"
    if content == "empty":
        save_map(OccupancyGrid(OccupancyParams()), path)
    elif content is not None:
        path.write_bytes(content)
    with pytest.raises(PriorMapError, match=named):
        load_prior_map(settings.model_copy(update={"prior_map": str(path)}))


def test_an_operators_pose_replaces_the_search_and_puts_a_lost_robot_back(
    settings: FrontendSettings, scan_at: Scanner
) -> None:
    frontend = Frontend(settings, grid=prior_grid(scan_at))
    frontend.set_pose(MAP_FROM_WORLD * START)  # before the first scan: the start
    first = frontend.process(scan_at(START), 0.0)
    assert first.status is FrontendStatus.TRACKED and near(first.pose, START)
    # Carried off, no search, no fallback: lost, until told where it is.
    stay_lost = settings.model_copy(update={"global_after_rejections": 0, "fallback_method": ""})
    lost = Frontend(stay_lost, initial_pose=MAP_FROM_WORLD * START, grid=prior_grid(scan_at))
    lost.process(scan_at(START), 0.0)
    away = path_from(KIDNAPPED_TO, 3)
    assert lost.process(scan_at(away[0]), 1.0).status is FrontendStatus.REJECTED
    lost.set_pose(MAP_FROM_WORLD * away[0] * Pose2D(0.15, -0.1, 0.05))  # roughly there
    back = lost.process(scan_at(away[1]), 1.1)
    assert back.status is FrontendStatus.TRACKED and near(back.pose, away[1])
    assert back.prediction_source == "hold"  # the decreed pose, not a velocity from the jump
    with pytest.raises(ValueError, match="finite"):
        lost.set_pose(Pose2D(math.inf, 0.0, 0.0))


def _over_the_caps_below(level_that_fits: int, monkeypatch: pytest.MonkeyPatch) -> list[int]:
    """The whole-map search refuses levels finer than `level_that_fits`, as it does a map
    too large for them (its caps); returns the levels tried."""
    from scanflow.frontend import tracker
    from scanflow.matching import MatchInputError

    tried: list[int] = []
    real = tracker.localise_globally

    def search(points, target, *, level: int, **options):
        tried.append(level)
        if level < level_that_fits:
            raise MatchInputError(f"a search of 2e9 candidates at level {level} is over the cap")
        return real(points, target, level=level, **options)

    monkeypatch.setattr(tracker, "localise_globally", search)
    return tried


@pytest.mark.parametrize(("fits_at", "tried"), [(2, [1, 2]), (99, [1, 2, 3, 4])])
def test_a_map_too_large_for_the_search_level_is_searched_coarser_or_the_scan_rejected(
    settings: FrontendSettings, scan_at: Scanner, monkeypatch: pytest.MonkeyPatch,
    fits_at: int, tried: list[int],
) -> None:
    levels = _over_the_caps_below(fits_at, monkeypatch)
    out = Frontend(settings, grid=prior_grid(scan_at)).process(scan_at(START), 0.0)
    assert levels == tried
    if fits_at <= 4:
        assert out.status is FrontendStatus.LOCALISED and near(out.pose, START)
    else:
        assert out.status is FrontendStatus.REJECTED
        assert "too large even at level 4" in out.message and "over the cap" in out.message
