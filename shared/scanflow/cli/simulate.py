"""`scanflow simulate`: run the built-in simulator and the deskewer in-process, print a summary."""

from __future__ import annotations

import json
import math

import numpy as np
import typer
from tqdm import tqdm

from scanflow.cli import app
from scanflow.deskew import OdometryBuffer, deskew
from scanflow.sim import WORLDS, SimConfig, simulate


@app.command("simulate")
def simulate_command(
    world: str = typer.Option("rooms", help=f"one of {sorted(WORLDS)}"),
    duration: float = typer.Option(30.0, min=0.1, help="simulated seconds"),
    seed: int = typer.Option(0, help="seed: the same seed gives the same run"),
    as_json: bool = typer.Option(False, "--json", help="print the summary as JSON"),
) -> None:
    """Simulate a run, deskew every scan with the odometry, and summarise the distortion."""
    if world not in WORLDS:
        raise typer.BadParameter(
            f"must be one of {sorted(WORLDS)}, got {world!r}", param_hint="--world"
        )
    try:
        config = SimConfig(world=world, duration_s=duration, seed=seed)
    except ValueError as exc:
        raise typer.BadParameter(str(exc)) from exc
    odometry = OdometryBuffer()
    scans = beams = valid = 0
    distance_m = 0.0
    previous = None
    before_m: list[float] = []
    after_m: list[float] = []
    sources: dict[str, int] = {}
    total = math.ceil(duration * config.rate_hz)
    for frame in tqdm(simulate(config), total=total, unit="scan", disable=as_json):
        for sample in frame.odometry:
            odometry.add_odometry(sample)
        result = deskew(frame.scan, odometry)
        sources[result.source_used] = sources.get(result.source_used, 0) + 1
        scans += 1
        beams += frame.scan.beam_count
        valid += result.valid_count
        if previous is not None:
            distance_m += frame.true_pose.relative_to(previous).translation_norm()
        previous = frame.true_pose
        raw = frame.scan.robot_points()
        before_m.append(float(np.linalg.norm(raw - frame.true_points, axis=1).mean()))
        after_m.append(float(np.linalg.norm(result.points - frame.true_points, axis=1).mean()))
    summary = {
        "world": world,
        "seed": seed,
        "scans": scans,
        "beams": beams,
        "valid_beams": valid,
        "distance_m": round(distance_m, 3),
        "mean_distortion_before_mm": round(1000 * float(np.mean(before_m)), 3),
        "mean_distortion_after_mm": round(1000 * float(np.mean(after_m)), 3),
        "deskew_sources": sources,
    }
    if as_json:
        typer.echo(json.dumps(summary))
        return
    typer.echo(
        f"{scans} scans ({beams} beams, {valid} valid) over {distance_m:.1f} m in '{world}'; "
        f"mean beam distortion {summary['mean_distortion_before_mm']:.2f} mm before deskew, "
        f"{summary['mean_distortion_after_mm']:.3f} mm after (sources: {sources})"
    )
