"""Scan matching on real logs (or simulated ones): every scanflow method next to the peers, on
the same pairs.

`python -m bench.matching (--data PATH | --sim WORLD) [--gap K] [--methods ...] [--peers ...]
[--limit N] [--stride S] [--start-step T] [--robust-pairs N] [--closure] [--repeats N] [--json]`

Pairs (i, i+K) of the log's keyframes, i stepping by K (K=1: each scan against the next; K=3:
every third scan) or by T (`--start-step 1` with K=3: every scan against the third after it,
so overlapping pairs), optionally every S-th pair and at most N pairs. Source = scan i+K, target =
scan i, so a match estimates T_i_(i+K). Ground truth: true_pose_i^-1 * true_pose_j; initial
guess: the wheel odometry odom_pose_i^-1 * odom_pose_j. Error: translation norm and |rotation|
of gt^-1 * estimate.
Simulated pairs (`--sim WORLD`, e.g. `campus` with `--lidar 181,180,80`): every `--sim-every`-th
sweep of a seeded run of the built-in simulator is a keyframe, its points exactly deskewed (range
noise and dropouts kept), its truth exact and its guess the simulated wheel odometry (1 % scale
error, yaw noise). A real log's corrected poses carry a few cm and ~0.3-0.6 deg of their own
error; here the success rates and percentiles are the matchers' own, and worlds and sensors
that the three logs lack (open space, far sparse returns, other beam layouts) can be tried.
Robustness: on a seeded subset of pairs, the guess is the ground truth composed with an error
of 0.1/0.3/1.0 m (random direction) and 5/15/30 deg (random sign).
Each matcher is called once untimed before its timed run (numba JIT and library warm-up).
Times: wall clock per match (median, mean) and the median process CPU time, which a shared
machine inflates less than wall time; with `--repeats N` each pair's times are the least of N
passes over the pairs, as bursts of a neighbour's load on a shared machine moved single-pass
medians by up to 50 % (thirty-fourth session).
Trust (scanflow methods only; the peers report no status): "trusted" is the share of pairs whose
status is ok, "silently wrong" the share trusted although beyond 10 cm or 1 deg (the figure to
drive down), "flagged good" the share not ok although within 5 cm and 0.5 deg (the cost). The
success rates count the pose whatever the status.
Closure (`--closure`, gap >= 2): a precision figure that needs no ground truth. Each direct
match (i, i+K) is compared with the chain of the same matcher's K next-scan matches spanning it
(each from its own odometry guess). Their difference holds the errors of K+1 independent
matches, so its spread bounds the direct match's own error from above; set next to the same
matches' spread against the corrected poses, it shows how much of that is the matcher's.
Odometry is left out: its chain equals its direct guess by construction. An error shared by
every match of one scan (a distortion of the scan itself) cancels in the chain and is not seen.
For a scanflow method the chain also splits its silently wrong share: "confirmed" where the
chain is beyond 10 cm / 1 deg of the direct match as well (the matcher's own failures, or the
chain's), "contra" where it agrees within 5 cm / 0.5 deg (the corrected poses' own error is the
likelier cause: two independent estimates agree against them).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from functools import reduce
from operator import mul
from pathlib import Path
from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray
from scanflow.deskew import OdometryBuffer
from scanflow.geometry import Pose2D
from scanflow.io.carmen import load_keyframes
from scanflow.matching import DEFAULT_METHOD, MatchResult, available_methods, match
from scanflow.sim import WORLDS, SimConfig, simulate
from tqdm import tqdm

from bench.lidar import add_lidar_option, lidar_report, sim_lidar_fields
from bench.peers import load_peers

THRESHOLDS = ((0.05, 0.5), (0.10, 1.0))  # (metres, degrees)
ROBUST_LEVELS = ((0.1, 5.0), (0.3, 15.0), (1.0, 30.0))
DEFAULT_METHODS = ("odometry", "icp", "plicp", "csm+plicp")
# A peer returns a pose; a scanflow method its whole result (pose and status).
Matcher = Callable[[NDArray[np.float64], NDArray[np.float64], Pose2D], Pose2D | MatchResult]


@dataclass(frozen=True, eq=False)
class Frame:
    """A keyframe as the benchmark sees it: points in the robot's frame, true and odometry pose."""

    points: NDArray[np.float64]
    true_pose: Pose2D
    odom_pose: Pose2D


def log_frames(path: Path) -> list[Frame]:
    """The log's keyframes: valid beam endpoints, corrected pose, chained wheel odometry."""
    return [Frame(k.scan.robot_points(), k.true_pose, k.odom_pose) for k in load_keyframes(path)]


def sim_frames(config: SimConfig, every: int) -> list[Frame]:
    """Every `every`-th sweep of a simulated run: its exactly deskewed points, true pose and the
    simulated wheel odometry at its stamp."""
    odometry = OdometryBuffer(max_age_s=config.duration_s + 1.0)
    frames = []
    for k, sim in enumerate(simulate(config)):
        for sample in sim.odometry:
            odometry.add_odometry(sample)
        if k % every == 0:
            x, y, theta = odometry.poses_at([sim.scan.stamp_s])
            frames.append(Frame(sim.true_points, sim.true_pose,
                                Pose2D(float(x[0]), float(y[0]), float(theta[0]))))
    return frames


@dataclass(frozen=True)
class Pair:
    source: NDArray[np.float64]
    target: NDArray[np.float64]
    truth: Pose2D
    guess: Pose2D
    first: int  # index of the target keyframe i


def keyframe_pairs(
    frames: list[Frame], gap: int, stride: int, limit: int | None,
    start_step: int | None = None,
) -> list[Pair]:
    """Pairs (i, i+gap), i stepping by start_step (default gap), every stride-th, at most limit."""
    starts = range(0, len(frames) - gap, start_step or gap)
    pairs = [pair_of(frames, i, i + gap) for i in starts][::stride]
    return pairs[:limit] if limit else pairs


def pair_of(frames: list[Frame], i: int, j: int) -> Pair:
    """Source scan j against target scan i, with their true and odometry motions."""
    return Pair(
        frames[j].points,
        frames[i].points,
        frames[j].true_pose.relative_to(frames[i].true_pose),
        frames[j].odom_pose.relative_to(frames[i].odom_pose),
        i,
    )


def scanflow_matcher(method: str) -> Matcher:
    """A Matcher that runs scanflow's `match` with `method` (a MatchResult, with its status)."""
    def run(src: NDArray[np.float64], tgt: NDArray[np.float64], guess: Pose2D) -> MatchResult:
        return match(src, tgt, guess, method=method)

    return run


def odometry_matcher(src: NDArray[np.float64], tgt: NDArray[np.float64], guess: Pose2D) -> Pose2D:
    """The initial guess itself: what the matchers start from."""
    return guess


def errors(truth: Pose2D, estimate: Pose2D) -> tuple[float, float]:
    """(translation m, |rotation| deg) of truth^-1 * estimate."""
    e = estimate.relative_to(truth)
    return e.translation_norm(), abs(math.degrees(e.theta))


def pose_of(estimate: Pose2D | MatchResult) -> Pose2D:
    """The pose of a scanflow result or of a peer's answer."""
    return estimate.pose if isinstance(estimate, MatchResult) else estimate


class Run(NamedTuple):
    """One matcher over the pairs: its summary, its poses and, for a scanflow method, which
    results were trusted (status ok); None for a peer or the odometry."""

    summary: dict
    poses: list[Pose2D]
    trusted: NDArray[np.bool_] | None


def run_matcher(
    name: str, fn: Matcher, pairs: list[Pair], guesses: list[Pose2D], repeats: int = 1
) -> Run:
    """Errors and timing of one matcher over the pairs (with the given guesses), and its poses;
    in `repeats` passes over all pairs, each pair's times the least over the passes (its pose
    the first pass's). Passes rather than back-to-back runs: a neighbour's load on a shared
    machine comes in bursts of seconds, which a pair's back-to-back runs all fall into."""
    fn(pairs[0].source, pairs[0].target, guesses[0])  # warm-up, untimed
    work = list(zip(pairs, guesses, strict=True))
    times, cpu = np.full(len(pairs), np.inf), np.full(len(pairs), np.inf)
    estimates: list[Pose2D | MatchResult] = []
    for run in range(repeats):
        label = name if repeats == 1 else f"{name} ({run + 1}/{repeats})"
        for k, (pair, guess) in enumerate(tqdm(work, desc=label, file=sys.stderr, leave=False)):
            t0, c0 = time.perf_counter(), time.process_time()
            est = fn(pair.source, pair.target, guess)
            times[k] = min(times[k], time.perf_counter() - t0)
            cpu[k] = min(cpu[k], time.process_time() - c0)
            if run == 0:
                estimates.append(est)
    poses = [pose_of(est) for est in estimates]
    errs = np.array([errors(pair.truth, pose) for pair, pose in zip(pairs, poses, strict=True)])
    trans_m, rot_deg = errs[:, 0], errs[:, 1]
    out = summarise(trans_m, rot_deg, times, cpu)
    trusted = [est.ok for est in estimates if isinstance(est, MatchResult)]
    if trusted:
        out.update(trust_shares(trans_m, rot_deg, np.array(trusted)))
    return Run(out, poses, np.array(trusted) if trusted else None)


def closure(
    name: str, fn: Matcher, pairs: list[Pair], direct: list[Pose2D], frames: list[Frame],
    gap: int, trusted: NDArray[np.bool_] | None = None,
) -> dict[str, float]:
    """Agreement of each direct match with the chain of next-scan matches spanning its pair.

    With `trusted` (the direct matches' ok flags), the silently wrong ones (trusted, beyond
    10 cm / 1 deg of the truth) are split by the chain: "confirmed" when the chain is beyond
    10 cm / 1 deg of the direct match too, "chain agrees" when it is within 5 cm / 0.5 deg (then
    the truth's own error is the likelier cause)."""
    steps: dict[int, Pose2D] = {}
    for i in tqdm(sorted({p.first + k for p in pairs for k in range(gap)}), desc=f"{name} chain",
                  file=sys.stderr, leave=False):
        step = pair_of(frames, i, i + 1)
        steps[i] = pose_of(fn(step.source, step.target, step.guess))
    chains = [reduce(mul, (steps[p.first + k] for k in range(gap))) for p in pairs]
    apart = np.array([errors(c, d) for c, d in zip(chains, direct, strict=True)])
    out = shares_within("agree", apart[:, 0], apart[:, 1])
    out.update(trans_p50_m=float(np.median(apart[:, 0])), rot_p50_deg=float(np.median(apart[:, 1])))
    out.update(spread("closure", chains, direct))
    out.update(spread("truth", [p.truth for p in pairs], direct))
    if trusted is not None:
        tight, loose = THRESHOLDS
        off = np.array([errors(p.truth, d) for p, d in zip(pairs, direct, strict=True)])
        silent = trusted & ~within(off[:, 0], off[:, 1], loose)
        out.update(
            silently_wrong_confirmed=float(np.mean(silent & ~within(apart[:, 0], apart[:, 1],
                                                                    loose))),
            silently_wrong_chain_agrees=float(np.mean(silent & within(apart[:, 0], apart[:, 1],
                                                                      tight))),
        )
    return out


def spread(label: str, references: list[Pose2D], estimates: list[Pose2D]) -> dict[str, float]:
    """Robust sigma (1.4826 MAD) of the signed x, y, theta of reference^-1 * estimate."""
    d = np.array([(e.x, e.y, e.theta) for e in
                  (est.relative_to(ref) for ref, est in zip(references, estimates, strict=True))])
    sigma = 1.4826 * np.median(np.abs(d - np.median(d, axis=0)), axis=0)
    return {f"{label}_sigma_xy_m": float(np.mean(sigma[:2])),
            f"{label}_sigma_deg": float(math.degrees(sigma[2]))}


def within(trans_m: NDArray, rot_deg: NDArray, threshold: tuple[float, float]) -> NDArray:
    """Mask of the pairs within (metres, degrees) of the truth."""
    return (trans_m <= threshold[0]) & (rot_deg <= threshold[1])


def trust_shares(trans_m: NDArray, rot_deg: NDArray, trusted: NDArray) -> dict[str, float]:
    """Shares of pairs trusted (status ok), trusted but wrong, flagged although good."""
    tight, loose = THRESHOLDS
    return {
        "trusted": float(np.mean(trusted)),
        "silently_wrong": float(np.mean(trusted & ~within(trans_m, rot_deg, loose))),
        "flagged_good": float(np.mean(~trusted & within(trans_m, rot_deg, tight))),
    }


def shares_within(prefix: str, trans_m: NDArray, rot_deg: NDArray) -> dict[str, float]:
    """Share of the pairs within each of THRESHOLDS, keyed `<prefix>_5cm_0.5deg` etc."""
    return {
        f"{prefix}_{int(t * 100)}cm_{d:g}deg": float(np.mean(within(trans_m, rot_deg, (t, d))))
        for t, d in THRESHOLDS
    }


def summarise(trans_m: NDArray, rot_deg: NDArray, times_s: NDArray, cpu_s: NDArray) -> dict:
    """Success shares at THRESHOLDS, error percentiles (m, deg), times (ms) and the pair count."""
    out = shares_within("ok", trans_m, rot_deg)
    out.update(
        trans_p50_m=float(np.median(trans_m)),
        trans_p95_m=float(np.percentile(trans_m, 95)),
        rot_p50_deg=float(np.median(rot_deg)),
        rot_p95_deg=float(np.percentile(rot_deg, 95)),
        time_p50_ms=float(np.median(times_s) * 1e3),
        time_mean_ms=float(np.mean(times_s) * 1e3),
        cpu_p50_ms=float(np.median(cpu_s) * 1e3),
        pairs=len(trans_m),
    )
    return out


def perturbed_guesses(pairs: list[Pair], metres: float, degrees: float, seed: int) -> list[Pose2D]:
    """Ground truth composed with an error of `metres` (random direction) and +-`degrees`."""
    rng = np.random.default_rng(seed)
    heading = rng.uniform(-math.pi, math.pi, len(pairs))
    sign = rng.choice((-1.0, 1.0), len(pairs))
    return [
        p.truth * Pose2D(metres * math.cos(h), metres * math.sin(h), s * math.radians(degrees))
        for p, h, s in zip(pairs, heading, sign, strict=True)
    ]


def matchers(
    methods: list[str], peers: list[str] | None
) -> tuple[dict[str, Matcher], dict[str, str]]:
    """The matchers by name: scanflow `methods` (or odometry) and the `peers` (None: every one
    that loads); and the peer libraries installed but not loaded, with why. Those, and a named
    peer that is not available, are reported on stderr."""
    loaded = load_peers()
    wanted = list(loaded.found) if peers is None else peers
    absent = [p for p in wanted if p not in loaded.found]
    if peers is None or absent:
        for library, reason in loaded.missing.items():
            print(f"peer library {library} not loaded, its peers left out: {reason}",
                  file=sys.stderr)
    if absent:
        print(f"peers not available (pip install -e .[bench]): {absent}", file=sys.stderr)
    out: dict[str, Matcher] = {}
    for m in methods:
        out[m] = odometry_matcher if m == "odometry" else scanflow_matcher(m)
    out.update({p: loaded.found[p] for p in wanted if p in loaded.found})
    return out, loaded.missing


def format_table(results: dict[str, dict]) -> str:
    """The results table: success shares, error percentiles, times and trust per matcher."""
    head = (
        f"{'matcher':<18} {'5cm/0.5d':>8} {'10cm/1d':>8} {'t50 m':>7} {'t95 m':>7} "
        f"{'r50 deg':>7} {'r95 deg':>7} {'med ms':>7} {'mean ms':>7} {'cpu ms':>7} "
        f"{'trusted':>7} {'silent':>7} {'flagged':>7}"
    )
    lines = [head]
    for name, r in results.items():
        lines.append(
            f"{name:<18} {r['ok_5cm_0.5deg']:>8.1%} {r['ok_10cm_1deg']:>8.1%} "
            f"{r['trans_p50_m']:>7.3f} {r['trans_p95_m']:>7.3f} {r['rot_p50_deg']:>7.2f} "
            f"{r['rot_p95_deg']:>7.2f} {r['time_p50_ms']:>7.2f} {r['time_mean_ms']:>7.2f} "
            f"{r['cpu_p50_ms']:>7.2f} " + trust_cells(r)
        )
    return "\n".join(lines)


def format_closure(closures: dict[str, dict[str, float]], gap: int) -> str:
    """The closure table: direct matches against their chains, and against the truth; for a
    scanflow method, its silently wrong share split by what the chain says."""
    lines = [
        f"\nclosure: direct match vs the chain of {gap} next-scan matches (no ground truth);"
        " robust sigma per axis; silently wrong (trusted, beyond 10cm/1d of the truth) that the"
        " chain confirms (beyond 10cm/1d of it too) / contradicts (within 5cm/0.5d of it)",
        f"{'matcher':<18} {'5cm/0.5d':>8} {'10cm/1d':>8} {'t50 m':>7} {'r50 deg':>7} "
        f"{'sig mm':>7} {'sig deg':>7} {'vs truth: sig mm':>17} {'sig deg':>7} "
        f"{'confirmed':>9} {'contra':>7}",
    ]
    for name, c in closures.items():
        split = (
            f"{c['silently_wrong_confirmed']:>9.1%} {c['silently_wrong_chain_agrees']:>7.1%}"
            if "silently_wrong_confirmed" in c else f"{'-':>9} {'-':>7}"
        )
        lines.append(
            f"{name:<18} {c['agree_5cm_0.5deg']:>8.1%} {c['agree_10cm_1deg']:>8.1%} "
            f"{c['trans_p50_m']:>7.3f} {c['rot_p50_deg']:>7.2f} "
            f"{c['closure_sigma_xy_m'] * 1e3:>7.1f} {c['closure_sigma_deg']:>7.3f} "
            f"{c['truth_sigma_xy_m'] * 1e3:>17.1f} {c['truth_sigma_deg']:>7.3f} {split}"
        )
    return "\n".join(lines)


def trust_cells(r: dict) -> str:
    """Trusted / silently wrong / flagged good of a result, blank for a peer (no status)."""
    if "trusted" not in r:
        return " ".join(f"{'-':>7}" for _ in range(3))
    return f"{r['trusted']:>7.1%} {r['silently_wrong']:>7.1%} {r['flagged_good']:>7.1%}"


def main(argv: list[str] | None = None) -> None:
    """Run the matchers on the pairs of --data or --sim and print tables (JSON with --json)."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    source = parser.add_mutually_exclusive_group(required=True)
    source.add_argument("--data", type=Path, help="CARMEN log (.log or .log.gz)")
    source.add_argument("--sim", choices=sorted(WORLDS),
                        help="pairs from a run of the simulator over this world (exact truth)")
    parser.add_argument("--sim-duration-s", type=float, default=120.0)
    parser.add_argument("--sim-every", type=int, default=5,
                        help="every N-th sweep (10 Hz) is a keyframe")
    add_lidar_option(parser)
    parser.add_argument("--sim-seed", type=int, default=0)
    parser.add_argument("--gap", type=int, default=1, help="pair scan i with scan i+gap")
    parser.add_argument("--methods", nargs="*", default=list(DEFAULT_METHODS),
                        help=f"scanflow methods ({', '.join(available_methods())}) or odometry")
    parser.add_argument("--peers", nargs="*", default=None, help="peer names (default: all)")
    parser.add_argument("--limit", type=int, default=None, help="at most N pairs")
    parser.add_argument("--stride", type=int, default=1, help="use every S-th pair")
    parser.add_argument("--start-step", type=int, default=None,
                        help="i steps by T (default: the gap; 1 gives every overlapping pair)")
    parser.add_argument("--robust-pairs", type=int, default=100,
                        help="pairs for the robustness sweep (0: skip it)")
    parser.add_argument("--closure", action="store_true",
                        help="also compare each direct match with its chain of next-scan matches")
    parser.add_argument("--repeats", type=int, default=1,
                        help="time the pairs in N passes, each pair's least (a shared machine's "
                             "noise only ever adds); the robustness sweep runs once")
    parser.add_argument("--seed", type=int, default=4)
    parser.add_argument("--json", action="store_true", help="print JSON instead of tables")
    args = parser.parse_args(argv)
    if args.gap < 1 or args.stride < 1 or (args.start_step is not None and args.start_step < 1):
        parser.error(f"--gap, --stride and --start-step must be >= 1, got {args.gap}, "
                     f"{args.stride} and {args.start_step}")
    if args.repeats < 1:
        parser.error(f"--repeats must be >= 1, got {args.repeats}")
    if args.closure and args.gap < 2:
        parser.error(f"--closure needs --gap >= 2 (a chain of next-scan matches), got {args.gap}")
    if args.sim_every < 1:
        parser.error(f"--sim-every must be >= 1, got {args.sim_every}")
    if args.sim:
        try:
            config = SimConfig(
                world=args.sim, duration_s=args.sim_duration_s, seed=args.sim_seed,
                **sim_lidar_fields(args.lidar),
            )
        except ValueError as exc:
            parser.error(str(exc))
        frames, label = sim_frames(config, args.sim_every), f"sim:{args.sim}"
    else:
        frames, label = log_frames(args.data), args.data.name
    start_step = args.start_step or args.gap
    pairs = keyframe_pairs(frames, args.gap, args.stride, args.limit, start_step)
    if not pairs:
        parser.error(f"{label} gives no pairs at gap {args.gap}")
    runners, peers_not_loaded = matchers(args.methods, args.peers)
    odom = [p.guess for p in pairs]
    results: dict[str, dict] = {}
    closures: dict[str, dict[str, float]] = {}
    for name, fn in runners.items():
        run = run_matcher(name, fn, pairs, odom, args.repeats)
        results[name] = run.summary
        if args.closure and name != "odometry":
            closures[name] = closure(name, fn, pairs, run.poses, frames, args.gap, run.trusted)
    robust: dict[str, dict[str, float]] = {}
    robust_trust: dict[str, dict[str, dict[str, float]]] = {}
    if args.robust_pairs > 0:
        rng = np.random.default_rng(args.seed)
        pick = sorted(rng.choice(len(pairs), min(args.robust_pairs, len(pairs)), replace=False))
        subset = [pairs[i] for i in pick]
        for metres, degrees in ROBUST_LEVELS:
            key = f"{metres:g}m_{degrees:g}deg"
            guesses = perturbed_guesses(subset, metres, degrees, args.seed)
            for name, fn in runners.items():
                if name != "odometry":
                    r = run_matcher(f"{name} {key}", fn, subset, guesses).summary
                    robust.setdefault(name, {})[key] = r["ok_10cm_1deg"]
                    if "trusted" in r:
                        robust_trust.setdefault(name, {})[key] = {
                            k: r[k] for k in ("trusted", "silently_wrong", "flagged_good")
                        }
    report = {
        "data": str(args.data) if args.data else label, "gap": args.gap, "stride": args.stride,
        "start_step": start_step, "pairs": len(pairs), "repeats": args.repeats,
        "default_method": DEFAULT_METHOD, "results": results, "robustness_ok_10cm_1deg": robust,
        "robustness_trust": robust_trust, "closure": closures,
        "peer_libraries_not_loaded": peers_not_loaded,
    }
    if args.sim:
        report["sim"] = {"world": args.sim, "duration_s": args.sim_duration_s,
                         "every": args.sim_every, "seed": args.sim_seed,
                         "lidar": lidar_report(config)}
    if args.json:
        print(json.dumps(report, indent=2))
        return
    print(f"{label}: {len(pairs)} pairs, gap {args.gap}, start step {start_step}, "
          f"stride {args.stride}, default method {DEFAULT_METHOD}")
    print(format_table(results))
    if robust:
        levels = [f"{m:g}m/{d:g}deg" for m, d in ROBUST_LEVELS]
        print(f"\nrobustness (success at 10cm/1deg from truth + error), {args.robust_pairs} pairs")
        print(f"{'matcher':<18} " + " ".join(f"{lv:>11}" for lv in levels))
        for name, row in robust.items():
            print(f"{name:<18} " + " ".join(f"{v:>11.1%}" for v in row.values()))
    if robust_trust:
        print("\nrobustness trust: trusted / silently wrong / flagged good per level")
        print(f"{'matcher':<18} " + " ".join(f"{lv:>20}" for lv in levels))
        for name, trust in robust_trust.items():
            cells = [f"{t['trusted']:.1%}/{t['silently_wrong']:.1%}/{t['flagged_good']:.1%}"
                     for t in trust.values()]
            print(f"{name:<18} " + " ".join(f"{c:>20}" for c in cells))
    if closures:
        print(format_closure(closures, args.gap))


if __name__ == "__main__":
    main()
