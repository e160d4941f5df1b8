"""Deskewing accuracy and speed on the built-in simulator.

`python -m bench.deskew [--json] [--repeats N]`. Accuracy: mean/max beam error against the
simulator's undistorted ground truth, next to the uncompensated error. Speed: median and p90 wall
time of one `deskew` call (odometry interpolation included) on fresh scans, plus CPU time (which a
shared machine inflates less), and on the same scans with a mounted lidar (`MOUNT`).
`accuracy_run` is the hook to extend with the downstream match error.
"""

from __future__ import annotations

import argparse
import json
import math
import time
from collections.abc import Callable, Mapping
from dataclasses import replace

import numpy as np
from scanflow.deskew import ConstantVelocityModel, OdometryBuffer, PoseSource, deskew
from scanflow.geometry import Pose2D
from scanflow.scan import LaserScan
from scanflow.sim import ConstantVelocityTrajectory, SimConfig, SimFrame, simulate

SPEED_MPS = 1.0
YAW_RATE_RPS = math.pi  # 180 deg/s
MOUNT = Pose2D(0.3, 0.1, 0.2)  # a lidar off the robot's origin: each beam's pose composed with it


def _config(beams: int, duration_s: float) -> SimConfig:
    return SimConfig(
        world="rooms",
        duration_s=duration_s,
        beams=beams,
        fov_deg=360,
        rate_hz=10.0,
        odom_rate_hz=50.0,
        max_speed_mps=1.5,
        max_yaw_rate_dps=180,
        range_noise_m=0.0,  # quiet: no range noise, dropouts or odometry errors
        dropout_prob=0.0,
        odom_scale_error=0.0,
        odom_yaw_noise=0.0,
    )


def _fast_circle() -> ConstantVelocityTrajectory:
    """1 m/s forward while turning at 180 deg/s: a 0.32 m circle in the middle of a room."""
    return ConstantVelocityTrajectory(Pose2D(7.5, 2.0, 0.0), SPEED_MPS, YAW_RATE_RPS)


def accuracy_run(
    frames: list[SimFrame],
    make_source: Callable[[SimFrame], PoseSource | None],
    warmup: int = 0,
) -> dict[str, object]:
    """Beam errors (m) against ground truth with and without deskewing over the frames.

    `make_source(frame)` returns the pose source to use for that frame (it may keep state); the
    first `warmup` frames only feed it.
    Extend here with the matcher's error with and without deskewing once matching lands.
    """
    raw, fixed, used = [], [], set()
    for index, frame in enumerate(frames):
        source = make_source(frame)
        if index < warmup:
            continue
        result = deskew(frame.scan, source)
        used.add(result.source_used)
        raw.append(np.linalg.norm(frame.scan.robot_points() - frame.true_points, axis=1))
        fixed.append(np.linalg.norm(result.points - frame.true_points, axis=1))
    raw_m, fixed_m = np.concatenate(raw), np.concatenate(fixed)
    return {
        "uncompensated_mean_mm": 1e3 * float(raw_m.mean()),
        "uncompensated_max_mm": 1e3 * float(raw_m.max()),
        "deskewed_mean_mm": 1e3 * float(fixed_m.mean()),
        "deskewed_max_mm": 1e3 * float(fixed_m.max()),
        "scans": len(raw),
        "sources_used": sorted(used),
    }


def _odometry_feeder(max_age_s: float = 2.0) -> Callable[[SimFrame], PoseSource]:
    buffer = OdometryBuffer(max_age_s=max_age_s)

    def feed(frame: SimFrame) -> PoseSource:
        for sample in frame.odometry:
            buffer.add_odometry(sample)
        return buffer

    return feed


def _velocity_feeder() -> Callable[[SimFrame], PoseSource]:
    """The model sees the true pose at each previous scan stamp (what a tracker would estimate)."""
    model = ConstantVelocityModel()
    previous: list[SimFrame] = []

    def feed(frame: SimFrame) -> PoseSource:
        if previous:
            model.update(previous[-1].scan.stamp_s, previous[-1].true_pose)
        previous[:] = [frame]
        return model

    return feed


def _timings_us(
    scans: list[LaserScan], source: PoseSource, repeats: int, fresh: bool
) -> dict[str, float]:
    """Per-call wall and CPU time; `fresh` scans also pay for `LaserScan.valid_mask` (first use)."""
    wall, cpu = [], []
    for _ in range(repeats):
        batch = [s.with_ranges(s.ranges_m) for s in scans] if fresh else scans
        for scan in batch:
            w0, c0 = time.perf_counter_ns(), time.thread_time_ns()
            deskew(scan, source)
            c1, w1 = time.thread_time_ns(), time.perf_counter_ns()
            wall.append(w1 - w0)
            cpu.append(c1 - c0)
    wall_us, cpu_us = np.array(wall) / 1e3, np.array(cpu) / 1e3
    return {
        "median_us": float(np.median(wall_us)),
        "p90_us": float(np.percentile(wall_us, 90)),
        "cpu_median_us": float(np.median(cpu_us)),
        "calls": int(wall_us.size),
    }


def speed(beams: int, repeats: int) -> dict[str, dict[str, float]]:
    """Per-call time of deskew with a filled odometry buffer, on scans of the fast circle."""
    frames = list(simulate(_config(beams, 1.0), _fast_circle()))
    buffer = OdometryBuffer(max_age_s=5.0)
    for frame in frames:
        for sample in frame.odometry:
            buffer.add_odometry(sample)
    scans = [f.scan for f in frames[1:-1]]
    mounted = [replace(s, mount=MOUNT) for s in scans]
    for scan in scans + mounted:
        deskew(scan, buffer)  # compile, warm up, cache each scan's validity mask
    return {
        "deskew_only": _timings_us(scans, buffer, repeats, fresh=False),
        "with_scan_validity_mask": _timings_us(scans, buffer, repeats, fresh=True),
        "deskew_only_mounted_lidar": _timings_us(mounted, buffer, repeats, fresh=False),
    }


def run(repeats: int = 200, duration_s: float = 5.0) -> dict[str, Mapping[str, object]]:
    """The setup, the beam errors with odometry and with the constant-velocity model, and the
    speed of deskew at 360 and 1440 beams."""
    frames = list(simulate(_config(360, duration_s), _fast_circle()))
    return {
        "setup": {
            "speed_mps": SPEED_MPS,
            "yaw_rate_dps": math.degrees(YAW_RATE_RPS),
            "rate_hz": 10.0,
            "beams": 360,
            "odometry_rate_hz": 50.0,
            "odometry_noise": "none",
            "simulated_s": duration_s,
        },
        "odometry_accuracy": accuracy_run(frames, _odometry_feeder()),
        "constant_velocity_accuracy": accuracy_run(frames, _velocity_feeder(), warmup=2),
        "speed_360_beams": speed(360, repeats),
        "speed_1440_beams": speed(1440, max(repeats // 4, 1)),
    }


def main() -> None:
    """Run the benchmark and print its figures (as JSON with --json)."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--json", action="store_true", help="print the figures as JSON")
    parser.add_argument("--repeats", type=int, default=200, help="passes over the scans timed")
    parser.add_argument("--duration", type=float, default=5.0, help="simulated seconds")
    args = parser.parse_args()
    figures = run(args.repeats, args.duration)
    if args.json:
        print(json.dumps(figures, indent=2))
        return
    for name, values in figures.items():
        print(f"{name}:")
        for key, value in values.items():
            print(f"  {key}: {value:.4g}" if isinstance(value, float) else f"  {key}: {value}")


if __name__ == "__main__":
    main()
