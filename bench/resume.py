"""What a restarted matcher pays to resume a robot's loop closure, and up to how long a run it
can: the map server's answer (`ResumeMessage`: the path and the keyframes; the map, under 1 MB
on these logs, left out) built and encoded, sent through a router as the reply to one query,
decoded, and turned into the back end (`Mapper(..., SavedRun)`), for runs of growing length.

    python -m bench.resume [--data LOG] [--keyframes 1916,5000,20000,60000] [--json]

The keyframes are a log's scans (every `--every`-th record) at their corrected poses, repeated
with fresh seqs and stamps up to each count; the path holds `--scans-per-keyframe` poses per
keyframe. A run whose message the wire refuses is reported with the error.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path
from typing import Any

import numpy as np
import zenoh
from scanflow.backend import Mapper, SavedRun
from scanflow.config import BackendSettings, FrontendSettings, ZenohSettings
from scanflow.frontend import Frontend
from scanflow.io.carmen import Keyframe, load_keyframes
from scanflow.wire import MapInsertMessage, ResumeMessage

from bench.data import corrected_log
from services.common.keyframes import scan_nodes
from services.common.launch import free_port
from services.common.zsession import open_session
from services.mapserver.keyframes import Keyframes

KEY = "scanflow-bench/keyframes"
ROBOT = "robot"


def kept_keyframes(frames: list[Keyframe], count: int) -> Keyframes:
    """The map server's keyframes of a run `count` keyframes long: the log's, over and over."""
    kept = Keyframes()
    period = frames[-1].scan.stamp_s - frames[0].scan.stamp_s + 1.0
    for i in range(count):
        lap, frame = divmod(i, len(frames))
        scan = frames[frame].scan
        kept.add(MapInsertMessage(
            ROBOT, 3 * i, scan.stamp_s + lap * period, frames[frame].true_pose, scan.points(),
            np.zeros((0, 2)), scan.mount,
        ))
    return kept


def through_router(payload: bytes) -> tuple[bytes | None, str | None, float]:
    """`payload` as the one reply to a query across a router: what came, any error, seconds."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    router = open_session(ZenohSettings(mode="router", listen=[endpoint], connect=[]))
    server = open_session(ZenohSettings(connect=[endpoint]))
    client = open_session(ZenohSettings(connect=[endpoint]))
    try:
        server.declare_queryable(KEY, lambda q: q.reply(KEY, payload))
        time.sleep(0.5)  # the queryable reaches the router
        t0 = time.perf_counter()
        got, error = None, None
        for reply in client.get(KEY, timeout=120.0, consolidation=zenoh.ConsolidationMode.NONE):
            result = reply.result  # a Sample, or the ReplyError of a failed reply
            if isinstance(result, zenoh.ReplyError):
                error = result.payload.to_string()
            else:
                got = result.payload.to_bytes()
        return got, error, time.perf_counter() - t0
    finally:
        for session in (client, server, router):
            session.close()


def run(frames: list[Keyframe], count: int, scans_per_keyframe: int) -> dict[str, Any]:
    """One run length: sizes, and the time of every step a resume takes."""
    kept = kept_keyframes(frames, count)
    row: dict[str, Any] = {"keyframes": count, "points": sum(len(n.points) for n in kept.nodes)}
    scans = count * scans_per_keyframe
    stamps, path = np.arange(scans, dtype=np.float64), np.zeros((scans, 3))
    t0 = time.perf_counter()
    try:
        payload = ResumeMessage(ROBOT, 0, b"", stamps, path, kept.message(ROBOT)).encode()
    except ValueError as exc:  # MessageError: over the wire's limit
        row["refused"] = str(exc)
        return row
    row["build_encode_ms"] = round((time.perf_counter() - t0) * 1e3, 1)
    row["message_mib"] = round(len(payload) / 2**20, 1)
    got, error, sent_s = through_router(payload)
    row["router_ms"] = round(sent_s * 1e3, 1)
    if got is None:
        row["refused"] = error or "no reply"
        return row
    t0 = time.perf_counter()
    resumed = ResumeMessage.decode(got)
    assert resumed.keyframes is not None
    nodes = scan_nodes(resumed.keyframes)
    row["decode_nodes_ms"] = round((time.perf_counter() - t0) * 1e3, 1)
    t0 = time.perf_counter()
    kept_seqs, kept_poses = resumed.keyframes.seqs.tolist(), resumed.keyframes.poses
    saved = SavedRun(nodes, kept_seqs, kept_poses, resumed.stamps_s, resumed.poses)
    mapper = Mapper(Frontend(FrontendSettings()), BackendSettings(loop_closure=True), saved)
    row["mapper_ms"] = round((time.perf_counter() - t0) * 1e3, 1)
    row["resumed_keyframes"] = mapper.graph.node_count
    return row


def main() -> None:
    """Measure the resume for each --keyframes count from the --data log's scans; print it."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=corrected_log("freiburg-079"))
    parser.add_argument("--keyframes", default="1916,5000,20000,60000")
    parser.add_argument("--every", type=int, default=1, help="take every k-th record")
    parser.add_argument("--scans-per-keyframe", type=int, default=3)
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args()
    frames = load_keyframes(args.data)[:: args.every]
    counts = [int(c) for c in args.keyframes.split(",")]
    report = {
        "log": args.data.name,
        "beams": len(frames[0].scan.ranges_m),
        "runs": [run(frames, n, args.scans_per_keyframe) for n in counts],
    }
    if args.json:
        print(json.dumps(report, indent=2))
        return
    print(f"{report['log']} ({report['beams']} beams)")
    for r in report["runs"]:
        print("  " + ", ".join(f"{k} {v}" for k, v in r.items()))


if __name__ == "__main__":
    main()
