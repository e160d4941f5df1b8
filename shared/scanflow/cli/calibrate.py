"""`scanflow calibrate --log LOG [--limit N] [--json]`: estimate the lidar's mount on the robot
from a CARMEN log's keyframes (their wheel odometry against scan-to-scan matching)."""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Annotated

import typer

from scanflow.calibration import estimate_mount, paired_motions
from scanflow.cli import SkippedRecords, app, check_log, finite_or_none
from scanflow.geometry import IDENTITY
from scanflow.io.carmen import load_keyframes
from scanflow.io.detect import carmen_error_handler


@app.command("calibrate")
def calibrate_command(
    log: Annotated[Path, typer.Option("--log", help="CARMEN log (.log or .gz)")],
    limit: int | None = typer.Option(None, min=2, help="use the first N keyframes"),
    as_json: bool = typer.Option(False, "--json", help="print the estimate as JSON"),
) -> None:
    """Fit T_base_laser to the log's odometry and scan matching (2D hand-eye calibration)."""
    if not log.exists():
        raise typer.BadParameter(f"no log at {log}", param_hint="--log")
    if check_log(log) != "carmen":
        raise typer.BadParameter("calibrate reads CARMEN logs (keyframes: scans without "
                                 "motion distortion)", param_hint="--log")
    skipped = SkippedRecords()
    frames = load_keyframes(log, on_error=carmen_error_handler(skipped))[:limit]
    # The log's declared mount (identity for FLASER) only seeds the scan matches.
    guess = frames[0].scan.mount if frames else IDENTITY
    robot, sensor = paired_motions(
        [kf.scan.points() for kf in frames], [kf.odom_pose for kf in frames], guess
    )
    estimate = estimate_mount(robot, sensor)
    m = estimate.mount
    summary = {
        "log": str(log),
        "status": str(estimate.status),
        "message": estimate.message,
        "mount_m_m_deg": [finite_or_none(v) for v in (m.x, m.y, math.degrees(m.theta))],
        "std_m_m_deg": [finite_or_none(v) for v in
                        (*estimate.std_xy_m, math.degrees(estimate.std_yaw_rad))],
        "residual_rms_m": finite_or_none(estimate.residual_rms_m),
        "pairs_used": estimate.pairs_used,
        "pairs_matched": len(robot),
        "keyframes": len(frames),
        "skipped_records": skipped.count,
    }
    if not as_json:
        skipped.warn()
    if as_json:
        typer.echo(json.dumps(summary))
    elif estimate.ok:
        typer.echo(
            f"mount (T_base_laser): x {m.x:.3f} m, y {m.y:.3f} m, yaw {math.degrees(m.theta):.2f}"
            f" deg (std {estimate.std_xy_m[0]:.3f} m, {estimate.std_xy_m[1]:.3f} m, "
            f"{math.degrees(estimate.std_yaw_rad):.2f} deg) from {estimate.pairs_used} of "
            f"{len(frames) - 1} keyframe pairs, residual {estimate.residual_rms_m:.3f} m rms\n"
            f"SCANFLOW_INGEST_MOUNT={m.x:.3f},{m.y:.3f},{math.degrees(m.theta):.2f}"
        )
    else:
        typer.echo(f"no estimate ({estimate.status}): {estimate.message}")
    if not estimate.ok:
        raise typer.Exit(1)
