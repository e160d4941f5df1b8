"""Correlative matching benchmark: branch and bound vs the exhaustive search on real scan pairs.

Consecutive keyframes of a CARMEN log (target = scan i, source = scan i+1, guess = wheel
odometry), searched at 5 cm / 0.5 deg over +-1 m and +-30 deg. Reports whether branch and bound
returned exactly the exhaustive optimum on every pair, the time of each search (search alone:
the max-pool stack build counts for branch and bound; and end to end, field build included)
and the accuracy of csm and csm+gn against the corrected poses.

    python -m bench.csm [--data PATH] [--pairs 20] [--json] [--cpu]
"""

from __future__ import annotations

import argparse
import json
import math
import time
from pathlib import Path

import numpy as np
from scanflow.io.carmen import load_keyframes
from scanflow.maps.maxpool import MaxPoolStack
from scanflow.matching import match
from scanflow.matching.csm_search import build_candidates, search, stack_depth
from scanflow.matching.field_cost import points_field

from bench.data import corrected_log

RESOLUTION_M = 0.05
ANGULAR_STEP_RAD = math.radians(0.5)
LINEAR_M = 1.0
ANGULAR_RAD = math.radians(30.0)
WINDOW = {
    "linear_m": LINEAR_M,
    "angular_rad": ANGULAR_RAD,
    "resolution_m": RESOLUTION_M,
    "angular_resolution_rad": ANGULAR_STEP_RAD,
}


def default_log() -> Path:
    """The corrected Intel log in the data directory (it may be missing)."""
    return corrected_log("intel")


def existing_log(path: Path | None) -> Path:
    """`path`, or the default log, or exit with a clear message when it is missing."""
    log = path or default_log()
    if not log.exists():
        raise SystemExit(f"log not found: {log} (set --data or SCANFLOW_DATA_DIR)")
    return log


# Wall time by default; --cpu times this process's CPU instead (steadier on a shared machine).
CLOCKS = {"wall": time.perf_counter, "cpu": time.process_time}
clock = CLOCKS["wall"]


def timed(fn, *args, **kwargs):  # type: ignore[no-untyped-def]
    """(fn(*args, **kwargs), its duration in s on the current `clock`)."""
    t0 = clock()
    out = fn(*args, **kwargs)
    return out, clock() - t0


def search_times(source: np.ndarray, target: np.ndarray, guess) -> tuple[float, float, bool]:  # type: ignore[no-untyped-def]
    """(branch-and-bound s incl. max-pool build, exhaustive s, same optimum) on a shared field."""
    field = points_field(target, RESOLUTION_M, RESOLUTION_M)
    depth = stack_depth(round(LINEAR_M / RESOLUTION_M))
    t0 = clock()
    stack = MaxPoolStack.from_values(field.spec, field.values, depth)
    cand = build_candidates(source, stack, guess, LINEAR_M, ANGULAR_RAD, ANGULAR_STEP_RAD)
    fast = search(cand, exhaustive=False)
    t_bnb = clock() - t0
    ref, t_exh = timed(search, cand, True)
    return t_bnb, t_exh, fast == ref


def run(log: Path, pairs: int) -> dict[str, object]:
    """Branch and bound vs exhaustive on up to `pairs` consecutive keyframe pairs spread over
    the log: agreement, median times (ms), speedups, csm and csm+gn success rates."""
    frames = load_keyframes(log)
    step = max((len(frames) - 1) // pairs, 1)
    idx = list(range(0, len(frames) - 1, step))[:pairs]
    # Compile (or load) the numba kernels outside the timings.
    a, b = frames[0], frames[1]
    match(b.scan, a.scan, b.odom_pose.relative_to(a.odom_pose), method="csm", **WINDOW)
    rows = []
    for i in idx:
        a, b = frames[i], frames[i + 1]
        guess = b.odom_pose.relative_to(a.odom_pose)
        truth = b.true_pose.relative_to(a.true_pose)
        src, tgt = b.scan.robot_points(), a.scan.robot_points()
        t_bnb, t_exh, same_search = search_times(src, tgt, guess)
        fast, tf = timed(match, src, tgt, guess, method="csm", **WINDOW)
        ref, te = timed(match, src, tgt, guess, method="csm_exhaustive", **WINDOW)
        refined = match(src, tgt, guess, method="csm", refine="gn", **WINDOW)
        errs = [r.pose.relative_to(truth) for r in (fast, refined)]
        rows.append(
            {
                "same": same_search and fast.pose == ref.pose and fast.score == ref.score,
                "search_bnb_s": t_bnb,
                "search_exhaustive_s": t_exh,
                "match_bnb_s": tf,
                "match_exhaustive_s": te,
                "err": [(e.translation_norm(), abs(e.theta)) for e in errs],
            }
        )

    def med(key: str) -> float:
        return float(np.median([r[key] for r in rows]))

    def success(k: int, t_m: float, r_deg: float) -> float:
        ok = [r["err"][k][0] <= t_m and r["err"][k][1] <= math.radians(r_deg) for r in rows]
        return float(np.mean(ok))

    return {
        "log": log.name,
        "clock": "cpu" if clock is CLOCKS["cpu"] else "wall",
        "pairs": len(rows),
        "bnb_equals_exhaustive": int(sum(r["same"] for r in rows)),
        "search_bnb_ms_median": 1e3 * med("search_bnb_s"),
        "search_exhaustive_ms_median": 1e3 * med("search_exhaustive_s"),
        "search_speedup_median": float(
            np.median([r["search_exhaustive_s"] / r["search_bnb_s"] for r in rows])
        ),
        "match_bnb_ms_median": 1e3 * med("match_bnb_s"),
        "match_exhaustive_ms_median": 1e3 * med("match_exhaustive_s"),
        "match_speedup_median": float(
            np.median([r["match_exhaustive_s"] / r["match_bnb_s"] for r in rows])
        ),
        "csm_success_5cm_0.5deg": success(0, 0.05, 0.5),
        "csm_success_10cm_1deg": success(0, 0.10, 1.0),
        "csm_gn_success_5cm_0.5deg": success(1, 0.05, 0.5),
        "csm_gn_success_10cm_1deg": success(1, 0.10, 1.0),
    }


def main() -> None:
    """Run the benchmark on --data (default: the Intel log) and print the figures."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=None, help="CARMEN log (default: intel)")
    parser.add_argument("--pairs", type=int, default=20)
    parser.add_argument("--json", action="store_true")
    parser.add_argument("--cpu", action="store_true", help="time process CPU, not wall clock")
    args = parser.parse_args()
    global clock
    clock = CLOCKS["cpu" if args.cpu else "wall"]
    result = run(existing_log(args.data), args.pairs)
    if args.json:
        print(json.dumps(result, indent=2))
    else:
        for key, value in result.items():
            print(f"{key:32s} {value:.3f}" if isinstance(value, float) else f"{key:32s} {value}")


if __name__ == "__main__":
    main()
