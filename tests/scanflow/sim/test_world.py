"""The built-in worlds: registry, walls, doors and free-space tours, by closed-form geometry."""

from __future__ import annotations

import math

import numpy as np
import pytest
from numpy.typing import NDArray
from scanflow.sim import WORLDS, get_world
from scanflow.sim.world import DOOR_WIDTH_M
from scipy.spatial import cKDTree


def _hits(origin: tuple[float, float], angles: NDArray[np.float64], segments: NDArray) -> NDArray:
    """Distance along each ray from `origin` to the nearest wall, inf when none: a plain loop
    over the walls solving origin + t d = a + u e by Cramer's rule."""
    out = np.full(angles.size, np.inf)
    ox, oy = origin
    for k, angle in enumerate(angles):
        dx, dy = math.cos(angle), math.sin(angle)
        for x0, y0, x1, y1 in segments.tolist():
            ex, ey = x1 - x0, y1 - y0
            det = ey * dx - ex * dy
            if abs(det) < 1e-12:
                continue
            wx, wy = x0 - ox, y0 - oy
            t = (wx * ey - wy * ex) / det
            u = (wx * dy - wy * dx) / det
            if t > 0 and 0.0 <= u <= 1.0:
                out[k] = min(out[k], t)
    return out


def _along(p: NDArray, q: NDArray, step_m: float = 0.01) -> NDArray[np.float64]:
    """Points every `step_m` (or closer) from p to q, both ends included."""
    count = max(2, math.ceil(float(np.hypot(*(q - p))) / step_m) + 1)
    return p + np.linspace(0.0, 1.0, count)[:, None] * (q - p)


def _leg_clearance(p: NDArray, q: NDArray, segments: NDArray) -> float:
    """Smallest distance between the straight leg p-q and any wall, both sampled every 1 cm
    (within 1 cm of the exact distance)."""
    walls = np.concatenate([_along(s[:2], s[2:]) for s in segments])
    return float(cKDTree(walls).query(_along(p, q))[0].min())


def test_unknown_world_names_the_choices():
    with pytest.raises(ValueError, match="world must be one of"):
        get_world("moon")


@pytest.mark.parametrize("name", ["rooms", "corridor", "loop", "campus"])
def test_each_registered_world_has_its_name_and_well_formed_walls_and_tour(name: str) -> None:
    world = get_world(name)
    assert world.name == name
    assert world.segments.dtype == np.float64 and world.segments.shape[1:] == (4,)
    assert world.waypoints.dtype == np.float64 and world.waypoints.shape[1:] == (2,)
    assert len(world.waypoints) >= 2
    lengths = np.hypot(*(world.segments[:, 2:] - world.segments[:, :2]).T)
    assert lengths.min() > 0.0  # no degenerate wall


def test_the_registry_holds_exactly_the_documented_worlds() -> None:
    assert sorted(WORLDS) == ["campus", "corridor", "loop", "rooms"]


@pytest.mark.parametrize("name", sorted(WORLDS))
def test_every_leg_of_the_closed_tour_stays_clear_of_the_walls(name: str) -> None:
    world = get_world(name)
    points = world.waypoints
    for p, q in zip(points, np.roll(points, -1, axis=0), strict=True):
        assert _leg_clearance(p, q, world.segments) > 0.3, (name, p, q)


@pytest.mark.parametrize(
    ("name", "box"),
    [("rooms", (0.0, 0.0, 15.0, 8.0)), ("corridor", (0.0, 0.0, 40.0, 2.0)),
     ("loop", (0.0, 0.0, 24.0, 16.0))],
)
def test_indoor_worlds_span_their_documented_outline(
    name: str, box: tuple[float, float, float, float]
) -> None:
    s = get_world(name).segments
    xs, ys = s[:, [0, 2]], s[:, [1, 3]]
    assert (xs.min(), ys.min(), xs.max(), ys.max()) == box


@pytest.mark.parametrize("name", ["corridor", "loop"])
def test_closed_worlds_return_every_ray_from_every_waypoint(name: str) -> None:
    world = get_world(name)
    angles = np.linspace(-math.pi, math.pi, 181, endpoint=False)
    for x, y in world.waypoints:
        assert np.isfinite(_hits((x, y), angles, world.segments)).all()


def test_rooms_leak_rays_only_through_the_open_east_door() -> None:
    world = get_world("rooms")
    angles = np.linspace(-math.pi, math.pi, 720, endpoint=False)
    escaped = 0
    for x, y in world.waypoints:
        missed = ~np.isfinite(_hits((x, y), angles, world.segments))
        for angle in angles[missed]:
            c, s = math.cos(angle), math.sin(angle)
            assert c > 0.0  # heading east
            y_at_wall = y + (15.0 - x) * s / c
            assert abs(y_at_wall - 2.0) <= DOOR_WIDTH_M / 2 + 1e-9
            escaped += 1
    assert escaped > 0  # the door really is open


def test_rooms_doors_are_door_width_wide_and_centred_as_documented() -> None:
    segments = get_world("rooms").segments
    east = np.array([0.0])
    # Just inside the east door's edges the rays leave; just outside they stop at the wall.
    for y, ahead in ((2.0, math.inf), (2.0 + 0.59, math.inf), (2.0 - 0.59, math.inf),
                     (2.0 + 0.61, 1.0), (2.0 - 0.61, 1.0)):
        assert _hits((14.0, y), east, segments)[0] == pytest.approx(ahead)
    # The inner wall at x = 5 m has doors at y = 2 m and 6 m, one between the lower rooms.
    assert _hits((4.0, 2.0), east, segments)[0] > 3.0
    assert _hits((4.0, 6.0), east, segments)[0] > 3.0
    assert _hits((4.0, 3.0), east, segments)[0] == pytest.approx(1.0)
