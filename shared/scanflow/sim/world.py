"""The built-in 2D worlds: walls as line segments plus a collision-free tour of waypoints.

- `rooms`: six rooms (5 m x 4 m) joined by 1.2 m doors, a few pillars, and an open door to
  the outside in the east wall: beams through it hit nothing (no return, as in open space);
- `corridor`: a long featureless 40 m x 2 m corridor, the degenerate case for matching;
- `loop`: corridors around a central block, with alcoves, for loop closure;
- `campus`: outdoors, a lawn with a pavilion and rows of trees among buildings 15-70 m away,
  with streets between them where beams find nothing: far, sparse returns (a lidar of 1 deg
  steps samples a wall 30 m away every 0.5 m), thin posts and much open sky, the case indoor
  tuning misses (run it with a longer range than `SimConfig`'s 30 m, e.g. 80 m).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

DOOR_WIDTH_M = 1.2


@dataclass(frozen=True, eq=False)
class World:
    """Walls (M, 4) as rows (x0, y0, x1, y1) and a closed tour of free-space waypoints (K, 2)."""

    name: str
    segments: NDArray[np.float64]
    waypoints: NDArray[np.float64]


def _box(x0: float, y0: float, x1: float, y1: float) -> list[tuple[float, float, float, float]]:
    return [(x0, y0, x1, y0), (x1, y0, x1, y1), (x1, y1, x0, y1), (x0, y1, x0, y0)]


def _wall_with_doors(
    start: tuple[float, float], end: tuple[float, float], door_centers: list[float]
) -> list[tuple[float, float, float, float]]:
    """An axis-aligned wall from start to end, cut by doors at distances along it."""
    (x0, y0), (x1, y1) = start, end
    length = float(np.hypot(x1 - x0, y1 - y0))
    ux, uy = (x1 - x0) / length, (y1 - y0) / length
    cuts = [0.0]
    for c in sorted(door_centers):
        cuts += [c - DOOR_WIDTH_M / 2, c + DOOR_WIDTH_M / 2]
    cuts.append(length)
    return [
        (x0 + ux * a, y0 + uy * a, x0 + ux * b, y0 + uy * b)
        for a, b in zip(cuts[::2], cuts[1::2], strict=True)
    ]


def rooms() -> World:
    """Six 5 m x 4 m rooms joined by doors, with pillars and an open door out in the east wall."""
    walls = [(0.0, 0.0, 15.0, 0.0), (15.0, 8.0, 0.0, 8.0), (0.0, 8.0, 0.0, 0.0)]
    walls += _wall_with_doors((15.0, 0.0), (15.0, 8.0), [2.0])
    walls += _wall_with_doors((5.0, 0.0), (5.0, 8.0), [2.0, 6.0])
    walls += _wall_with_doors((10.0, 0.0), (10.0, 8.0), [2.0, 6.0])
    walls += _wall_with_doors((0.0, 4.0), (15.0, 4.0), [2.5, 12.5])
    for cx, cy in ((0.8, 7.2), (7.5, 3.3), (14.2, 0.8), (7.5, 7.3), (11.0, 4.7)):
        walls += _box(cx - 0.2, cy - 0.2, cx + 0.2, cy + 0.2)
    tour = [(2.5, 2.0), (7.5, 2.0), (12.5, 2.0), (12.5, 6.0), (7.5, 6.0), (2.5, 6.0)]
    return World("rooms", np.array(walls, dtype=np.float64), np.array(tour, dtype=np.float64))


def corridor() -> World:
    """A featureless 40 m x 2 m corridor, toured end to end: the degenerate case for matching."""
    walls = _box(0.0, 0.0, 40.0, 2.0)
    tour = [(2.0, 1.0), (38.0, 1.0)]
    return World("corridor", np.array(walls, dtype=np.float64), np.array(tour, dtype=np.float64))


def loop() -> World:
    """Corridors around a central block, with alcoves, toured around the block for loop closure."""
    walls = _box(0.0, 0.0, 24.0, 16.0) + _box(4.0, 3.0, 20.0, 13.0)
    for x in (7.0, 15.0):
        walls += [(x, 0.0, x, 0.6), (x + 1.0, 0.0, x + 1.0, 0.6)]
        walls += [(x, 16.0, x, 15.4), (x + 1.0, 16.0, x + 1.0, 15.4)]
    walls += _box(0.0, 7.5, 0.5, 8.5) + _box(23.5, 6.0, 24.0, 7.0)
    tour = [(2.0, 1.5), (22.0, 1.5), (22.0, 14.5), (2.0, 14.5)]
    return World("loop", np.array(walls, dtype=np.float64), np.array(tour, dtype=np.float64))


def campus() -> World:
    """Outdoors: buildings 15-70 m away, rows of trees and open streets (far, sparse returns)."""
    buildings = [
        (0.0, 70.0, 45.0, 85.0), (55.0, 72.0, 110.0, 82.0), (95.0, 60.0, 110.0, 72.0),
        (-20.0, 10.0, -5.0, 60.0), (120.0, 5.0, 135.0, 40.0), (10.0, -25.0, 40.0, -10.0),
        (60.0, -30.0, 95.0, -12.0), (45.0, 30.0, 52.0, 36.0),
    ]
    walls = [side for b in buildings for side in _box(*b)]
    trees = [(x, y) for y in (20.0, 45.0) for x in np.arange(10.0, 91.0, 8.0)]
    trees += [(5.0, y) for y in np.arange(5.0, 61.0, 9.0)]
    trees += [(100.0, 20.0), (104.0, 31.0), (30.0, 62.0), (70.0, 63.0)]
    for x, y in trees:
        walls += _box(x - 0.2, y - 0.2, x + 0.2, y + 0.2)
    tour = [(15.0, 10.0), (85.0, 10.0), (85.0, 55.0), (15.0, 55.0)]
    return World("campus", np.array(walls, dtype=np.float64), np.array(tour, dtype=np.float64))


WORLDS: dict[str, Callable[[], World]] = {
    "rooms": rooms, "corridor": corridor, "loop": loop, "campus": campus,
}


def get_world(name: str) -> World:
    """The world registered under `name`."""
    if name not in WORLDS:
        raise ValueError(f"world must be one of {sorted(WORLDS)}, got {name!r}")
    return WORLDS[name]()
