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

Part 3, ndt against a growing map: the log's keyframes inserted one by one at their corrected
poses; before each insert the scan is matched with ndt against the map so far, guess = the
previous corrected pose moved by the odometry increment (a front end's prediction). Each scan
is matched twice on the same map: against the map (its overlapping NDT cells kept current
incrementally) and as the matcher did before, listing the map's occupied points and building
the cells of every level from them. Reports time per match and success of both.

    python -m bench.scan_to_map [--data PATH] [--pairs 60] [--map-scans N] [--json]
"""

from __future__ import annotations

import argparse
import json
import math
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
from numpy.typing import NDArray
from scanflow.geometry import Pose2D
from scanflow.io.carmen import load_keyframes
from scanflow.maps.grid import CellBox
from scanflow.maps.matching_map import MatchingMap
from scanflow.maps.occupancy import OccupancyGrid
from scanflow.matching import MatchResult, match
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
                b.scan.robot_points(),
                a.scan.robot_points(),
                b.odom_pose.relative_to(a.odom_pose),
                b.true_pose.relative_to(a.true_pose),
            )
        )
    out: dict[str, object] = {"log": log.name, "pairs": len(jobs)}
    for method in METHODS:
        match(jobs[0][0], jobs[0][1], jobs[0][2], method=method)  # compile / warm caches
        runs = Runs()
        for src, tgt, guess, truth in jobs:
            runs.time(truth, match, src, tgt, guess, method=method)
        out[method] = runs.summary()
    return out


class Runs:
    """Wall and CPU time per match and the errors against the truth, summarised."""

    def __init__(self) -> None:
        self.wall: list[float] = []
        self.cpu: list[float] = []
        self.errors: list[tuple[float, float]] = []

    def time(
        self, truth: Pose2D, run: Callable[..., MatchResult], *args: object, **kwargs: object
    ) -> MatchResult:
        """`run(*args, **kwargs)`, timed, and its pose's error against `truth`."""
        t0, c0 = time.perf_counter(), time.process_time()
        result = run(*args, **kwargs)
        self.wall.append(time.perf_counter() - t0)
        self.cpu.append(time.process_time() - c0)
        e = result.pose.relative_to(truth)
        self.errors.append((e.translation_norm(), abs(e.theta)))
        return result

    def summary(self) -> dict[str, float]:
        """Wall time median, mean, p95 and CPU median (ms), and success at 5 cm / 0.5 deg and
        10 cm / 1 deg."""
        err = np.array(self.errors)
        return {
            "ms_median": 1e3 * float(np.median(self.wall)),
            "ms_mean": 1e3 * float(np.mean(self.wall)),
            "ms_p95": 1e3 * float(np.percentile(self.wall, 95)),
            "cpu_ms_median": 1e3 * float(np.median(self.cpu)),
            "success_5cm_0.5deg": float(
                np.mean((err[:, 0] <= 0.05) & (err[:, 1] <= math.radians(0.5)))
            ),
            "success_10cm_1deg": float(
                np.mean((err[:, 0] <= 0.10) & (err[:, 1] <= math.radians(1.0)))
            ),
        }


def ndt_on_listed_points(
    source: NDArray[np.float64], world: MatchingMap, guess: Pose2D
) -> MatchResult:
    """ndt as it read a map before: its occupied points listed, cells built from them (as
    they are: not filled along surfaces, which is for a scan)."""
    return match(source, world.occupied_points(), guess, method="ndt", surface_step_m=None)


def ndt_on_map(log: Path, scans: int | None) -> dict[str, object]:
    """ndt against a map growing scan by scan: the map's kept cells vs cells rebuilt per match
    from its listed occupied points (what the matcher did before), on the same map states."""
    frames = load_keyframes(log)[:scans]
    world = MatchingMap()
    kept, rebuilt = Runs(), Runs()
    differences = []
    for i, frame in enumerate(frames):
        pose, source = frame.true_pose, frame.scan.robot_points()
        if i > 0:
            before = frames[i - 1]
            guess = before.true_pose * frame.odom_pose.relative_to(before.odom_pose)
            if i == 1:  # compile / warm caches on the one-scan map
                match(source, world, guess, method="ndt")
            old = rebuilt.time(pose, ndt_on_listed_points, source, world, guess)
            new = kept.time(pose, match, source, world, guess, method="ndt")
            differences.append(np.abs(new.pose.to_array() - old.pose.to_array()).max())
        world.update(pose.transform_points(source), (pose.x, pose.y))
    spec = world.grid.spec
    return {
        "log": log.name,
        "matches": len(differences),
        "final_area_m2": round(spec.width_m * spec.height_m, 1),
        "final_occupied_cells": len(world.occupied_points()),
        "ndt_kept_cells": kept.summary(),
        "ndt_rebuilt_cells": rebuilt.summary(),
        "max_pose_difference": float(max(differences, default=0.0)),
    }


def centres_only(grid: OccupancyGrid) -> OccupancyGrid:
    """The same log-odds grid without hit sums: its fields fall back to cell centres."""
    box = grid.extent or CellBox(0, 0, 0, 0)  # an empty grid has no extent
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
    """Run the three parts on --data (default: the Intel log) and print them as JSON."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=None, help="CARMEN log (default: intel)")
    parser.add_argument("--pairs", type=int, default=60)
    parser.add_argument("--sim-seconds", type=float, default=20.0)
    parser.add_argument(
        "--map-scans", type=int, default=None, help="keyframes in the ndt map run (default: all)"
    )
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args()
    log = existing_log(args.data)
    result = {
        "real": real_pairs(log, args.pairs),
        "sim": sim_map(args.sim_seconds, 0),
        "map": ndt_on_map(log, args.map_scans),
    }
    print(json.dumps(result, indent=None if args.json else 2))


if __name__ == "__main__":
    main()
