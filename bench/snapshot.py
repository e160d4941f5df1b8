"""What a map server's snapshot costs as a loop-closing run grows: the first snapshot, the next
ones (every `SCANFLOW_MAPSERVER_SNAPSHOT_INTERVAL_S`, 10 s, while the robot maps: here 100 more
keyframes each), the files on disk and the load at a restart.

    python -m bench.snapshot [--data LOG] [--keyframes 1916,5000,20000,60000] [--json]

The keyframes are a log's scans at their corrected poses, repeated with fresh seqs up to each
count (as `bench.resume`); the map is the log's first 300 scans. Every step runs in a fresh
directory.
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np
from scanflow.io.carmen import Keyframe, load_keyframes
from scanflow.maps.occupancy import OccupancyGrid, OccupancyParams

from bench.data import corrected_log
from bench.resume import kept_keyframes
from services.mapserver.snapshot import PER_FILE, Snapshot, load_snapshots, save_snapshot

ROBOT = "robot"
GROWTH = 100  # keyframes a robot adds between two snapshots (10 s at 0.1 s per keyframe)


def map_of(frames: list[Keyframe], scans: int) -> OccupancyGrid:
    """The occupancy grid of the first `scans` keyframes at their corrected sensor poses."""
    grid = OccupancyGrid(OccupancyParams())
    for frame in frames[:scans]:
        sensor = frame.true_pose * frame.scan.mount
        grid.insert_scan(sensor.transform_points(frame.scan.points()), [sensor.x, sensor.y])
    return grid


def disk_mib(folder: Path) -> float:
    """Total size of the files under `folder`, in MiB (one decimal)."""
    return round(sum(p.stat().st_size for p in folder.rglob("*") if p.is_file()) / 2**20, 1)


def run(
    frames: list[Keyframe], grid: OccupancyGrid, count: int, per_file: int = PER_FILE
) -> dict[str, Any]:
    """Snapshots of a run `count` keyframes long, then `GROWTH` keyframes longer (keyframes'
    scans `per_file` to a file)."""
    kept = kept_keyframes(frames, count + GROWTH)
    grown = kept.seqs, kept.nodes, kept.poses
    kept.seqs, kept.nodes, kept.poses = kept.seqs[:count], kept.nodes[:count], kept.poses[:count]
    row: dict[str, Any] = {"keyframes": count}
    with tempfile.TemporaryDirectory(prefix="scanflow-bench-") as tmp:
        folder = Path(tmp)

        def snapshot() -> float:
            path = np.zeros((3 * len(kept), 3))
            t0 = time.perf_counter()
            save_snapshot(folder, Snapshot(ROBOT, grid, path[:, 0], path, 1, kept), per_file)
            return round(time.perf_counter() - t0, 3)

        row["first_s"] = snapshot()
        kept.seqs, kept.nodes, kept.poses = grown
        row["next_s"] = snapshot()
        row["disk_mib"] = disk_mib(folder)
        t0 = time.perf_counter()
        (loaded,), skipped = load_snapshots(folder)
        row["load_s"] = round(time.perf_counter() - t0, 3)
        assert not skipped and loaded.keyframes is not None
        row["loaded_keyframes"] = len(loaded.keyframes)
    return row


def main() -> None:
    """Snapshot runs of each --keyframes count on the --data log; print their figures."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=corrected_log("freiburg-079"))
    parser.add_argument("--keyframes", default="1916,5000,20000,60000")
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args()
    frames = load_keyframes(args.data)
    grid = map_of(frames, 300)
    report = {
        "log": args.data.name,
        "runs": [run(frames, grid, int(n)) for n in args.keyframes.split(",")],
    }
    if args.json:
        print(json.dumps(report, indent=2))
        return
    print(report["log"])
    for r in report["runs"]:
        print("  " + ", ".join(f"{k} {v}" for k, v in r.items()))


if __name__ == "__main__":
    main()
