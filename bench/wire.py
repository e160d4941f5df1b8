"""Wire format cost for a 1081-beam scan: msgpack codec vs stdlib JSON of the same message.

Both sides start from and end at a LaserScan (with intensities and per-beam times), so JSON
pays for its float lists both ways. Run: `python -m bench.wire [--runs N] [--json]`.
"""

from __future__ import annotations

import argparse
import json
import math
import platform
import statistics
import time
from collections.abc import Callable
from typing import Any

import numpy as np
from scanflow.scan import LaserScan
from scanflow.wire import ScanMessage

BEAMS = 1081  # 270 deg at 0.25 deg, e.g. a Hokuyo UTM-30LX at 40 Hz


def make_scan(seed: int = 0, beams: int = BEAMS) -> LaserScan:
    """A realistic scan: ranges up to 30 m, 5 % dropouts as NaN, intensities, per-beam times."""
    rng = np.random.default_rng(seed)
    ranges = rng.uniform(0.1, 30.0, beams).astype(np.float32)
    ranges[rng.random(beams) < 0.05] = np.nan
    fov_rad = math.radians(270.0)
    return LaserScan(
        ranges_m=ranges,
        angle_min_rad=-fov_rad / 2,
        angle_increment_rad=fov_rad / (beams - 1),
        range_min_m=0.1,
        range_max_m=30.0,
        stamp_s=1_700_000_000.25,
        scan_duration_s=0.025,
        beam_time_offsets_s=np.linspace(0.0, 0.025 * (beams - 1) / beams, beams),
        robot_id="robot_1",
        frame_id="laser",
        intensities=rng.uniform(0, 4000, beams).astype(np.float32),
        seq=123_456,
    )


def json_encode(scan: LaserScan) -> bytes:
    """The same message as JSON with lists of floats (NaN as the non-standard NaN token)."""
    offsets = scan.beam_time_offsets_s
    intensities = scan.intensities
    return json.dumps(
        {
            "type": "scan",
            "v": 1,
            "robot_id": scan.robot_id,
            "frame_id": scan.frame_id,
            "seq": scan.seq,
            "stamp_s": scan.stamp_s,
            "angle_min_rad": scan.angle_min_rad,
            "angle_increment_rad": scan.angle_increment_rad,
            "range_min_m": scan.range_min_m,
            "range_max_m": scan.range_max_m,
            "scan_duration_s": scan.scan_duration_s,
            "ranges_m": scan.ranges_m.tolist(),
            "beam_time_offsets_s": None if offsets is None else offsets.tolist(),
            "intensities": None if intensities is None else intensities.tolist(),
        }
    ).encode()


def json_decode(data: bytes) -> LaserScan:
    """The LaserScan of `json_encode`'s bytes."""
    obj = json.loads(data)
    del obj["type"], obj["v"]
    return LaserScan(**obj)


def median_us(fn: Callable[[], Any], runs: int) -> float:
    """Median wall time of one call, in microseconds, after a short warm-up."""
    for _ in range(min(50, runs)):
        fn()
    samples = []
    for _ in range(runs):
        t0 = time.perf_counter_ns()
        fn()
        samples.append(time.perf_counter_ns() - t0)
    return statistics.median(samples) / 1000.0


def run(runs: int, seed: int) -> dict[str, Any]:
    """Median encode and decode times (us) and sizes of msgpack and JSON, and their ratios;
    RuntimeError when a codec does not give the ranges back."""
    scan = make_scan(seed)
    message = ScanMessage(scan)
    packed = message.encode()
    text = json_encode(scan)
    exact = ScanMessage.decode(packed).scan.ranges_m.tobytes() == scan.ranges_m.tobytes()
    if not (exact and np.array_equal(json_decode(text).ranges_m, scan.ranges_m, equal_nan=True)):
        raise RuntimeError("a codec did not reproduce the scan's ranges")
    msgpack_figures = {
        "encode_us": median_us(message.encode, runs),
        "decode_us": median_us(lambda: ScanMessage.decode(packed), runs),
        "bytes": len(packed),
    }
    json_figures = {
        "encode_us": median_us(lambda: json_encode(scan), runs),
        "decode_us": median_us(lambda: json_decode(text), runs),
        "bytes": len(text),
    }
    return {
        "beams": scan.beam_count,
        "runs": runs,
        "python": platform.python_version(),
        "msgpack": msgpack_figures,
        "json": json_figures,
        "json_over_msgpack": {
            key: json_figures[key] / msgpack_figures[key]
            for key in ("encode_us", "decode_us", "bytes")
        },
    }


def main(argv: list[str] | None = None) -> None:
    """Run the benchmark and print a table (JSON with --json)."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=2000, help="timed calls per figure")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--json", action="store_true", help="print the figures as JSON")
    args = parser.parse_args(argv)
    if args.runs < 1:
        parser.error(f"--runs must be >= 1, got {args.runs}")
    result = run(args.runs, args.seed)
    if args.json:
        print(json.dumps(result, indent=2))
        return
    print(f"ScanMessage, {result['beams']} beams, median of {args.runs} runs")
    print(f"{'codec':8} {'encode us':>10} {'decode us':>10} {'bytes':>8}")
    for codec in ("msgpack", "json"):
        r = result[codec]
        print(f"{codec:8} {r['encode_us']:10.1f} {r['decode_us']:10.1f} {r['bytes']:8d}")
    ratio = result["json_over_msgpack"]
    print(
        f"json/msgpack: encode x{ratio['encode_us']:.1f}, decode x{ratio['decode_us']:.1f}, "
        f"size x{ratio['bytes']:.1f}"
    )


if __name__ == "__main__":
    main()
