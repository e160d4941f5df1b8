"""Deskewing downstream: match error on fast simulated motion with and without deskewing.

`python -m bench.deskew_downstream [--duration S] [--seed N] [--json]`

For each motion level of the simulator (speed, yaw rate), consecutive scans are matched
scan-to-scan (`--method`, default icp; guess = odometry increment) from the raw (distorted)
points and from the deskewed points, and the error of the estimated motion against the true
motion between the scan stamps is summarised (median and p95, translation mm and rotation
deg). The front end's ATE on the same run, with and without deskewing, is given next to it.
"""

from __future__ import annotations

import argparse
import json
import math

import numpy as np
from numpy.typing import NDArray
from scanflow.frontend import default_settings
from scanflow.geometry import Pose2D
from scanflow.matching import match
from scanflow.pipeline import DeskewStage
from scanflow.sim import SimConfig, simulate

from bench.frontend import run_sim

LEVELS = ((0.5, 45.0), (1.0, 90.0), (1.5, 180.0))


def pair_errors(speed_mps: float, yaw_dps: float, duration_s: float, seed: int,
                method: str) -> dict[str, dict[str, float]]:
    """Scan-to-scan errors of consecutive scans at one motion level from the raw and from the
    deskewed points (guess: the odometry step), summarised per kind."""
    config = SimConfig(duration_s=duration_s, seed=seed, max_speed_mps=speed_mps,
                       max_yaw_rate_dps=yaw_dps)
    stage = DeskewStage()
    errors: dict[str, list[tuple[float, float]]] = {"raw": [], "deskewed": []}
    # The last scan's points by kind, true pose and odometry pose, when it had one.
    previous: tuple[dict[str, NDArray[np.float64]], Pose2D, Pose2D] | None = None
    for frame in simulate(config):
        for sample in frame.odometry:
            stage.add_odometry(sample)
        odom_pose = stage.odometry_pose_at(frame.scan.stamp_s)
        points = {"raw": frame.scan.robot_points(), "deskewed": stage.process(frame.scan).points}
        if previous is not None and odom_pose is not None:
            before, before_truth, before_odom = previous
            truth = frame.true_pose.relative_to(before_truth)
            odom_step = odom_pose.relative_to(before_odom)
            for kind in ("raw", "deskewed"):
                result = match(points[kind], before[kind], odom_step, method=method)
                err = result.pose.relative_to(truth)
                errors[kind].append((err.translation_norm(), abs(math.degrees(err.theta))))
        previous = None if odom_pose is None else (points, frame.true_pose, odom_pose)
    return {kind: _summary(np.array(v)) for kind, v in errors.items()}


def _summary(errors: np.ndarray) -> dict[str, float]:
    return {
        "pairs": len(errors),
        "trans_median_mm": float(1000 * np.median(errors[:, 0])),
        "trans_p95_mm": float(1000 * np.percentile(errors[:, 0], 95)),
        "rot_median_deg": float(np.median(errors[:, 1])),
        "rot_p95_deg": float(np.percentile(errors[:, 1], 95)),
    }


def main(argv: list[str] | None = None) -> None:
    """Match errors at each motion level and the front end's ATE at fast motion; print them."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--duration", type=float, default=20.0, help="simulated seconds per level")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--method", default="icp", help="scan-to-scan method")
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args(argv)
    levels = [
        (speed, yaw, pair_errors(speed, yaw, args.duration, args.seed, args.method))
        for speed, yaw in LEVELS
    ]
    fast = run_sim(default_settings(), args.duration, args.seed)
    report = {
        "method": args.method,
        "duration_s": args.duration,
        "levels": [
            {"speed_mps": speed, "yaw_rate_dps": yaw, "scan_to_scan": s2s}
            for speed, yaw, s2s in levels
        ],
        "frontend_fast": fast,
    }
    if args.json:
        print(json.dumps(report))
        return
    for speed, yaw, s2s in levels:
        print(f"{speed} m/s, {yaw} deg/s: "
              f"raw {s2s['raw']['trans_median_mm']:.1f} mm / {s2s['raw']['rot_median_deg']:.2f} deg"
              f", deskewed {s2s['deskewed']['trans_median_mm']:.1f} mm / "
              f"{s2s['deskewed']['rot_median_deg']:.2f} deg (median)")
    print(f"front end ATE at 1.5 m/s, 180 deg/s: deskewed {fast['deskewed']['ate_rmse_m']:.3f} m, "
          f"raw {fast['raw']['ate_rmse_m']:.3f} m")


if __name__ == "__main__":
    main()
