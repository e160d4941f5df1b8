"""Loop closure and pose-graph optimisation on a real log, against the front end alone.

`python -m bench.slam --data PATH [--limit N] [--method M] [--json]`
`python -m bench.slam --data PATH --starts N [--limit N] [--method M] [--json]`
`python -m bench.slam --sim [--world loop] [--duration 240] [--odom-scale-error 0.03] [--method M]
[--json]`

The keyframes of a CARMEN log go through the in-process pipeline twice with the wheel odometry of
each record: the front end alone (the baseline: scan-to-map tracking, what `scanflow run` does
without loop closure), then with the back end (`BackendSettings(loop_closure=True)`, its last
optimisation at the end of the log). Against the corrected poses: ATE (RMSE after SE(2)
alignment), the largest aligned error, RPE per metre. Without them: the map's occupied cells
(a wall drawn twice by drift takes more). For the back end: its closures, how many of them the
corrected poses disagree with (relative pose beyond 0.3 m / 3 deg: a wrong closure is one the
optimiser must out-vote), keyframes, inserts culled as keyframes and map redraws; wall time
of both passes. `served_ate_rmse_m` is the ATE of the path as the services serve it over HTTP:
the map server's path is corrected at each redraw only (the corrected path up to that scan,
then the front end's estimates), and no service knows when a log ends, so it has no last
optimisation.
Each pass's map is saved as PNG in bench/out. The back end's other settings come from
`SCANFLOW_BACKEND_*` as in `scanflow run` (e.g. `SCANFLOW_BACKEND_CONFIRM_KEYFRAMES=0`,
`SCANFLOW_BACKEND_CULL_M=0.3`).
Sim mode: the same two passes on the built-in simulator, whose poses are exact (the ring world
`loop` by default, with wheel odometry of a given scale error and yaw noise), so the figures
carry no reference noise. With `--prior-s S` both passes run on a prior map, the front end's map
of an earlier run over the tour's first S seconds from the same start: localising on it and
extending it (the front end alone), against loop closure on it. `abs_mean_m` / `abs_max_m` are
then the errors without alignment, where the prior map puts the robot.
`--starts N` runs both passes on the log from each of its first N keyframes instead and reports
every ATE: one run's figure on a real log swings with where it starts (a fast turn, a
corridor decides it), so a change is judged by the spread.
"""

from __future__ import annotations

import argparse
import copy
import json
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray
from scanflow.config import BackendSettings, FrontendSettings
from scanflow.frontend import default_settings
from scanflow.geometry import Pose2D
from scanflow.io.carmen import Keyframe
from scanflow.maps.export import save_png
from scanflow.maps.occupancy import OccupancyGrid
from scanflow.pipeline import Pipeline
from scanflow.scan import LaserScan, Odometry
from scanflow.sim import SimConfig, simulate
from tqdm import tqdm

from bench.data import log_keyframes
from bench.frontend import (
    OUT_DIR,
    SIM_MAP_FROM_WORLD,
    accuracy,
    align_se2,
    ate_rmse_m,
    poses_array,
    settings_for,
)

WRONG_CLOSURE_M = 0.3
WRONG_CLOSURE_DEG = 3.0


def max_error_m(estimate: NDArray[np.float64], truth: NDArray[np.float64]) -> float:
    """The largest position error after SE(2) alignment."""
    aligned = align_se2(estimate[:, :2], truth[:, :2])
    return float(np.max(np.hypot(*(aligned - truth[:, :2]).T)))


@dataclass
class Feed:
    """What one pass replays: per scan, the scan and either its odometry pose (a log's
    keyframes) or the odometry samples before it (the simulator)."""

    scans: list[LaserScan]
    odom_poses: list[Pose2D | None]
    odometry: list[list[Odometry]]


@dataclass
class PassResult:
    """One pass: the pipeline, its final poses per scan (after the last optimisation), the
    path as the map server serves it, wall time, the keyframes' scan indices and how often
    the map was redrawn."""

    pipeline: Pipeline
    poses: NDArray[np.float64]
    served: NDArray[np.float64]
    wall_s: float
    keyframes: list[int]
    redraws: int


def run_pass(
    feed: Feed, settings: FrontendSettings, backend: BackendSettings | None, name: str,
    initial_pose: Pose2D | None = None, prior: OccupancyGrid | None = None,
) -> PassResult:
    """Replay the feed through one pipeline (on a copy of `prior`, if any; see `PassResult`)."""
    grid = None if prior is None else copy.deepcopy(prior)
    pipeline = Pipeline(settings, backend=backend, initial_pose=initial_pose, grid=grid)
    poses, served, keyframes, redraws = [], [], [], 0
    t0 = time.perf_counter()
    for i, scan in enumerate(tqdm(feed.scans, desc=name, file=sys.stderr, leave=False)):
        for sample in feed.odometry[i]:
            pipeline.add_odometry(sample)
        out = pipeline.process(scan, feed.odom_poses[i])
        poses.append(out.estimate.pose)
        served.append(out.estimate.pose.to_array())
        if out.backend is not None:
            redraws += out.backend.redrawn
            if out.backend.node is not None:
                keyframes.append(i)
            if out.backend.redrawn:  # the redraw carries the corrected path, this scan's last
                assert pipeline.mapper is not None
                served = list(pipeline.mapper.trajectory())
    final = pipeline.finish()
    redraws += final is not None and final.redrawn
    wall_s = time.perf_counter() - t0
    final_poses = (
        pipeline.mapper.trajectory() if pipeline.mapper is not None else poses_array(poses)
    )
    return PassResult(pipeline, final_poses, np.asarray(served), wall_s, keyframes, redraws)


def closure_agreement(
    pipeline: Pipeline, truth: NDArray[np.float64], keyframes: list[int]
) -> dict[str, float]:
    """How many closures the reference disagrees with (relative pose older -> newer)."""
    mapper = pipeline.mapper
    assert mapper is not None
    wrong = 0
    for closure in mapper.closures:
        a = Pose2D.from_array(truth[keyframes[closure.older]])
        b = Pose2D.from_array(truth[keyframes[closure.newer]])
        error = closure.measurement.relative_to(a.inverse() * b)
        wrong += (
            error.translation_norm() > WRONG_CLOSURE_M
            or abs(np.degrees(error.theta)) > WRONG_CLOSURE_DEG
        )
    return {"closures": len(mapper.closures), "disagreeing": wrong}


def passes() -> tuple[tuple[str, BackendSettings | None], ...]:
    """The two passes: the front end alone, then with loop closure (SCANFLOW_BACKEND_* apply,
    read now)."""
    return ("frontend", None), ("loop_closure", BackendSettings(loop_closure=True))


def compare(
    name: str, feed: Feed, truth: NDArray[np.float64], initial_pose: Pose2D | None = None,
    prior: OccupancyGrid | None = None, settings: FrontendSettings | None = None,
) -> dict[str, object]:
    """The front end alone and with the back end on the same scans, against `truth` (both on
    `prior`, if any: then the errors without alignment too, in the prior map's frame)."""
    settings = settings or default_settings()
    OUT_DIR.mkdir(exist_ok=True)
    report: dict[str, object] = {"scans": len(feed.scans), "method": settings.method}
    for label, backend in passes():
        result = run_pass(feed, settings, backend, label, initial_pose, prior)
        pipeline, poses, wall_s = result.pipeline, result.poses, result.wall_s
        grid = (pipeline.frontend.map if pipeline.mapper is None
                else pipeline.mapper.draw_map()).grid
        png = save_png(grid, OUT_DIR / f"slam_{name}_{label}.png")
        row: dict[str, object] = {
            **accuracy(poses, truth),
            "max_error_m": max_error_m(poses, truth),
            "wall_s": wall_s,
            "scans_per_s": len(feed.scans) / wall_s,
            "map_png": str(png),
            # Walls drawn twice (drift) take more cells: fewer is a crisper map of the same place.
            "occupied_cells": int(np.count_nonzero(grid.occupied_mask())),
        }
        if prior is not None:  # on a map, no alignment: where the map puts the robot
            off = np.hypot(*(poses[:, :2] - truth[:, :2]).T)
            row.update(abs_mean_m=float(off.mean()), abs_max_m=float(off.max()))
        if pipeline.mapper is not None:
            row.update(closure_agreement(pipeline, truth, result.keyframes))
            row["served_ate_rmse_m"] = ate_rmse_m(result.served, truth)
            row["keyframes"] = len(result.keyframes)
            # Inserts the back end did not make keyframes (SCANFLOW_BACKEND_CULL_M; 0: off).
            row["culled"] = len(pipeline.mapper.culled_seqs)
            row["cull_m"] = pipeline.mapper.settings.cull_m
            row["map_redraws"] = result.redraws
        report[label] = row
    return report


def log_feed(frames: list[Keyframe]) -> tuple[Feed, NDArray[np.float64]]:
    """The keyframes' scans with their wheel odometry, and their corrected poses."""
    feed = Feed([kf.scan for kf in frames], [kf.odom_pose for kf in frames],
                [[] for _ in frames])
    return feed, poses_array([kf.true_pose for kf in frames])


def run_log(path: Path, limit: int | None, settings: FrontendSettings | None = None) -> dict:
    """Both passes on the log's keyframes (the first `limit`) against its corrected poses, and
    the odometry's accuracy."""
    frames = log_keyframes(path, limit)
    feed, truth = log_feed(frames)
    report = {"log": path.name,
              **compare(path.name.split(".")[0], feed, truth, settings=settings)}
    report["odometry"] = accuracy(poses_array([kf.odom_pose for kf in frames]), truth)
    return report


def run_log_starts(
    path: Path, limit: int | None, starts: int, settings: FrontendSettings | None = None
) -> dict:
    """Both passes on the log from each of its first `starts` keyframes: every ATE, and the
    median and largest of each pass's."""
    settings = settings or default_settings()
    frames = log_keyframes(path, limit)
    if not 0 < starts < len(frames):
        raise ValueError(f"starts must be in 1..{len(frames) - 1} for {path.name}, got {starts}")
    report: dict[str, object] = {"log": path.name, "method": settings.method}
    runs = [log_feed(frames[k:]) for k in range(starts)]
    for label, backend in passes():
        ates = []
        for k, (feed, truth) in enumerate(runs):
            result = run_pass(feed, settings, backend, f"{label} from {k}")
            ates.append(ate_rmse_m(result.poses, truth))
        report[label] = {"ate_by_start_m": ates, "median_ate_m": float(np.median(ates)),
                         "max_ate_m": float(np.max(ates))}
    return report


def sim_feed(
    world: str, duration_s: float, scale_error: float, yaw_noise: float
) -> tuple[Feed, NDArray[np.float64]]:
    """The simulator's scans and odometry (seed 1), and the true poses in the map frame."""
    config = SimConfig(world=world, duration_s=duration_s, seed=1,
                       odom_scale_error=scale_error, odom_yaw_noise=yaw_noise)
    frames = list(simulate(config))
    feed = Feed([f.scan for f in frames], [None] * len(frames), [f.odometry for f in frames])
    return feed, poses_array([SIM_MAP_FROM_WORLD * f.true_pose for f in frames])


def run_sim(
    world: str, duration_s: float, scale_error: float, yaw_noise: float, prior_s: float = 0.0,
    settings: FrontendSettings | None = None,
) -> dict:
    """Both passes on the simulator; with `prior_s`, both on a prior map: the front end's map
    of an earlier run over the first `prior_s` seconds of the same tour from the same start."""
    settings = settings or default_settings()
    feed, truth = sim_feed(world, duration_s, scale_error, yaw_noise)
    start = Pose2D.from_array(truth[0])
    prior = None
    if prior_s > 0.0:
        first, _ = sim_feed(world, prior_s, scale_error, yaw_noise)
        prior = run_pass(first, settings, None, "prior", start).pipeline.frontend.map.grid
    return {
        "world": world, "duration_s": duration_s, "odom_scale_error": scale_error,
        "odom_yaw_noise": yaw_noise, "prior_s": prior_s,
        **compare(f"sim_{world}", feed, truth, start, prior, settings),
    }


def main(argv: list[str] | None = None) -> None:
    """Run the sim or log comparison the arguments choose and print its report as JSON."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, help="CARMEN log (.log or .log.gz)")
    parser.add_argument("--limit", type=int, default=None, help="first N keyframes only")
    parser.add_argument("--sim", action="store_true", help="the simulator instead of a log")
    parser.add_argument("--world", default="loop", help="sim: the world to drive")
    parser.add_argument("--duration", type=float, default=240.0, help="sim seconds")
    parser.add_argument("--odom-scale-error", type=float, default=0.03)
    parser.add_argument("--odom-yaw-noise", type=float, default=0.01)
    parser.add_argument("--prior-s", type=float, default=0.0,
                        help="sim: both passes on the map of an earlier run's first S seconds")
    parser.add_argument("--method", default=None, help="the front end's scan-to-map method")
    parser.add_argument("--starts", type=int, default=0,
                        help="log: both passes from each of the first N keyframes instead")
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args(argv)
    settings = settings_for(args.method)
    if args.sim:
        report = run_sim(args.world, args.duration, args.odom_scale_error, args.odom_yaw_noise,
                         args.prior_s, settings)
    elif args.data is not None and args.starts:
        try:
            report = run_log_starts(args.data, args.limit, args.starts, settings)
        except ValueError as exc:
            parser.error(str(exc))
    elif args.data is not None:
        report = run_log(args.data, args.limit, settings)
    else:
        parser.error("give --data PATH or --sim")
    print(json.dumps(report, default=float, indent=None if args.json else 2))


if __name__ == "__main__":
    main()
