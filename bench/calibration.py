"""Mount calibration (`scanflow.calibration`): how well the lidar's mount comes back.

Simulator (`--sim`): the built-in lidar mounted at several poses on a robot driven slowly
(0.3 m/s, 30 deg/s: the scans stay motion-distorted, as a real slow drive's), wheel odometry
with its simulated scale and yaw errors, every `--step`-th scan paired with the next chosen
one. Per mount: the estimate's error against the true mount. The baseline is not calibrating
at all, i.e. taking the mount as the robot's origin (error = the mount itself).

Real logs (`--data LOG`): no true mount is known, so the figure is agreement: the estimate
from the whole log next to those from its first and second halves, with the fit's own
uncertainty and residual.

    python -m bench.calibration --sim --json
    python -m bench.calibration --data ../shared/data/intel-corrected.log.gz --json
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

from scanflow.calibration import MountEstimate, estimate_mount, paired_motions
from scanflow.geometry import IDENTITY, Pose2D
from scanflow.io.carmen import load_keyframes
from scanflow.pipeline import DeskewStage
from scanflow.sim import SimConfig, simulate
from tqdm import tqdm

SIM_MOUNTS = {
    "front, turned 20 deg": Pose2D(0.3, -0.1, math.radians(20.0)),
    "rear-facing": Pose2D(-0.25, 0.0, math.pi),
    "side, 90 deg": Pose2D(0.0, 0.2, math.pi / 2),
    "centre": IDENTITY,
}


def describe(estimate: MountEstimate, seconds: float) -> dict:
    """An estimate as figures: status, mount and std (m, m, deg), residual, pairs, `seconds`."""
    m = estimate.mount
    return {
        "status": str(estimate.status),
        "mount_m_m_deg": [m.x, m.y, math.degrees(m.theta)],
        "std_m_m_deg": [*estimate.std_xy_m, math.degrees(estimate.std_yaw_rad)],
        "residual_rms_m": estimate.residual_rms_m,
        "pairs_used": estimate.pairs_used,
        "pairs_given": estimate.pairs_given,
        "seconds": seconds,
    }


def sim_case(mount: Pose2D, duration_s: float, step: int, seed: int) -> dict:
    """Calibrate one simulated mount; errors of the estimate and of not calibrating."""
    config = SimConfig(duration_s=duration_s, seed=seed, mount=mount, max_speed_mps=0.3,
                       max_yaw_rate_dps=30.0)
    buffer = DeskewStage()  # the odometry buffer only
    points, odom = [], []
    for k, frame in enumerate(simulate(config)):
        for sample in frame.odometry:
            buffer.add_odometry(sample)
        # Mid-sweep: the time a motion-distorted scan is, on average, taken at.
        pose = buffer.odometry_pose_at(0.5 * (frame.scan.stamp_s + frame.scan.end_stamp_s))
        if k % step == 0 and pose is not None:
            points.append(frame.scan.points())  # the lidar's own frame
            odom.append(pose)
    t0 = time.perf_counter()
    estimate = estimate_mount(*paired_motions(points, odom))
    report = describe(estimate, time.perf_counter() - t0)
    error = estimate.mount.relative_to(mount)
    report["error_m"] = error.translation_norm()
    report["error_deg"] = abs(math.degrees(error.theta))
    report["uncalibrated_error_m"] = mount.translation_norm()
    report["uncalibrated_error_deg"] = abs(math.degrees(mount.theta))
    return report


def log_case(path: Path) -> dict:
    """The whole log's estimate and its halves'."""
    frames = load_keyframes(path)
    half = len(frames) // 2
    report = {"log": path.name, "keyframes": len(frames)}
    for name, part in (("all", frames), ("first_half", frames[:half]),
                       ("second_half", frames[half:])):
        t0 = time.perf_counter()
        pairs = paired_motions([kf.scan.points() for kf in part], [kf.odom_pose for kf in part])
        report[name] = describe(estimate_mount(*pairs), time.perf_counter() - t0)
    return report


def main(argv: list[str] | None = None) -> None:
    """Calibrate the simulated mounts or the log's and print the report as JSON."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    source = parser.add_mutually_exclusive_group(required=True)
    source.add_argument("--sim", action="store_true", help="simulated mounts")
    source.add_argument("--data", type=Path, help="CARMEN log (.log or .gz)")
    parser.add_argument("--duration", type=float, default=60.0, help="simulated seconds")
    parser.add_argument("--step", type=int, default=5, help="use every N-th simulated scan")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--json", action="store_true", help="print the figures as JSON")
    args = parser.parse_args(argv)
    if args.step < 1 or args.duration <= 0:
        parser.error("--step must be >= 1 and --duration > 0")
    if args.sim:
        report = {name: sim_case(mount, args.duration, args.step, args.seed)
                  for name, mount in tqdm(SIM_MOUNTS.items(), file=sys.stderr, leave=False)}
    else:
        report = log_case(args.data)
    print(json.dumps(report) if args.json else json.dumps(report, indent=1))


if __name__ == "__main__":
    main()
