"""Where the map ends: scan-to-map matchers on the map built so far against a complete map.

`python -m bench.map_edge [--world rooms] [--duration 20] [--methods gn,gn+plicp] [--json]`

The simulator at 1.5 m/s and 180 deg/s with exact wheel odometry; each scan deskewed by the
pipeline's deskew stage. Every other scan is matched from its TRUE pose, once on the map of the
scans before it (inserted at their true poses: what a front end has, with walls it is seeing for
the first time) and once on the map of every scan of the run (a complete map). The errors are
the matcher's own, with no drift and no wrong guess in them: their mean is a bias, their
spread the precision. A method sharp on the complete map but not on the map so far is pulled by
the map's edges (BENCHMARKS.md, "Front end").
"""

from __future__ import annotations

import argparse
import json
import math

import numpy as np
from numpy.typing import NDArray
from scanflow.frontend import default_settings
from scanflow.frontend.tracker import insert_scan, occupancy_params
from scanflow.geometry import Pose2D
from scanflow.maps.matching_map import MatchingMap
from scanflow.maps.occupancy import OccupancyGrid
from scanflow.matching import match
from scanflow.pipeline import Pipeline
from scanflow.sim import WORLDS, simulate

from bench.frontend import SIM_MAP_FROM_WORLD, fast_sim_config


def deskewed_scans(world: str, duration_s: float) -> tuple[list[NDArray[np.float64]], list[Pose2D]]:
    """Each sweep's deskewed endpoints (robot frame) and its true pose in the map frame."""
    frames = list(simulate(fast_sim_config(world, duration_s, 0, perfect_odometry=True)))
    truth = [SIM_MAP_FROM_WORLD * f.true_pose for f in frames]
    pipeline = Pipeline(default_settings(), initial_pose=truth[0])
    points = []
    for frame in frames:
        for sample in frame.odometry:
            pipeline.add_odometry(sample)
        points.append(np.asarray(pipeline.process(frame.scan).deskew.points))
    return points, truth


def summary(errors: NDArray[np.float64]) -> dict[str, float]:
    """Mean and standard deviation of (x, y) in mm and theta in degrees, in the robot's frame."""
    out = {}
    for column, (name, scale) in enumerate((("x", 1000.0), ("y", 1000.0), ("theta", 1.0))):
        unit = "deg" if name == "theta" else "mm"
        out[f"{name}_mean_{unit}"] = float(errors[:, column].mean() * scale)
        out[f"{name}_std_{unit}"] = float(errors[:, column].std() * scale)
    return out


def run(world: str, duration_s: float, methods: list[str]) -> dict:
    """Every other scan matched from its true pose on the map so far and on the complete map:
    per method and map, the errors' mean and std."""
    points, truth = deskewed_scans(world, duration_s)
    params = occupancy_params(default_settings())
    complete = MatchingMap(OccupancyGrid(params))
    for scan, pose in zip(points, truth, strict=True):
        insert_scan(complete, scan, pose)
    so_far = MatchingMap(OccupancyGrid(params))
    errors: dict[str, dict[str, list]] = {m: {"so_far": [], "complete": []} for m in methods}
    for k, (scan, pose) in enumerate(zip(points, truth, strict=True)):
        if k > 0 and k % 2 == 0:
            for method in methods:
                for name, target in (("so_far", so_far), ("complete", complete)):
                    off = pose.inverse() * match(scan, target, pose, method=method).pose
                    errors[method][name].append((off.x, off.y, math.degrees(off.theta)))
        insert_scan(so_far, scan, pose)
    return {
        "world": world, "duration_s": duration_s, "scans": len(points),
        "matches": len(errors[methods[0]]["so_far"]),
        "methods": {
            method: {name: summary(np.array(rows)) for name, rows in by_map.items()}
            for method, by_map in errors.items()
        },
    }


def main(argv: list[str] | None = None) -> None:
    """Run the benchmark and print its report as JSON (one line with --json)."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--world", default="rooms", choices=sorted(WORLDS), help="sim world")
    parser.add_argument("--duration", type=float, default=20.0, help="sim seconds")
    parser.add_argument("--methods", default="gn,gn+plicp", help="comma-separated")
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args(argv)
    report = run(args.world, args.duration, args.methods.split(","))
    print(json.dumps(report, indent=None if args.json else 2))


if __name__ == "__main__":
    main()
