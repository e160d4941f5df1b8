"""`scanflow inspect FILE [--json]`: what a CARMEN log or ROS bag holds, in one streaming pass."""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Any

import numpy as np
import typer
from tqdm import tqdm

from scanflow.cli import app, finite_or_none
from scanflow.io.detect import detect_format, open_log, record_payload
from scanflow.scan import LaserScan, Odometry

MAX_LISTED_ERRORS = 10
MAX_LISTED_MOUNTS = 10  # distinct lidar mounts (x m, y m, yaw deg; mm / 0.01 deg) listed


@dataclass
class LogSummary:
    """Running statistics over the scans and odometry samples of one log."""

    scans: int = 0
    odometry: int = 0
    beams: set[int] = field(default_factory=set)
    robots: set[str] = field(default_factory=set)
    beam_total: int = 0
    dropped_total: int = 0
    valid_range_sum_m: float = 0.0
    range_min_m: float = math.inf
    range_max_m: float = -math.inf
    angle_min_rad: float = math.inf
    angle_max_rad: float = -math.inf
    span_max_rad: float = 0.0
    no_return_m: set[float] = field(default_factory=set)
    scan_stamp_min_s: float = math.inf
    scan_stamp_max_s: float = -math.inf
    mounts: set[tuple[float, float, float]] = field(default_factory=set)

    def add_scan(self, scan: LaserScan) -> None:
        """Count one scan in: beams, drops, valid ranges, angles, stamps, robot and mount."""
        self.scans += 1
        self.beams.add(scan.beam_count)
        self.robots.add(scan.robot_id)
        self.beam_total += scan.beam_count
        self.dropped_total += scan.dropped_count
        self.no_return_m.add(scan.range_max_m)
        valid = scan.ranges_m[scan.valid_mask]
        if valid.size:
            self.valid_range_sum_m += float(valid.sum(dtype=np.float64))
            self.range_min_m = min(self.range_min_m, float(valid.min()))
            self.range_max_m = max(self.range_max_m, float(valid.max()))
        if scan.beam_count:
            first, last = float(scan.angles_rad[0]), float(scan.angles_rad[-1])
            self.angle_min_rad = min(self.angle_min_rad, first, last)
            self.angle_max_rad = max(self.angle_max_rad, first, last)
            self.span_max_rad = max(self.span_max_rad, abs(last - first))
        self.scan_stamp_min_s = min(self.scan_stamp_min_s, scan.stamp_s)
        self.scan_stamp_max_s = max(self.scan_stamp_max_s, scan.stamp_s)
        if len(self.mounts) < MAX_LISTED_MOUNTS:  # per-record mounts may differ by rounding
            m = scan.mount
            self.mounts.add((round(m.x, 3), round(m.y, 3), round(math.degrees(m.theta), 2)))

    def add_odometry(self, odom: Odometry) -> None:
        """Count one odometry sample and its robot in."""
        self.odometry += 1
        self.robots.add(odom.robot_id)

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready summary; durations and rates come from the scan stamps."""
        duration_s = self.scan_stamp_max_s - self.scan_stamp_min_s if self.scans else 0.0
        valid_total = self.beam_total - self.dropped_total
        return {
            "scans": self.scans,
            "beams": sorted(self.beams),
            "fov_deg": round(math.degrees(self.span_max_rad), 6),
            "angle_min_deg": _deg_or_none(self.angle_min_rad),
            "angle_max_deg": _deg_or_none(self.angle_max_rad),
            "duration_s": round(duration_s, 6),
            "rate_hz": round((self.scans - 1) / duration_s, 6) if duration_s > 0 else None,
            "odometry": self.odometry,
            "robots": sorted(self.robots),
            "dropped_beam_fraction": (
                round(self.dropped_total / self.beam_total, 6) if self.beam_total else None
            ),
            "range_m": {
                "min": finite_or_none(self.range_min_m),
                "max": finite_or_none(self.range_max_m),
                "mean": round(self.valid_range_sum_m / valid_total, 6) if valid_total else None,
            },
            "no_return_at_m": sorted(finite_or_none(v) for v in self.no_return_m if v < math.inf),
            "lidar_mounts_m_m_deg": sorted(list(m) for m in self.mounts),
        }


def _deg_or_none(angle_rad: float) -> float | None:
    return round(math.degrees(angle_rad), 6) if math.isfinite(angle_rad) else None


def summarize_log(path: Path, *, progress: bool | None = False) -> dict[str, Any]:
    """Read a whole log once and describe it (format, counts, layout, timing, quality).

    `progress=None` shows a bar on stderr only when stderr is a terminal.
    """
    reader = open_log(path)
    summary = LogSummary()
    records = tqdm(
        reader,
        desc=path.name,
        unit=" rec",
        disable=None if progress is None else not progress,
        leave=False,
    )
    for record in records:
        payload = record_payload(record)
        if isinstance(payload, LaserScan):
            summary.add_scan(payload)
        else:
            summary.add_odometry(payload)
    result = {"path": str(path), "format": detect_format(path), **summary.to_dict()}
    result["malformed"] = reader.error_count
    result["errors"] = [str(e) for e in reader.errors[:MAX_LISTED_ERRORS]]
    skipped = getattr(reader, "skipped", None)
    if skipped is not None:
        result["skipped_lines"] = dict(sorted(skipped.items()))
    return result


@app.command()
def inspect(
    file: Annotated[Path, typer.Argument(help="CARMEN log (.log/.clf, gzip ok) or ROS 1/2 bag.")],
    as_json: Annotated[bool, typer.Option("--json", help="Print one JSON object.")] = False,
) -> None:
    """Tell what a log or bag holds: scans, beams, field of view, timing, odometry, robots."""
    try:
        summary = summarize_log(file, progress=None)
    except (OSError, ValueError) as exc:
        typer.echo(f"error: cannot read {file}: {exc}", err=True)
        raise typer.Exit(code=2) from exc
    if as_json:
        typer.echo(json.dumps(summary))
        return
    for key, value in summary.items():
        typer.echo(f"{key:>22}: {value}")
