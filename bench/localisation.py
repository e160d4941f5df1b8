"""Localisation on a prior map, on a real CARMEN log.

The prior map: the log's even keyframes inserted at their corrected poses (5 cm), saved to and
read back from .npz as a user's map would be. The odd keyframes are the robot's new visit.

Part 1, global localisation (no guess at all): `localise_globally` on `--queries` odd keyframes
drawn at random (seeded), on the coarse level the front end uses (`--level`, default 1) and,
as the baseline, on the full-resolution level 0 (the plain Cartographer-style search). Per
setting: success at 5 cm / 0.5 deg and 10 cm / 1 deg against the corrected pose, how many are
flagged AMBIGUOUS, how many are grossly wrong (> 0.5 m or > 5 deg) yet reported OK, and the
median / 95th-percentile / max time.

Part 2, tracking the odd keyframes in order with their wheel odometry:
- `localise`: the front end on the prior map, start unknown (whole-map search), map frozen;
- `slam` (baseline): the front end mapping from scratch, started at the true first pose.
Per run: error of every pose against the corrected pose in the map frame (no alignment: a
localised robot must be right in the map's frame), success at 10 cm / 1 deg, statuses and
time per scan.

    python -m bench.localisation --data ../shared/data/intel-corrected.log.gz --json
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from scanflow.config import FrontendSettings
from scanflow.frontend import default_settings, insert_scan
from scanflow.io.carmen import Keyframe, load_keyframes
from scanflow.maps.export import load_map, save_map
from scanflow.maps.matching_map import MatchingMap
from scanflow.maps.occupancy import OccupancyGrid, OccupancyParams
from scanflow.matching import MatchStatus
from scanflow.matching.global_search import localise_globally
from scanflow.pipeline import Pipeline
from tqdm import tqdm

from bench.matching import errors, shares_within

GROSS_M, GROSS_DEG = 0.5, 5.0


def prior_map(frames: list[Keyframe], resolution_m: float, folder: Path) -> OccupancyGrid:
    """The even keyframes at their corrected poses, through a saved .npz."""
    world = MatchingMap(OccupancyGrid(OccupancyParams(resolution_m=resolution_m)))
    for kf in frames[::2]:
        insert_scan(world, kf.scan.robot_points(), kf.true_pose, mount=kf.scan.mount)
    return load_map(save_map(world.grid, folder / "prior.npz"))


def rates(errs: list[tuple[float, float]]) -> dict[str, float]:
    """Success shares at bench.matching's THRESHOLDS and error percentiles of (m, deg) errors."""
    e = np.asarray(errs).reshape(-1, 2)
    return {
        **shares_within("success", e[:, 0], e[:, 1]),
        "t50_m": float(np.median(e[:, 0])),
        "t95_m": float(np.percentile(e[:, 0], 95)),
        "r50_deg": float(np.median(e[:, 1])),
        "r95_deg": float(np.percentile(e[:, 1], 95)),
    }


def global_part(
    world: MatchingMap, frames: list[Keyframe], queries: list[int], level: int, method: str
) -> dict:
    """`localise_globally` on each query keyframe: accuracy, flags and time."""
    errs, times, ambiguous, gross_ok = [], [], 0, 0
    for i in tqdm(queries, desc=f"global level {level}", file=sys.stderr, leave=False):
        kf = frames[i]
        t0 = time.perf_counter()
        found = localise_globally(kf.scan.robot_points(), world, refine=method, level=level)
        times.append(time.perf_counter() - t0)
        err = errors(kf.true_pose, found.pose)
        errs.append(err)
        ambiguous += found.status is MatchStatus.AMBIGUOUS
        gross_ok += found.ok and (err[0] > GROSS_M or err[1] > GROSS_DEG)
    ms = np.asarray(times) * 1e3
    return {
        "queries": len(queries),
        **rates(errs),
        "ambiguous": ambiguous,
        "gross_but_ok": gross_ok,
        "median_ms": float(np.median(ms)),
        "p95_ms": float(np.percentile(ms, 95)),
        "max_ms": float(ms.max()),
    }


def tracking_part(
    frames: list[Keyframe], settings: FrontendSettings, grid: OccupancyGrid | None
) -> dict:
    """The odd keyframes in order: on the prior map (start unknown) or mapping from scratch."""
    visit = frames[1::2]
    start = None if grid is not None else visit[0].true_pose
    pipeline = Pipeline(settings, initial_pose=start, grid=grid)
    errs = []
    statuses: dict[str, int] = {}
    t0 = time.perf_counter()
    for kf in tqdm(visit, desc="tracking", file=sys.stderr, leave=False):
        est = pipeline.process(kf.scan, kf.odom_pose).estimate
        statuses[str(est.status)] = statuses.get(str(est.status), 0) + 1
        errs.append(errors(kf.true_pose, est.pose))
    wall_s = time.perf_counter() - t0
    e = np.asarray(errs)
    return {
        "scans": len(visit),
        **rates(errs),
        "rmse_m": float(np.sqrt(np.mean(e[:, 0] ** 2))),
        "max_m": float(e[:, 0].max()),
        "statuses": statuses,
        "ms_per_scan": 1e3 * wall_s / len(visit),
    }


def run(path: Path, queries: int, seed: int, level: int, limit: int | None = None) -> dict:
    """The prior map from the even keyframes, then global localisation (at `level` and level 0)
    and tracking on the odd ones."""
    frames = load_keyframes(path)[:limit]
    settings = default_settings()
    with tempfile.TemporaryDirectory() as tmp:
        grid = prior_map(frames, settings.map_resolution_m, Path(tmp))
    world = MatchingMap(grid)
    odd = np.arange(1, len(frames), 2)
    picks = np.random.default_rng(seed).choice(odd, min(queries, len(odd)), replace=False)
    chosen = sorted(int(i) for i in picks)
    localise = settings.model_copy(update={"update_map": False, "global_level": level})
    return {
        "log": path.name,
        "keyframes": len(frames),
        "map_m": [round(grid.spec.cols * grid.resolution_m, 1),
                  round(grid.spec.rows * grid.resolution_m, 1)],
        "global": {
            f"level_{level}": global_part(world, frames, chosen, level, settings.method),
            "level_0_baseline": global_part(world, frames, chosen, 0, settings.method),
        },
        "tracking": {
            "localise": tracking_part(frames, localise, grid),
            "slam_baseline": tracking_part(frames, settings, None),
        },
    }


def main(argv: list[str] | None = None) -> None:
    """Run the benchmark on --data and print tables (JSON with --json)."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, required=True, help="CARMEN log (.log or .gz)")
    parser.add_argument("--queries", type=int, default=60, help="keyframes for part 1")
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--level", type=int, default=default_settings().global_level)
    parser.add_argument("--limit", type=int, default=None, help="the log's first N keyframes")
    parser.add_argument("--json", action="store_true", help="print the figures as JSON")
    args = parser.parse_args(argv)
    if args.queries < 1 or args.level < 0 or (args.limit is not None and args.limit < 4):
        parser.error("--queries must be >= 1, --level >= 0 and --limit >= 4")
    report = run(args.data, args.queries, args.seed, args.level, args.limit)
    if args.json:
        print(json.dumps(report))
        return
    print(f"{report['log']}: {report['keyframes']} keyframes, map {report['map_m']} m")
    print("global     5cm/0.5d 10cm/1d  t50 m  r50 deg  ambiguous gross_ok  med ms  p95 ms")
    for name, g in report["global"].items():
        print(f"{name:<10} {g['success_5cm_0.5deg']:8.1%} {g['success_10cm_1deg']:7.1%} "
              f"{g['t50_m']:6.3f} {g['r50_deg']:8.2f} {g['ambiguous']:10d} {g['gross_but_ok']:8d} "
              f"{g['median_ms']:7.0f} {g['p95_ms']:7.0f}")
    print("tracking        10cm/1d  rmse m  max m  ms/scan  statuses")
    for name, t in report["tracking"].items():
        print(f"{name:<15} {t['success_10cm_1deg']:7.1%} {t['rmse_m']:7.3f} {t['max_m']:6.2f} "
              f"{t['ms_per_scan']:8.1f}  {t['statuses']}")


if __name__ == "__main__":
    main()
