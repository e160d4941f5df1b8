"""`scanflow up`: run router, services and gateway locally until Ctrl-C (used by `make run`)."""

from __future__ import annotations

import importlib.util
import math
import signal
import tempfile
import time
from pathlib import Path
from typing import Annotated

import typer

from scanflow.cli import app, check_log
from scanflow.config import (
    SECTIONS,
    BackendSettings,
    FrontendSettings,
    SettingsError,
    check_environment,
)
from scanflow.frontend.prior import PriorMapError, load_prior_map


@app.command()
def up(
    log: Annotated[
        Path | None, typer.Option(exists=True, help="CARMEN log or ROS bag; default: sim")
    ] = None,
    rate: Annotated[
        float, typer.Option(min=0.0, help="x real time; 0 = as fast as possible")
    ] = 1.0,
    port: Annotated[int, typer.Option(min=1, max=65535, help="gateway HTTP port")] = 8000,
    zenoh_port: Annotated[
        int, typer.Option(min=1, max=65535, help="router TCP port on 127.0.0.1")
    ] = 7447,
    data_dir: Annotated[Path, typer.Option(help="map snapshots")] = Path("scanflow-data"),
    limit: Annotated[
        int | None, typer.Option(min=1, help="publish at most this many scans")
    ] = None,
    prior_map: Annotated[
        Path | None,
        typer.Option("--prior-map", help="start every robot on this map (.npz or .yaml)"),
    ] = None,
    loop_closure: bool = typer.Option(
        False, "--loop-closure", help="close loops and optimise the keyframes' pose graph"
    ),
) -> None:
    """Start the whole pipeline as local processes; stop them all on Ctrl-C or SIGTERM.
    Exits 0 when every service stopped cleanly, else 1 naming the ones that did not."""
    from services.common.launch import ORDER, PIPELINE, STOP_ORDER, Launcher

    try:  # every service reads the same environment: one bad variable stops them all
        check_environment(*SECTIONS)
    except SettingsError as exc:
        raise typer.BadParameter(str(exc), param_hint="SCANFLOW_* environment") from exc
    backend = BackendSettings()
    if loop_closure:
        backend = backend.model_copy(update={"loop_closure": True})
    if not math.isfinite(rate):  # the range check lets inf by; ingest would refuse it
        raise typer.BadParameter(f"must be finite, got {rate}", param_hint="--rate")
    settings = {
        "SCANFLOW_INGEST_RATE": str(rate),
        "SCANFLOW_MAPSERVER_DATA_DIR": str(data_dir.resolve()),
        "SCANFLOW_GATEWAY_PORT": str(port),
    }
    if log is not None:
        check_log(log)  # as ingest will read it: it would stop at its start, the rest running
        settings["SCANFLOW_INGEST_LOG"] = str(log.resolve())
    if limit is not None:
        settings["SCANFLOW_INGEST_LIMIT"] = str(limit)
    frontend = FrontendSettings()
    if prior_map is not None:
        frontend = frontend.model_copy(update={"prior_map": str(prior_map)})
        settings["SCANFLOW_FRONTEND_PRIOR_MAP"] = str(prior_map.resolve())
    try:  # read as the matcher and map server will: a bad map would stop them at start-up
        load_prior_map(frontend)
    except PriorMapError as exc:
        raise typer.BadParameter(str(exc), param_hint="--prior-map") from exc
    if loop_closure:
        settings["SCANFLOW_BACKEND_LOOP_CLOSURE"] = "true"
    log_dir = Path(tempfile.mkdtemp(prefix="scanflow-up-"))
    launcher = Launcher.local(log_dir, zenoh_port, **settings)
    stopping = False

    def on_signal(_signum: int, _frame: object) -> None:
        nonlocal stopping
        stopping = True

    signal.signal(signal.SIGTERM, on_signal)
    signal.signal(signal.SIGINT, on_signal)
    try:
        for name in ORDER:
            if stopping:
                break
            if name == "gateway" and importlib.util.find_spec("services.gateway") is None:
                typer.echo("gateway: not installed, skipped")
                continue
            if name == "ingest":  # publish only once the pipeline listens
                launcher.wait_healthy(PIPELINE)
            launcher.start(name)
        typer.echo(f"source:   {log or 'built-in simulator'} at rate {rate}")
        if prior_map is not None:
            typer.echo(f"map:      every robot starts on {prior_map.resolve()}")
        if backend.loop_closure:
            typer.echo("back end: loop closure on (the map is redrawn when a loop closes)")
            if backend.cull_m > 0:
                typer.echo(f"          keyframes culled within {backend.cull_m} m / "
                           f"{backend.cull_deg} deg of one drawn")
        typer.echo(f"gateway:  http://127.0.0.1:{port}/")
        typer.echo(f"zenoh:    tcp/127.0.0.1:{zenoh_port} (SCANFLOW_ZENOH_CONNECT)")
        typer.echo(f"data dir: {data_dir.resolve()}")
        typer.echo(f"logs:     {log_dir}")
        typer.echo("Ctrl-C stops everything.")
        reported: set[str] = set()
        while not stopping:
            for name, returncode in launcher.exited().items():
                if name not in reported:
                    reported.add(name)
                    typer.echo(f"{name} exited with code {returncode} (log: {log_dir / name}.log)")
            time.sleep(0.5)
    finally:
        typer.echo("stopping...")
        codes = launcher.stop_all(STOP_ORDER)
        for name, code in codes.items():
            typer.echo(f"  {name}: exit {code}")
    failed = sorted(name for name, code in codes.items() if code != 0)
    if failed:
        typer.echo(f"not a clean stop: {', '.join(failed)} (logs: {log_dir})", err=True)
        raise typer.Exit(1)
