import numpy as np
import pytest
from scanflow.geometry import Pose2D
from scanflow.maps.matching_map import MatchingMap
from scanflow.maps.occupancy import OccupancyGrid
from scanflow.matching.map_free_space import map_free_space_test


@pytest.fixture
def grid(room, caster) -> OccupancyGrid:
    """The room seen from its middle, several times (its free cells confidently free)."""
    world = MatchingMap()
    for _ in range(4):
        world.update(caster(room, Pose2D()), (0.0, 0.0))
    return world.grid


def test_the_walls_do_not_conflict_and_points_in_the_room_do(grid, room, caster) -> None:
    walls = caster(room, Pose2D())
    assert map_free_space_test(walls, grid, 0.2).share == 0.0
    inside = map_free_space_test(0.5 * walls, grid, 0.2)  # halfway to the walls: seen free
    assert inside.tested > 0.9 * len(walls) and inside.share > 0.9


def test_points_off_the_map_or_within_the_margin_are_not_conflicts(grid, room, caster) -> None:
    walls = caster(room, Pose2D())
    assert map_free_space_test(walls + 100.0, grid, 0.2).tested == 0
    unit = walls / np.linalg.norm(walls, axis=1, keepdims=True)
    assert map_free_space_test(walls - 0.15 * unit, grid, 0.2).conflicts == 0


def test_an_empty_map_tests_nothing_and_a_negative_margin_is_refused() -> None:
    assert map_free_space_test(np.ones((3, 2)), OccupancyGrid(), 0.2).tested == 0
    with pytest.raises(ValueError, match=r"margin_m must be >= 0, got -1"):
        map_free_space_test(np.ones((3, 2)), OccupancyGrid(), -1.0)
