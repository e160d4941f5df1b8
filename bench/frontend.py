"""The scan-to-map front end on a real log, or on the simulator at fast motion.

`python -m bench.frontend --data PATH [--limit N] [--method M] [--replays 2] [--json]`
`python -m bench.frontend --data PATH --starts N [--method M] [--json]`
`python -m bench.frontend --sim [--duration S] [--world W] [--perfect-odometry]
[--mount X,Y,YAW_DEG] [--json]`

Log mode: the keyframes of a CARMEN log (`load_keyframes`) through the in-process pipeline
(deskew stage + front end) with the wheel odometry of each record. Against the corrected poses:
ATE = RMSE of positions after the closed-form SE(2) alignment (Umeyama, no scale), RPE per metre
= mean over i of |relative-motion error from i to the first j >= 1 m further along the true
path| / that path length (translation m/m, rotation deg/m). Baselines on the same scans: wheel
odometry alone, and scan-to-scan ICP chained from consecutive keyframes (guess = odometry
increment). Throughput = scans / wall time of the pipeline loop, with the share of deskew,
match and map insertion. Peak RSS of the process (includes the loaded log). `--replays 2` runs
the log again on the finished map (a new Frontend on the same grid, from the first pose) and
reports the map's bytes after each pass: equal bytes = no growth with scan count once mapped.
`--starts N` runs the log from each of its first N keyframes instead and reports every ATE:
how much one run's figure depends on where the log starts.

Sim mode: the built-in simulator at 1.5 m/s and 180 deg/s, ATE with and without deskewing,
and the largest and last errors without alignment (where the map puts the robot).
`--perfect-odometry` makes the wheel odometry exact: what error is left is the matching's.
With `--mount`, the simulator's lidar sits there on the robot (metres, degrees) and a third run,
"mount_ignored", declares it at the robot's origin: what a pipeline without sensor extrinsics
gives (the lidar's poses taken as the robot's, odometry applied to the lidar).
"""

from __future__ import annotations

import argparse
import itertools
import json
import math
import resource
import sys
import time
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
from numpy.typing import NDArray
from scanflow.config import FrontendSettings
from scanflow.frontend import default_settings
from scanflow.geometry import IDENTITY, Pose2D, normalize_angles
from scanflow.io.carmen import Keyframe
from scanflow.maps.export import save_png
from scanflow.matching import match
from scanflow.pipeline import Pipeline
from scanflow.sim import WORLDS, SimConfig, simulate
from tqdm import tqdm

from bench.data import log_keyframes
from bench.lidar import Lidar, add_lidar_option, lidar_report, sim_lidar_fields

OUT_DIR = Path(__file__).resolve().parent / "out"
RPE_DELTA_M = 1.0
# The simulated worlds have walls at whole multiples of the 5 cm cell: turn the map frame so
# they do not lie exactly on cell boundaries, as no real wall does.
SIM_MAP_FROM_WORLD = Pose2D(0.013, -0.021, 0.3)


def poses_array(poses: list[Pose2D]) -> NDArray[np.float64]:
    """Poses as an (N, 3) array of (x, y, theta); (0, 3) for none."""
    return np.array([p.to_array() for p in poses]).reshape(-1, 3)


def align_se2(estimate_xy: NDArray[np.float64], truth_xy: NDArray[np.float64]) -> NDArray:
    """Estimate positions moved by the rotation + translation that best fit the truth."""
    mu_e, mu_t = estimate_xy.mean(axis=0), truth_xy.mean(axis=0)
    cov = (truth_xy - mu_t).T @ (estimate_xy - mu_e)
    u, _, vt = np.linalg.svd(cov)
    d = np.diag([1.0, np.sign(np.linalg.det(u @ vt))])
    rotation = u @ d @ vt
    return (estimate_xy - mu_e) @ rotation.T + mu_t


def ate_rmse_m(estimate: NDArray[np.float64], truth: NDArray[np.float64]) -> float:
    """Position RMSE after SE(2) alignment of (N, 3) estimate to (N, 3) truth."""
    aligned = align_se2(estimate[:, :2], truth[:, :2])
    return float(np.sqrt(np.mean(np.sum((aligned - truth[:, :2]) ** 2, axis=1))))


def rpe_per_m(estimate: NDArray[np.float64], truth: NDArray[np.float64]) -> dict[str, float]:
    """Mean relative-motion error per metre over true-path segments of >= RPE_DELTA_M."""
    step = np.hypot(*np.diff(truth[:, :2], axis=0).T)
    path = np.concatenate(([0.0], np.cumsum(step)))
    j = np.searchsorted(path, path + RPE_DELTA_M)
    i = np.flatnonzero(j < len(path))
    trans, rot = [], []
    for a, b in zip(i, j[i], strict=True):
        rel_t = Pose2D.from_array(truth[b]).relative_to(Pose2D.from_array(truth[a]))
        rel_e = Pose2D.from_array(estimate[b]).relative_to(Pose2D.from_array(estimate[a]))
        err = rel_e.relative_to(rel_t)
        length = path[b] - path[a]
        trans.append(err.translation_norm() / length)
        rot.append(abs(math.degrees(err.theta)) / length)
    if not trans:
        return {"trans_m_per_m": math.nan, "rot_deg_per_m": math.nan}
    return {"trans_m_per_m": float(np.mean(trans)), "rot_deg_per_m": float(np.mean(rot))}


def accuracy(estimate: NDArray[np.float64], truth: NDArray[np.float64]) -> dict[str, float]:
    """ATE (RMSE after SE(2) alignment, m) and RPE per metre of (N, 3) estimate against truth."""
    return {"ate_rmse_m": ate_rmse_m(estimate, truth), **rpe_per_m(estimate, truth)}


def chained_icp(frames: list[Keyframe]) -> NDArray[np.float64]:
    """Scan-to-scan ICP between consecutive keyframes, chained; odometry where ICP fails."""
    poses = [frames[0].odom_pose]
    for prev, cur in tqdm(itertools.pairwise(frames), total=len(frames) - 1, desc="icp chain",
                          file=sys.stderr, leave=False):
        guess = cur.odom_pose.relative_to(prev.odom_pose)
        result = match(cur.scan.robot_points(), prev.scan.robot_points(), guess, method="icp")
        poses.append(poses[-1] * (result.pose if result.ok else guess))
    return poses_array(poses)


@dataclass
class Pass:
    poses: NDArray[np.float64]
    wall_s: float
    stage_s: dict[str, float]
    statuses: dict[str, int]
    inserted: int
    rechecked: int  # passing matches searched again (recheck), whether replaced or kept
    rechecked_s: float  # the match time of those scans, first match and search together


def run_pass(pipeline: Pipeline, frames: list[Keyframe], desc: str) -> Pass:
    """One pass of `frames` through `pipeline`: poses, wall time, time per stage, statuses,
    inserts and rechecks."""
    poses = []
    statuses: dict[str, int] = {}
    stage = {"deskew": 0.0, "match": 0.0, "insert": 0.0}
    inserted = rechecked = 0
    rechecked_s = 0.0
    t0 = time.perf_counter()
    for kf in tqdm(frames, desc=desc, file=sys.stderr, leave=False):
        out = pipeline.process(kf.scan, kf.odom_pose)
        est = out.estimate
        poses.append(est.pose)
        statuses[str(est.status)] = statuses.get(str(est.status), 0) + 1
        stage["deskew"] += out.deskew_time_s
        stage["match"] += est.match_time_s
        stage["insert"] += est.insert_time_s
        inserted += est.inserted
        if est.rechecked:
            rechecked += 1
            rechecked_s += est.match_time_s
    return Pass(poses_array(poses), time.perf_counter() - t0, stage, statuses, inserted,
                rechecked, rechecked_s)


def peak_rss_mb() -> float:
    """Peak RSS of this process so far, in MiB (ru_maxrss is in KiB on Linux)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def run_log(path: Path, settings: FrontendSettings, limit: int | None, replays: int) -> dict:
    """The log through the pipeline: accuracy against the corrected poses (also odometry's and
    chained ICP's), throughput, stage shares, the map and its PNG; replays on that map."""
    frames = log_keyframes(path, limit)
    truth = poses_array([kf.true_pose for kf in frames])
    odometry = poses_array([kf.odom_pose for kf in frames])
    pipeline = Pipeline(settings)
    first = run_pass(pipeline, frames, path.name)
    grid = pipeline.frontend.map.grid
    name = path.name.split(".")[0]
    OUT_DIR.mkdir(exist_ok=True)
    png = save_png(grid, OUT_DIR / f"frontend_{name}.png")
    shares = {k: round(v / first.wall_s, 3) for k, v in first.stage_s.items()}
    shares["other"] = round(1.0 - sum(shares.values()), 3)
    report = {
        "log": path.name,
        "scans": len(frames),
        "beams": frames[0].scan.beam_count if frames else 0,
        "method": settings.method,
        "recheck_ratio": settings.recheck_ratio,
        "fallback": settings.fallback_method,
        "frontend": accuracy(first.poses, truth),
        "odometry": accuracy(odometry, truth),
        "statuses": first.statuses,
        "rechecked_scans": first.rechecked,
        "rechecked_match_s": first.rechecked_s,
        "inserted_scans": first.inserted,
        "scans_per_s": len(frames) / first.wall_s,
        "stage_shares": shares,
        "map_bytes": pipeline.frontend.map.nbytes,
        "map_extent_m2": round(float(grid.occupied_mask().size) * grid.resolution_m**2, 1),
        "map_png": str(png),
    }
    for k in range(1, replays):
        replay = Pipeline(settings, initial_pose=Pose2D.from_array(first.poses[0]), grid=grid)
        again = run_pass(replay, frames, f"replay {k}")
        report[f"replay_{k}"] = {
            "frontend": accuracy(again.poses, truth),
            "statuses": again.statuses,
            "map_bytes": replay.frontend.map.nbytes,
        }
    report["icp_chain"] = accuracy(chained_icp(frames), truth)
    report["peak_rss_mb"] = peak_rss_mb()
    return report


def run_starts(path: Path, settings: FrontendSettings, limit: int | None, starts: int) -> dict:
    """The log from each of its first `starts` keyframes: the ATE of every run. A log whose
    figure swings with where it starts is decided by a few scans (a fast turn, a corridor),
    not by the method's precision; the spread says how much one run's ATE can be trusted."""
    frames = log_keyframes(path, limit)
    ates, rechecked = [], []
    for k in range(starts):
        truth = poses_array([kf.true_pose for kf in frames[k:]])
        run = run_pass(Pipeline(settings), frames[k:], f"{path.name} from {k}")
        ates.append(accuracy(run.poses, truth)["ate_rmse_m"])
        rechecked.append(run.rechecked)
    return {"log": path.name, "method": settings.method,
            "recheck_ratio": settings.recheck_ratio, "ate_by_start_m": ates,
            "median_ate_m": float(np.median(ates)), "max_ate_m": float(np.max(ates)),
            "rechecked_scans_by_start": rechecked}


def fast_sim_config(
    world: str, duration_s: float, seed: int, mount: Pose2D = IDENTITY,
    perfect_odometry: bool = False, lidar: Lidar | None = None,
) -> SimConfig:
    """The simulator at 1.5 m/s and 180 deg/s; with perfect odometry, exact wheel odometry;
    `lidar` (beams, fov deg, range m, and maybe rate and bearing noise) instead of SimConfig's."""
    config = SimConfig(world=world, duration_s=duration_s, seed=seed, max_speed_mps=1.5,
                       max_yaw_rate_dps=180.0, mount=mount, **sim_lidar_fields(lidar))
    return replace(config, odom_scale_error=0.0, odom_yaw_noise=0.0) if perfect_odometry else config


def settings_for(method: str | None, recheck_ratio: float | None = None) -> FrontendSettings:
    """The documented front-end defaults, with `method` and `recheck_ratio` when given."""
    update: dict[str, object] = {"method": method} if method else {}
    if recheck_ratio is not None:
        update["recheck_ratio"] = recheck_ratio
    return default_settings().model_copy(update=update)


def run_sim(
    settings: FrontendSettings,
    duration_s: float,
    seed: int,
    mount: Pose2D = IDENTITY,
    world: str = "rooms",
    perfect_odometry: bool = False,
    lidar: Lidar | None = None,
) -> dict:
    """ATE of the robot's poses on the simulator at 1.5 m/s and 180 deg/s, with and without
    deskewing (and with the lidar's mount ignored, when it has one), and the CPU time per scan.
    With perfect odometry, whatever error remains is the matching's own."""
    config = fast_sim_config(world, duration_s, seed, mount, perfect_odometry, lidar)
    frames = list(simulate(config))
    truth = poses_array([SIM_MAP_FROM_WORLD * f.true_pose for f in frames])
    report: dict = {"scans": len(frames), "speed_mps": 1.5, "yaw_rate_dps": 180.0,
                    "world": world, "perfect_odometry": perfect_odometry,
                    "lidar": lidar_report(config),
                    "method": settings.method, "recheck_ratio": settings.recheck_ratio,
                    "mount": mount.to_array().tolist()}
    runs = {"deskewed": (True, mount), "raw": (False, mount)}
    if mount != IDENTITY:
        runs["mount_ignored"] = (True, IDENTITY)
    for name, (enabled, declared) in runs.items():
        pipeline = Pipeline(settings, deskew_enabled=enabled,
                            initial_pose=Pose2D.from_array(truth[0]))
        poses = []
        statuses: dict[str, int] = {}
        cpu0 = time.process_time()
        for frame in frames:
            for sample in frame.odometry:
                pipeline.add_odometry(sample)
            est = pipeline.process(replace(frame.scan, mount=declared)).estimate
            poses.append(est.pose)
            statuses[str(est.status)] = statuses.get(str(est.status), 0) + 1
        cpu_ms_per_scan = (time.process_time() - cpu0) * 1e3 / len(frames)
        estimate = poses_array(poses)
        heading = normalize_angles(estimate[:, 2] - truth[:, 2])
        report[name] = {
            **accuracy(estimate, truth),
            "max_position_error_m": float(np.max(np.hypot(*(estimate - truth)[:, :2].T))),
            "max_heading_error_deg": float(np.degrees(np.max(np.abs(heading)))),
            "final_position_error_m": float(np.hypot(*(estimate - truth)[-1, :2])),
            "final_heading_error_deg": float(np.degrees(heading[-1])),
            "statuses": statuses,
            "cpu_ms_per_scan": cpu_ms_per_scan,
        }
    report["peak_rss_mb"] = peak_rss_mb()
    return report


def parse_mount(text: str) -> Pose2D:
    """'x_m,y_m,yaw_deg' -> Pose2D (yaw in radians)."""
    try:
        x, y, yaw_deg = (float(v) for v in text.split(","))
        return Pose2D(x, y, math.radians(yaw_deg))
    except ValueError as exc:
        raise argparse.ArgumentTypeError(f"mount must be X_M,Y_M,YAW_DEG, got {text!r}") from exc


def main(argv: list[str] | None = None) -> None:
    """Run the sim, starts or log benchmark the arguments choose and print its report as JSON."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, help="CARMEN log (.log or .log.gz)")
    parser.add_argument("--sim", action="store_true", help="simulator at fast motion instead")
    parser.add_argument("--limit", type=int, default=None, help="first N keyframes only")
    parser.add_argument("--replays", type=int, default=1, help="passes over the log (>= 1)")
    parser.add_argument("--starts", type=int, default=0,
                        help="instead: the log from each of its first N keyframes, every ATE")
    parser.add_argument("--method", default=None, help="scan-to-map method (default: settings)")
    parser.add_argument("--recheck-ratio", type=float, default=None,
                        help="the front end's recheck_ratio (default: settings; 0 = off)")
    parser.add_argument("--duration", type=float, default=30.0, help="sim seconds")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--mount", type=parse_mount, default=IDENTITY,
                        help="sim: the lidar's place on the robot, X_M,Y_M,YAW_DEG")
    parser.add_argument("--world", default="rooms", choices=sorted(WORLDS), help="sim world")
    parser.add_argument("--perfect-odometry", action="store_true",
                        help="sim: exact wheel odometry (the error left is the matching's)")
    add_lidar_option(parser)
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args(argv)
    settings = settings_for(args.method, args.recheck_ratio)
    if args.sim and args.lidar:
        try:
            fast_sim_config(args.world, args.duration, args.seed, lidar=args.lidar)
        except ValueError as exc:
            parser.error(str(exc))
    if args.sim:
        report = run_sim(settings, args.duration, args.seed, args.mount, args.world,
                         args.perfect_odometry, args.lidar)
    elif args.data is not None and args.starts > 0:
        report = run_starts(args.data, settings, args.limit, args.starts)
    elif args.data is not None:
        report = run_log(args.data, settings, args.limit, max(1, args.replays))
    else:
        parser.error("give --data PATH or --sim")
    if args.json:
        print(json.dumps(report, default=float))
        return
    print(json.dumps(report, indent=2, default=float))


if __name__ == "__main__":
    main()
