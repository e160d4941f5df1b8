"""`scanflow serve <service>`: run one service process (the same as `python -m services.<name>`)."""

from __future__ import annotations

import importlib.util
import runpy
from enum import StrEnum
from typing import Annotated

import typer

from scanflow.cli import app


class ServiceName(StrEnum):
    router = "router"
    ingest = "ingest"
    deskew = "deskew"
    matcher = "matcher"
    mapserver = "mapserver"
    gateway = "gateway"


@app.command()
def serve(name: Annotated[ServiceName, typer.Argument(help="which service to run")]) -> None:
    """Run one scanflow service in this process; settings come from SCANFLOW_* variables."""
    module = f"services.{name.value}"
    if importlib.util.find_spec(module) is None:
        raise typer.BadParameter(f"service {name.value!r} is not installed ({module} is missing)")
    runpy.run_module(module, run_name="__main__", alter_sys=True)
