"""What a map server's catch-up costs when the matcher (without loop closure) no longer keeps
the inserts it missed: the matcher's whole map and path (`MapStateMessage`), against the
baseline of the same inserts sent again one by one (what a gap within the matcher's last
`resend_inserts` costs).

    python -m bench.map_state [--data LOG] [--limit N] [--json]

A log's keyframes go through the in-process pipeline (the front end alone, as the services
track without loop closure), and each insert is kept as the matcher sends it. The gap is the
whole run. State: the matcher builds the message under its lock (the map as .npz and the path:
tracking waits meanwhile) and encodes it; the map server decodes it, reads the map and takes it
(`RobotMap.take_state`). Inserts: each encoded, decoded and inserted into a new map, as a
resend is. Both must end with the same map, which is checked.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path
from typing import Any

import numpy as np
from scanflow.maps.export import grid_from_npz_bytes
from scanflow.maps.occupancy import OccupancyGrid
from scanflow.pipeline import Pipeline
from scanflow.wire import MapInsertMessage, MapStateMessage, new_run

from bench.data import corrected_log, log_keyframes
from services.mapserver.robot import RobotMap
from services.matcher.recent import RecentInserts, map_state

ROBOT = "robot"


def run(path: Path, limit: int | None) -> dict[str, Any]:
    """The log's inserts taken as one MapStateMessage and resent one by one: bytes and times
    (ms) of each; asserts both end with the front end's map."""
    frames = log_keyframes(path, limit)
    pipeline = Pipeline()
    recent = RecentInserts(0, new_run())
    inserts: list[MapInsertMessage] = []
    for kf in frames:
        step = pipeline.process(kf.scan, kf.odom_pose)
        out, result = step.estimate, step.deskew
        recent.tracked(out.seq, out.inserted)
        if out.inserted:
            inserts.append(MapInsertMessage(
                ROBOT, out.seq, out.stamp_s, out.pose, result.points, result.no_return_points,
                result.mount, inserts[-1].seq if inserts else None,
            ))
    frontend = pipeline.frontend
    params = frontend.map.grid.params

    t0 = time.perf_counter()
    state = map_state(ROBOT, frontend, recent)
    build_s = time.perf_counter() - t0
    payload = state.encode()
    encode_s = time.perf_counter() - t0 - build_s
    t1 = time.perf_counter()
    decoded = MapStateMessage.decode(payload)
    robot = RobotMap(ROBOT, lambda: OccupancyGrid(params))
    robot.take_state(decoded, grid_from_npz_bytes(decoded.map_npz, "the state"), -1)
    take_s = time.perf_counter() - t1

    t2 = time.perf_counter()
    payloads = [m.encode() for m in inserts]
    inserts_encode_s = time.perf_counter() - t2
    t3 = time.perf_counter()
    again = RobotMap(ROBOT, lambda: OccupancyGrid(params))
    for data in payloads:
        again.insert(MapInsertMessage.decode(data))
    inserts_take_s = time.perf_counter() - t3

    for grid in (robot.map.grid, again.map.grid):
        np.testing.assert_array_equal(grid.log_odds, frontend.map.grid.log_odds)
    return {
        "log": path.name,
        "scans": len(frames),
        "inserts": len(inserts),
        "map_cells": int(frontend.map.grid.log_odds.size),
        "state": {
            "bytes": len(payload),
            "build_ms_under_lock": 1e3 * build_s,
            "encode_ms": 1e3 * encode_s,
            "take_ms": 1e3 * take_s,
        },
        "inserts_again": {
            "bytes": sum(len(p) for p in payloads),
            "encode_ms": 1e3 * inserts_encode_s,
            "take_ms": 1e3 * inserts_take_s,
        },
    }


def main(argv: list[str] | None = None) -> None:
    """Run the benchmark on --data (default: the Intel log) and print its report as JSON."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=corrected_log("intel"))
    parser.add_argument("--limit", type=int, default=None, help="first N keyframes only")
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args(argv)
    report = run(args.data, args.limit)
    print(json.dumps(report, default=float, indent=None if args.json else 2))


if __name__ == "__main__":
    main()
