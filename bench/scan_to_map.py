"""Iterative field/NDT matchers (gn, lm, ndt): time per match and accuracy, plus gn against a map.

Part 1, real pairs: consecutive keyframes of a CARMEN log (target = scan i, source = scan i+1,
guess = wheel odometry), every method building what it needs from the target scan inside the
timed call. Reports median/mean wall time and median CPU time of this process per match (on a
shared machine the CPU time is the better estimate of an unloaded wall time) and the success
rate at 5 cm / 0.5 deg and 10 cm / 1 deg against the corrected poses.

Part 2, simulator: a map of the `rooms` world built from the true poses, then every scan's
undistorted endpoints matched with gn from a perturbed guess, once against fields that measure
distances to each cell's mean hit point and once against cell centres (the same grid without
its hit sums, as an old npz loads). Reports the translation / rotation errors.

    python -m bench.scan_to_map [--data PATH] [--pairs 60] [--json]
"""

from __future__ import annotations

import argparse
import json
import math
import time
from pathlib import Path

import numpy as np
from scanflow.geometry import Pose2D
from scanflow.io.carmen import load_keyframes
from scanflow.maps.matching_map import MatchingMap
from scanflow.maps.occupancy import OccupancyGrid
from scanflow.matching import match
from scanflow.sim import SimConfig, simulate

from bench.csm import existing_log

METHODS = ("gn", "lm", "ndt")
SIM_GUESS_ERROR = (0.05, 0.05, math.radians(1.0))


def real_pairs(log: Path, pairs: int) -> dict[str, object]:
    """Time and accuracy per method on `pairs` evenly spread consecutive keyframe pairs."""
    frames = load_keyframes(log)
    step = max((len(frames) - 1) // pairs, 1)
    idx = list(range(0, len(frames) - 1, step))[:pairs]
    jobs = []
    for i in idx:
        a, b = frames[i], frames[i + 1]
        jobs.append(
            (
                b.scan.points(),
                a.scan.points(),
                b.odom_pose.relative_to(a.odom_pose),
                b.true_pose.relative_to(a.true_pose),
            )
        )
    out: dict[str, object] = {"log": log.name, "pairs": len(jobs)}
    for method in METHODS:
        match(jobs[0][0], jobs[0][1], jobs[0][2], method=method)  # compile / warm caches
        times, cpu, errs = [], [], []
        for src, tgt, guess, truth in jobs:
            t0, c0 = time.perf_counter(), time.process_time()
            result = match(src, tgt, guess, method=method)
            times.append(time.perf_counter() - t0)
            cpu.append(time.process_time() - c0)
            e = result.pose.relative_to(truth)
            errs.append((e.translation_norm(), abs(e.theta)))
        err = np.array(errs)
        out[method] = {
            "ms_median": 1e3 * float(np.median(times)),
            "ms_mean": 1e3 * float(np.mean(times)),
            "cpu_ms_median": 1e3 * float(np.median(cpu)),
            "success_5cm_0.5deg": float(
                np.mean((err[:, 0] <= 0.05) & (err[:, 1] <= math.radians(0.5)))
            ),
            "success_10cm_1deg": float(
                np.mean((err[:, 0] <= 0.10) & (err[:, 1] <= math.radians(1.0)))
            ),
        }
    return out


def centres_only(grid: OccupancyGrid) -> OccupancyGrid:
    """The same log-odds grid without hit sums: its fields fall back to cell centres."""
    box = grid.extent
    return OccupancyGrid.from_arrays(
        grid.log_odds, grid.observed, box, grid.anchor_x_m, grid.anchor_y_m, grid.params
    )


def sim_map(duration_s: float, seed: int) -> dict[str, object]:
    """gn against a simulator map: errors with mean-hit fields vs cell-centre fields."""
    frames = list(simulate(SimConfig(world="rooms", duration_s=duration_s, seed=seed)))
    world = MatchingMap()
    for f in frames:
        world.update(f.true_pose.transform_points(f.true_points), [f.true_pose.x, f.true_pose.y])
    maps = {"mean_hits": world, "cell_centres": MatchingMap(centres_only(world.grid))}
    rng = np.random.default_rng(seed)
    out: dict[str, object] = {"world": "rooms", "scans": len(frames)}
    for name, target in maps.items():
        errs = []
        for f in frames:
            noise = rng.uniform(-1.0, 1.0, 3) * SIM_GUESS_ERROR
            guess = Pose2D.from_array(f.true_pose.to_array() + noise)
            result = match(f.true_points, target, guess, method="gn")
            e = result.pose.relative_to(f.true_pose)
            errs.append((e.translation_norm(), abs(e.theta)))
        err = np.array(errs)
        out[name] = {
            "trans_mm_median": 1e3 * float(np.median(err[:, 0])),
            "trans_mm_p95": 1e3 * float(np.percentile(err[:, 0], 95)),
            "rot_mdeg_median": 1e3 * math.degrees(float(np.median(err[:, 1]))),
        }
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=None, help="CARMEN log (default: intel)")
    parser.add_argument("--pairs", type=int, default=60)
    parser.add_argument("--sim-seconds", type=float, default=20.0)
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args()
    log = existing_log(args.data)
    result = {"real": real_pairs(log, args.pairs), "sim": sim_map(args.sim_seconds, 0)}
    print(json.dumps(result, indent=None if args.json else 2))


if __name__ == "__main__":
    main()
