"""`scanflow run`: replay the simulator (default) or a log through the in-process pipeline
(deskew + scan-to-map front end), print a summary, optionally write the map and trajectory."""

from __future__ import annotations

import json
import math
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Annotated

import numpy as np
import typer
from tqdm import tqdm

from scanflow.cli import SkippedRecords, app, check_log
from scanflow.config import BackendSettings, FrontendSettings, SettingsError, check_environment
from scanflow.frontend import save_tum
from scanflow.frontend.prior import FrontendStart, PriorMapError
from scanflow.io.carmen import load_keyframes
from scanflow.io.detect import carmen_error_handler, detect_format
from scanflow.io.rosbag import BagFormatError, BagOdom, BagReader
from scanflow.maps.export import save_map
from scanflow.pipeline import Pipeline, PipelineOutput
from scanflow.sim import SimConfig, simulate


def _sim_outputs(pipeline: Pipeline, config: SimConfig) -> Iterator[PipelineOutput]:
    for frame in simulate(config):
        for sample in frame.odometry:
            pipeline.add_odometry(sample)
        yield pipeline.process(frame.scan)


def _log_outputs(
    pipeline: Pipeline, path: Path, on_error: Callable[[str], None]
) -> Iterator[PipelineOutput]:
    """CARMEN: keyframes with their chained wheel odometry; bags: scans and odometry streams.
    Each record skipped as unreadable is passed to `on_error`."""
    if detect_format(path) == "carmen":
        for kf in load_keyframes(path, on_error=carmen_error_handler(on_error)):
            yield pipeline.process(kf.scan, kf.odom_pose)
        return
    for record in BagReader(path, on_error=on_error):
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
    loop_closure: bool = typer.Option(
        False, "--loop-closure", help="close loops and optimise the keyframes' pose graph"
    ),
) -> None:
    """Track scans into a map in one process; settings from SCANFLOW_FRONTEND_* and
    SCANFLOW_BACKEND_*."""
    if log is not None and not log.exists():
        raise typer.BadParameter(f"no log at {log}", param_hint="--log")
    if log is not None:
        check_log(log)
    if map_out is not None and map_out.exists() and not map_out.is_dir():
        raise typer.BadParameter(f"{map_out} is not a directory", param_hint="--map-out")
    try:
        sim = SimConfig(duration_s=duration, seed=seed)
    except ValueError as exc:
        raise typer.BadParameter(str(exc)) from exc
    try:
        check_environment(FrontendSettings, BackendSettings)
    except SettingsError as exc:
        raise typer.BadParameter(str(exc), param_hint="SCANFLOW_* environment") from exc
    settings = FrontendSettings()
    if prior_map is not None:
        settings = settings.model_copy(update={"prior_map": str(prior_map)})
    try:
        start = FrontendStart(settings)
    except PriorMapError as exc:
        raise typer.BadParameter(str(exc), param_hint="--prior-map") from exc
    if map_out is not None:
        try:  # made now: a place that cannot be written fails here, not after the whole run
            map_out.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise typer.BadParameter(f"cannot make {map_out}: {exc.strerror}",
                                     param_hint="--map-out") from exc
    backend = BackendSettings()
    if loop_closure:
        backend = backend.model_copy(update={"loop_closure": True})
    pipeline = Pipeline(settings, initial_pose=start.pose, grid=start.grid(), backend=backend)
    skipped, broken = SkippedRecords(), ""
    outputs = (_log_outputs(pipeline, log, skipped) if log is not None
               else _sim_outputs(pipeline, sim))
    total = limit or (None if log is not None else math.ceil(duration * sim.rate_hz))
    statuses: dict[str, int] = {}
    sources: dict[str, int] = {}
    scans = inserted = rechecked = redraws = 0
    t0 = time.perf_counter()
    try:
        for out in tqdm(outputs, total=total, unit="scan", disable=as_json):
            est = out.estimate
            statuses[str(est.status)] = statuses.get(str(est.status), 0) + 1
            sources[out.deskew.source_used] = sources.get(out.deskew.source_used, 0) + 1
            scans += 1
            inserted += est.inserted
            rechecked += est.rechecked
            redraws += out.backend is not None and out.backend.redrawn
            if limit is not None and scans >= limit:
                break
    except BagFormatError as exc:
        if scans == 0:  # a bag that cannot be opened: nothing to show
            typer.echo(f"error: cannot read {log}: {exc}", err=True)
            raise typer.Exit(code=2) from exc
        broken = str(exc)  # it broke off: the scans before it are tracked, mapped and written
    final = pipeline.finish()
    wall_s = time.perf_counter() - t0
    frontend, mapper = pipeline.frontend, pipeline.mapper
    poses = frontend.trajectory.poses if mapper is None else mapper.trajectory()
    # The map of the optimised keyframes (the front end's, without loop closure).
    matching_map = frontend.map if mapper is None else mapper.draw_map()
    distance_m = float(np.sum(np.hypot(*np.diff(poses[:, :2], axis=0).T)))
    summary: dict[str, object] = {
        "source": str(log) if log is not None else "simulator",
        "prior_map": settings.prior_map or None,
        "method": settings.method,
        "scans": scans,
        "statuses": statuses,
        "rechecked": rechecked,
        "deskew_sources": sources,
        "inserted": inserted,
        "distance_m": round(distance_m, 3),
        "final_pose": [round(float(v), 4) for v in poses[-1]] if len(poses) else None,
        "scans_per_s": round(scans / wall_s, 2) if wall_s > 0 else None,
        "map_bytes": matching_map.nbytes,
    }
    if log is not None:
        summary["skipped_records"] = skipped.count
    if broken:
        summary["log_error"] = broken
    failure = (f"the log broke off, the run ends where it did: {broken}" if broken
               else f"no scans in {log}" if log is not None and scans == 0 else "")
    if mapper is not None:
        summary["loop_closure"] = {
            "keyframes": mapper.graph.node_count,
            "culled": len(mapper.culled_seqs),  # inserts hung from a keyframe (cull_m)
            "closures": len(mapper.closures),
            "map_redraws": redraws + (final is not None and final.redrawn),
        }
    written: list[Path] = []
    if map_out is not None:
        written = [] if matching_map.grid.is_empty else [  # no scan inserted: no map to draw
            save_map(matching_map.grid, map_out / f"map{suffix}")
            for suffix in (".png", ".yaml", ".npz")
        ]
        written.append(
            save_tum(map_out / "trajectory.tum", frontend.trajectory.stamps_s, poses)
        )
        summary["written"] = [str(p) for p in written]
    if as_json:
        typer.echo(json.dumps(summary))
        _end(skipped, failure, as_json)
        return
    typer.echo(
        f"{scans} scans ({statuses}) over {distance_m:.1f} m, {inserted} inserted, "
        f"{summary['scans_per_s']} scans/s, map {matching_map.nbytes / 1e6:.1f} MB"
    )
    if mapper is not None:
        typer.echo(
            f"loop closure: {len(mapper.closures)} closures between {mapper.graph.node_count} "
            f"keyframes ({len(mapper.culled_seqs)} inserts culled); map and trajectory optimised"
        )
    if map_out is not None and matching_map.grid.is_empty:
        typer.echo("warning: no scan was inserted: no map written", err=True)
    for path in written:
        typer.echo(f"wrote {path}")
    _end(skipped, failure, as_json)


def _end(skipped: SkippedRecords, failure: str, as_json: bool) -> None:
    """Warn of the log's skipped records (unless --json, whose summary counts them); exit 1
    naming the `failure` when there is one (the log broke off, or held no scan)."""
    if not as_json:
        skipped.warn()
    if failure:
        typer.echo(f"error: {failure}", err=True)
        raise typer.Exit(code=1)
