"""Grid-map benchmark: scan insert time, incremental view refresh vs full rebuild, memory.

A simulated 40 m x 40 m building (4 x 4 rooms of 10 m with 1.2 m doors) is mapped at 5 cm by
a robot driving a serpentine through every row of rooms with a 360-beam, 10 m lidar, one scan
every 0.25 m; then it drives the same path again over the mapped area (steady state).

    python -m bench.maps [--json] [--step-m 0.25] [--rebuilds 5]
"""

from __future__ import annotations

import argparse
import itertools
import json
import math
import resource
import time
from collections.abc import Callable, Iterator

import numpy as np
from numpy.typing import NDArray
from scanflow.maps.field import LikelihoodField
from scanflow.maps.matching_map import MatchingMap
from scanflow.maps.occupancy import OccupancyGrid, OccupancyParams
from scanflow.sim import cast_rays

SIDE_M = 40.0
ROOM_M = 10.0
DOOR_M = 1.2
BEAMS = 360
RANGE_MAX_M = 10.0
RANGE_NOISE_M = 0.01
PYRAMID_LEVELS = 3


def building_walls() -> NDArray[np.float64]:
    """(M, 4) wall segments: outer box plus inner walls every 10 m, a door mid-way per room."""
    doors = np.arange(ROOM_M / 2, SIDE_M, ROOM_M)
    cuts = np.concatenate(
        ([0.0], np.repeat(doors, 2) + np.tile([-DOOR_M, DOOR_M], len(doors)) / 2, [SIDE_M])
    )
    spans = cuts.reshape(-1, 2)
    walls = []
    for at in np.arange(ROOM_M, SIDE_M, ROOM_M):
        walls += [(at, a, at, b) for a, b in spans] + [(a, at, b, at) for a, b in spans]
    walls += [
        (0, 0, SIDE_M, 0),
        (SIDE_M, 0, SIDE_M, SIDE_M),
        (SIDE_M, SIDE_M, 0, SIDE_M),
        (0, SIDE_M, 0, 0),
    ]
    return np.array(walls, dtype=np.float64)


def serpentine(step_m: float) -> Iterator[tuple[float, float, float]]:
    """Poses (x, y, heading) every step_m along the room rows, turning through the doors."""
    lo, hi = ROOM_M / 2, SIDE_M - ROOM_M / 2
    corners = []
    for i, y in enumerate(np.arange(lo, SIDE_M, ROOM_M)):
        corners += [(lo, y), (hi, y)] if i % 2 == 0 else [(hi, y), (lo, y)]
    for (x0, y0), (x1, y1) in itertools.pairwise(corners):
        length = math.hypot(x1 - x0, y1 - y0)
        heading = math.atan2(y1 - y0, x1 - x0)
        for s in np.arange(0.0, length, step_m):
            yield x0 + s * math.cos(heading), y0 + s * math.sin(heading), heading


def scan_at(
    pose: tuple[float, float, float], walls: NDArray[np.float64], rng: np.random.Generator
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """World endpoints of returns, no-return beam ends, and the sensor origin for one pose."""
    x, y, heading = pose
    angles = heading + np.linspace(-math.pi, math.pi, BEAMS, endpoint=False)
    origin = np.array([x, y])
    ranges = cast_rays(np.tile(origin, (BEAMS, 1)), angles, walls, RANGE_MAX_M)
    ranges = ranges + rng.normal(0.0, RANGE_NOISE_M, BEAMS)
    hit = np.isfinite(ranges)
    directions = np.column_stack((np.cos(angles), np.sin(angles)))
    hits = origin + directions[hit] * ranges[hit, None]
    misses = origin + directions[~hit] * RANGE_MAX_M
    return hits, misses, origin


def timed(fn: Callable[[], object]) -> float:
    start = time.perf_counter()
    fn()
    return time.perf_counter() - start


def summary_ms(samples_s: list[float]) -> dict[str, float]:
    ms = np.array(samples_s) * 1e3
    return {
        "mean": round(float(ms.mean()), 3),
        "p50": round(float(np.percentile(ms, 50)), 3),
        "p95": round(float(np.percentile(ms, 95)), 3),
        "max": round(float(ms.max()), 3),
    }


def run(step_m: float, rebuilds: int) -> dict[str, object]:
    rng = np.random.default_rng(0)
    walls = building_walls()
    scans = [scan_at(pose, walls, rng) for pose in serpentine(step_m)]
    warm_up = MatchingMap()  # JIT-load the ray marker outside the timings
    warm_up.update(*scans[0][:1], scans[0][2], scans[0][1])
    warm_up.likelihood_pyramid(PYRAMID_LEVELS)
    world = MatchingMap(OccupancyGrid(OccupancyParams(resolution_m=0.05)))
    world.likelihood_pyramid(PYRAMID_LEVELS)  # views exist from the start, as in a front end

    phases: dict[str, dict[str, object]] = {}
    for phase in ("mapping", "revisit"):
        insert_s, field0_s, pyramid_s, changed = [], [], [], 0
        for hits, misses, origin in scans:
            result = None

            def insert(h=hits, m=misses, o=origin) -> None:
                nonlocal result
                result = world.update(h, o, m)

            insert_s.append(timed(insert))
            changed += result is not None and result.occupied_changed is not None
            field0_s.append(timed(lambda: world.likelihood_field(0)))
            coarser_s = timed(lambda: world.likelihood_pyramid(PYRAMID_LEVELS))
            pyramid_s.append(field0_s[-1] + coarser_s)
        phases[phase] = {
            "scans": len(scans),
            "insert_ms": summary_ms(insert_s),
            "field0_refresh_ms": summary_ms(field0_s),
            "pyramid_refresh_ms": summary_ms(pyramid_s),
            "scans_flipping_occupancy": changed,
            "storage_generation": world.grid.storage_generation,
            "map_bytes": world.nbytes,
        }

    grid = world.grid
    spec, occupied = grid.spec, grid.occupied_mask()

    def rebuild_field0() -> None:
        LikelihoodField.from_occupied(spec, occupied, world.sigma_m, 4.0 * world.sigma_m)

    rebuild_field_s = [timed(rebuild_field0) for _ in range(rebuilds)]
    rebuild_pyramid_s = [
        timed(lambda: MatchingMap(grid).likelihood_pyramid(PYRAMID_LEVELS)) for _ in range(rebuilds)
    ]
    area_m2 = spec.width_m * spec.height_m
    return {
        "world": f"{SIDE_M:g} m x {SIDE_M:g} m, {BEAMS} beams, {RANGE_MAX_M:g} m range",
        "resolution_m": grid.resolution_m,
        "step_m": step_m,
        "extent_cells": [spec.rows, spec.cols],
        "mapped_area_m2": round(area_m2, 1),
        "phases": phases,
        "full_rebuild_field0_ms": summary_ms(rebuild_field_s),
        "full_rebuild_pyramid_ms": summary_ms(rebuild_pyramid_s),
        "storage_cells": list(grid.storage_box.shape) if grid.storage_box else [0, 0],
        "grid_bytes": grid.nbytes,
        "grid_bytes_per_m2": round(grid.nbytes / area_m2, 1),
        "map_and_views_bytes": world.nbytes,
        "map_and_views_bytes_per_m2": round(world.nbytes / area_m2, 1),
        "peak_rss_mb": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1),
    }


def print_table(r: dict[str, object]) -> None:
    print(f"{r['world']}, {r['resolution_m']} m cells, one scan every {r['step_m']} m")
    print(
        f"extent {r['extent_cells']} cells = {r['mapped_area_m2']} m^2, "
        f"storage {r['storage_cells']} cells"
    )
    for name, p in r["phases"].items():  # type: ignore[union-attr]
        ins, f0, pyr = p["insert_ms"], p["field0_refresh_ms"], p["pyramid_refresh_ms"]
        print(
            f"{name:8s} {p['scans']} scans ({p['scans_flipping_occupancy']} flipped occupancy, "
            f"map {p['map_bytes'] / 1e6:.1f} MB)\n"
            f"  insert mean {ins['mean']} ms p95 {ins['p95']} max {ins['max']}\n"
            f"  field refresh mean {f0['mean']} ms p95 {f0['p95']} max {f0['max']}\n"
            f"  {PYRAMID_LEVELS}-level pyramid refresh mean {pyr['mean']} ms p95 {pyr['p95']} "
            f"max {pyr['max']}"
        )
    print(
        f"full rebuild: field level 0 over the extent {r['full_rebuild_field0_ms']['mean']} ms, "
        f"{PYRAMID_LEVELS}-level pyramid {r['full_rebuild_pyramid_ms']['mean']} ms"
    )
    print(
        f"memory: grid {r['grid_bytes'] / 1e6:.2f} MB ({r['grid_bytes_per_m2']} B/m^2), "
        f"grid + views {r['map_and_views_bytes'] / 1e6:.2f} MB "
        f"({r['map_and_views_bytes_per_m2']} B/m^2), peak RSS {r['peak_rss_mb']} MB"
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--json", action="store_true", help="print one JSON object")
    parser.add_argument("--step-m", type=float, default=0.25, help="distance between scans")
    parser.add_argument("--rebuilds", type=int, default=5, help="full rebuilds to time")
    args = parser.parse_args()
    result = run(args.step_m, args.rebuilds)
    if args.json:
        print(json.dumps(result, indent=2))
    else:
        print_table(result)


if __name__ == "__main__":
    main()
