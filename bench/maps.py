"""Grid-map benchmark: scan insert time, incremental view refresh vs full rebuild, memory.

A simulated 40 m x 40 m building (4 x 4 rooms of 10 m with 1.2 m doors) is mapped at 5 cm by
a robot driving a serpentine through every row of rooms with a 360-beam, 10 m lidar, one scan
every 0.25 m; then it drives the same path again over the mapped area (steady state).

With --data LOG, also the insert time of every keyframe at its corrected pose, one at a time
as a front end inserts them, and what redrawing all of them costs the back end after a loop
closure (`draw_keyframes`, one pass; median of --rebuilds), and the matching views that gn,
csm and NDT read, on that map: the per-scan refresh of the level-0 likelihood field,
of the 3-level pyramid, of the max-pool stack, of the NDT cells and of the overlapping NDT
cells the ndt matcher reads (its three cell sizes) while the map is small (after --small-scans
scans) and at the end, each next to the full rebuild it replaces. The refresh should not grow
with the map; the rebuild does. --tile-cells sets the side of the tiles the fields track
changes by (default: the library's).

    python -m bench.maps [--json] [--step-m 0.25] [--rebuilds 5]
    python -m bench.maps --data ../shared/data/intel-corrected.log.gz --views-only [--json]
"""

from __future__ import annotations

import argparse
import itertools
import json
import math
import resource
import time
from collections.abc import Callable, Iterator, Mapping
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scanflow.backend.loops import ScanNode, draw_keyframes
from scanflow.io.carmen import load_keyframes
from scanflow.maps.field import LikelihoodField
from scanflow.maps.matching_map import MatchingMap
from scanflow.maps.maxpool import MaxPoolStack
from scanflow.maps.ndt_cells import NDTCells, OverlappingCells
from scanflow.maps.occupancy import OccupancyGrid, OccupancyParams
from scanflow.sim import cast_rays

SIDE_M = 40.0
ROOM_M = 10.0
DOOR_M = 1.2
BEAMS = 360
RANGE_MAX_M = 10.0
RANGE_NOISE_M = 0.01
PYRAMID_LEVELS = 3
STACK_DEPTH = 4  # csm's stack at the front end's +-1 m fallback window on 5 cm cells
NDT_CELL_M = 0.5  # the ndt matcher's finest cell size
NDT_SIZES_M = (2.0, 1.0, 0.5)  # the overlapping cells of its three levels


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
    """Wall time of one call of `fn`, in s."""
    start = time.perf_counter()
    fn()
    return time.perf_counter() - start


def summary_ms(samples_s: list[float]) -> dict[str, float]:
    """Mean, p50, p95 and max of `samples_s`, in ms (3 decimals)."""
    ms = np.array(samples_s) * 1e3
    return {
        "mean": round(float(ms.mean()), 3),
        "p50": round(float(np.percentile(ms, 50)), 3),
        "p95": round(float(np.percentile(ms, 95)), 3),
        "max": round(float(ms.max()), 3),
    }


def run(step_m: float, rebuilds: int) -> dict[str, object]:
    """The simulated building mapped, then driven again: insert and refresh times per scan,
    full rebuild times, map memory and peak RSS."""
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

            def insert(
                h: NDArray[np.float64] = hits,
                m: NDArray[np.float64] = misses,
                o: NDArray[np.float64] = origin,
            ) -> None:
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


def rebuild_views(world: MatchingMap, rebuilds: int) -> dict[str, dict[str, float]]:
    """Times of rebuilding the stack and NDT cells whole, as MatchingMap did after every change
    of the occupied cells (the NDT cells from freshly listed occupied cell centres), and the
    ndt matcher's overlapping cells as it built them on every match."""
    field = world.likelihood_field(0)
    grid = world.grid
    spec, occupied = grid.spec, grid.occupied_mask()
    anchor = (grid.anchor_x_m, grid.anchor_y_m)

    def rebuild_field0() -> None:
        MatchingMap(grid).likelihood_field(0)

    def rebuild_pyramid() -> None:
        MatchingMap(grid).likelihood_pyramid(PYRAMID_LEVELS)

    def rebuild_stack() -> None:
        MaxPoolStack.from_values(field.spec, field.values, STACK_DEPTH)

    def rebuild_ndt() -> None:
        NDTCells.from_points(spec.cell_centers(np.argwhere(occupied)), NDT_CELL_M, anchor)

    def rebuild_overlapping() -> None:
        centres = spec.cell_centers(np.argwhere(occupied))
        for size in NDT_SIZES_M:
            OverlappingCells.from_points(centres, size, anchor)

    builds = {
        "field0": rebuild_field0,
        "pyramid": rebuild_pyramid,
        "maxpool": rebuild_stack,
        "ndt": rebuild_ndt,
        "overlapping": rebuild_overlapping,
    }
    for build in builds.values():
        build()  # compiled kernels loaded outside the timings
    return {
        f"{view}_rebuild_ms": summary_ms([timed(build) for _ in range(rebuilds)])
        for view, build in builds.items()
    }


def view_refresh(
    log: Path,
    small_scans: int,
    samples: int,
    rebuilds: int,
    limit: int | None,
    tile_cells: int | None = None,
) -> dict[str, object]:
    """Per-scan refresh of the fields, the max-pool stack and the NDT cells on a real log's
    map, while it is small and at the end, next to rebuilding them whole."""
    frames = load_keyframes(log)[:limit]
    if small_scans + 2 * samples > len(frames):
        need = small_scans + 2 * samples
        raise SystemExit(f"{log.name}: {len(frames)} keyframes, need >= {need}")
    windows = {
        "small": range(small_scans, small_scans + samples),
        "large": range(len(frames) - samples, len(frames)),
    }
    world = MatchingMap() if tile_cells is None else MatchingMap(tile_cells=tile_cells)
    out: dict[str, object] = {"log": log.name, "scans": len(frames), "tile_cells": tile_cells}
    views = ("field0", "pyramid", "maxpool", "ndt", "overlapping")
    samples_ms: dict[str, list[float]] = {view: [] for view in views}
    insert_s: list[float] = []
    first, at = frames[0], frames[0].true_pose * frames[0].scan.mount
    MatchingMap().update(first.true_pose.transform_points(first.scan.robot_points()), (at.x, at.y))
    for i, frame in enumerate(frames):
        pose, sensor = frame.true_pose, frame.true_pose * frame.scan.mount
        points = pose.transform_points(frame.scan.robot_points())
        insert_s.append(timed(lambda: world.update(points, (sensor.x, sensor.y))))  # noqa: B023
        # Views read after every scan, as a front end would: each refresh covers one scan.
        field0_s = timed(lambda: world.likelihood_field(0))
        times = {
            "field0": field0_s,
            "pyramid": field0_s + timed(lambda: world.likelihood_pyramid(PYRAMID_LEVELS)),
            "maxpool": timed(lambda: world.maxpool_stack(STACK_DEPTH)),
            "ndt": timed(lambda: world.ndt_cells(NDT_CELL_M)),
            "overlapping": timed(
                lambda: [world.overlapping_ndt_cells(size) for size in NDT_SIZES_M]
            ),
        }
        name = next((n for n, w in windows.items() if i in w), None)
        if name is None:
            continue
        for key, t in times.items():
            samples_ms[key].append(t)
        if i != windows[name][-1]:
            continue
        spec = world.grid.spec
        out[name] = {
            "after_scans": i + 1,
            "extent_cells": [spec.rows, spec.cols],
            "mapped_area_m2": round(spec.width_m * spec.height_m, 1),
            "occupied_cells": len(world.occupied_points()),
            "ndt_cells": len(world.ndt_cells(NDT_CELL_M)),
            "overlapping_blocks": [len(world.overlapping_ndt_cells(s)) for s in NDT_SIZES_M],
            **{f"{key}_refresh_ms": summary_ms(t) for key, t in samples_ms.items()},
            **rebuild_views(world, rebuilds),
        }
        samples_ms = {key: [] for key in samples_ms}
    out["insert_ms"] = summary_ms(insert_s)
    out["inserts_total_s"] = round(sum(insert_s), 3)
    nodes = [ScanNode(0.0, f.scan.robot_points(), np.zeros((0, 2)), f.scan.mount) for f in frames]
    poses = np.array([f.true_pose.to_array() for f in frames])
    redraws = [timed(lambda: draw_keyframes(nodes, poses, world.grid.params))
               for _ in range(rebuilds)]
    out["redraw_s"] = round(float(np.median(redraws)), 3)
    return out


def print_table(r: Mapping[str, Any]) -> None:
    """Print the report of `run` as text (its JSON object: values of every kind)."""
    print(f"{r['world']}, {r['resolution_m']} m cells, one scan every {r['step_m']} m")
    print(
        f"extent {r['extent_cells']} cells = {r['mapped_area_m2']} m^2, "
        f"storage {r['storage_cells']} cells"
    )
    for name, p in r["phases"].items():
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


def print_views(v: Mapping[str, Any]) -> None:
    """Print the report of `view_refresh` as text (its JSON object: values of every kind)."""
    ins = v["insert_ms"]
    print(f"matching views on {v['log']} ({v['scans']} scans at the corrected poses):")
    print(f"insert p50 {ins['p50']} mean {ins['mean']} p95 {ins['p95']} ms "
          f"(all {v['inserts_total_s']} s); all redrawn in one pass {v['redraw_s']} s")
    for name in ("small", "large"):
        w = v[name]
        print(
            f"{name:6s} after {w['after_scans']} scans: extent {w['extent_cells']} cells "
            f"({w['mapped_area_m2']} m^2), {w['occupied_cells']} occupied, "
            f"{w['ndt_cells']} NDT cells"
        )
        for view in ("field0", "pyramid", "maxpool", "ndt", "overlapping"):
            fresh, full = w[f"{view}_refresh_ms"], w[f"{view}_rebuild_ms"]
            print(
                f"  {view:11s} refresh after one scan mean {fresh['mean']} p95 {fresh['p95']} "
                f"max {fresh['max']} ms | full rebuild mean {full['mean']} ms"
            )


def main() -> None:
    """Run the building (unless --views-only) and, with --data, the log's views; print them."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--json", action="store_true", help="print one JSON object")
    parser.add_argument("--step-m", type=float, default=0.25, help="distance between scans")
    parser.add_argument("--rebuilds", type=int, default=5, help="full rebuilds to time")
    parser.add_argument("--data", type=Path, help="CARMEN log: also time the matching views")
    parser.add_argument("--views-only", action="store_true", help="skip the simulated building")
    parser.add_argument("--small-scans", type=int, default=100, help="scans in the small map")
    parser.add_argument("--samples", type=int, default=50, help="scans timed per map size")
    parser.add_argument("--limit", type=int, help="use only the log's first LIMIT keyframes")
    parser.add_argument("--tile-cells", type=int, help="side of the fields' dirty tiles")
    args = parser.parse_args()
    if args.views_only and args.data is None:
        parser.error("--views-only needs --data")
    result: dict[str, object] = {} if args.views_only else run(args.step_m, args.rebuilds)
    views = None
    if args.data is not None:
        views = view_refresh(
            args.data, args.small_scans, args.samples, args.rebuilds, args.limit, args.tile_cells
        )
        result["views"] = views
    if args.json:
        print(json.dumps(result, indent=2))
        return
    if not args.views_only:
        print_table(result)
    if views is not None:
        print_views(views)


if __name__ == "__main__":
    main()
