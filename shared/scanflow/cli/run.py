"""`scanflow run`: replay the simulator (default) or a log through the in-process pipeline
(deskew + scan-to-map front end), print a summary, optionally write the map and trajectory."""

from __future__ import annotations

import json
import math
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Annotated

import typer
from tqdm import tqdm

from scanflow.cli import app
from scanflow.config import FrontendSettings
from scanflow.frontend.prior import FrontendStart, PriorMapError
from scanflow.geometry import Pose2D
from scanflow.io.carmen import load_keyframes
from scanflow.io.detect import detect_format, open_log
from scanflow.io.rosbag import BagOdom
from scanflow.maps.export import save_map
from scanflow.pipeline import Pipeline, PipelineOutput
from scanflow.sim import SimConfig, simulate


def _sim_outputs(pipeline: Pipeline, duration_s: float, seed: int) -> Iterator[PipelineOutput]:
    for frame in simulate(SimConfig(duration_s=duration_s, seed=seed)):
        for sample in frame.odometry:
            pipeline.add_odometry(sample)
        yield pipeline.process(frame.scan)


def _log_outputs(pipeline: Pipeline, path: Path) -> Iterator[PipelineOutput]:
    """CARMEN: keyframes with their chained wheel odometry; bags: scans and odometry streams."""
    if detect_format(path) == "carmen":
        for kf in load_keyframes(path):
            yield pipeline.process(kf.scan, kf.odom_pose)
        return
    for record in open_log(path):
        if isinstance(record, BagOdom):
            pipeline.add_odometry(record.odom)
        else:
            yield pipeline.process(record.scan)


@app.command("run")
def run_command(
    log: Annotated[
        Path | None, typer.Option("--log", help="CARMEN log or ROS bag; default: simulator")
    ] = None,
    map_out: Annotated[
        Path | None,
        typer.Option("--map-out", help="write map.png, map.yaml/.pgm, map.npz, trajectory.tum"),
    ] = None,
    duration: float = typer.Option(30.0, min=0.1, help="simulated seconds (simulator only)"),
    seed: int = typer.Option(0, help="simulator seed"),
    limit: int | None = typer.Option(None, min=1, help="stop after this many scans"),
    as_json: bool = typer.Option(False, "--json", help="print the summary as JSON"),
    prior_map: Annotated[
        Path | None,
        typer.Option("--prior-map", help="localise on this map (.npz or map_server .yaml)"),
    ] = None,
) -> None:
    """Track scans into a map in one process; settings from SCANFLOW_FRONTEND_*."""
    if log is not None and not log.exists():
        raise typer.BadParameter(f"no log at {log}", param_hint="--log")
    settings = FrontendSettings()
    if prior_map is not None:
        settings = settings.model_copy(update={"prior_map": str(prior_map)})
    try:
        start = FrontendStart(settings)
    except PriorMapError as exc:
        raise typer.BadParameter(str(exc), param_hint="--prior-map") from exc
    pipeline = Pipeline(settings, initial_pose=start.pose, grid=start.grid())
    outputs = _log_outputs(pipeline, log) if log is not None else _sim_outputs(
        pipeline, duration, seed
    )
    total = limit or (None if log is not None else math.ceil(duration * SimConfig().rate_hz))
    statuses: dict[str, int] = {}
    sources: dict[str, int] = {}
    scans = inserted = 0
    distance_m = 0.0
    last: Pose2D | None = None
    t0 = time.perf_counter()
    for out in tqdm(outputs, total=total, unit="scan", disable=as_json):
        est = out.estimate
        statuses[str(est.status)] = statuses.get(str(est.status), 0) + 1
        sources[out.deskew.source_used] = sources.get(out.deskew.source_used, 0) + 1
        scans += 1
        inserted += est.inserted
        if last is not None:
            distance_m += est.pose.relative_to(last).translation_norm()
        last = est.pose
        if limit is not None and scans >= limit:
            break
    wall_s = time.perf_counter() - t0
    frontend = pipeline.frontend
    summary: dict[str, object] = {
        "source": str(log) if log is not None else "simulator",
        "prior_map": settings.prior_map or None,
        "method": settings.method,
        "scans": scans,
        "statuses": statuses,
        "deskew_sources": sources,
        "inserted": inserted,
        "distance_m": round(distance_m, 3),
        "final_pose": None if last is None else [round(v, 4) for v in last.to_array()],
        "scans_per_s": round(scans / wall_s, 2) if wall_s > 0 else None,
        "map_bytes": frontend.map.nbytes,
    }
    written: list[Path] = []
    if map_out is not None:
        map_out.mkdir(parents=True, exist_ok=True)
        written = [save_map(frontend.map.grid, map_out / f"map{suffix}")
                   for suffix in (".png", ".yaml", ".npz")]
        written.append(frontend.trajectory.save_tum(map_out / "trajectory.tum"))
        summary["written"] = [str(p) for p in written]
    if as_json:
        typer.echo(json.dumps(summary))
        return
    typer.echo(
        f"{scans} scans ({statuses}) over {distance_m:.1f} m, {inserted} inserted, "
        f"{summary['scans_per_s']} scans/s, map {frontend.map.nbytes / 1e6:.1f} MB"
    )
    for path in written:
        typer.echo(f"wrote {path}")
