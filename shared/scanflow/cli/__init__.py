"""The `scanflow` command line: one module per subcommand, registered on `app` here."""

from __future__ import annotations

import math
from pathlib import Path
from typing import TYPE_CHECKING

import typer

if TYPE_CHECKING:
    from scanflow.io.detect import LogFormat

app = typer.Typer(
    name="scanflow",
    help="2D LiDAR pipeline: simulate, inspect logs, run the services, benchmark.",
    no_args_is_help=True,
    add_completion=False,
)


@app.callback()
def _root() -> None:
    """2D LiDAR pipeline: simulate, inspect logs, run the services, benchmark."""


def finite_or_none(value: float) -> float | None:
    """`value` rounded to 4 decimals for a --json summary, None for NaN or an infinity (JSON
    has neither: `json.dumps` would write tokens no JSON parser reads)."""
    return round(value, 4) if math.isfinite(value) else None


class SkippedRecords:
    """A log's unreadable records, as its reader reports them (the `on_error` callback): how
    many, and the first few to name."""

    SHOWN = 5

    def __init__(self) -> None:
        self.count = 0
        self.first: list[str] = []

    def __call__(self, message: str) -> None:
        self.count += 1
        if len(self.first) < self.SHOWN:
            self.first.append(message)

    def warn(self) -> None:
        """Name them on stderr: a run on part of a log (cut short, damaged) says so."""
        if self.count:
            typer.echo(f"warning: {self.count} unreadable records of the log skipped, the "
                       f"first {len(self.first)}:", err=True)
            for message in self.first:
                typer.echo(f"  {message}", err=True)


def check_log(log: Path) -> LogFormat:
    """The format of a --log (see `detect_format`); one that is no log (missing, unreadable, a
    directory that is no ROS 2 bag) is refused as a usage error naming it, before anything
    runs."""
    from scanflow.io.detect import detect_format

    try:
        return detect_format(log)
    except (OSError, ValueError) as exc:
        raise typer.BadParameter(str(exc), param_hint="--log") from exc


def main() -> None:
    """Console entry point."""
    _register()
    app()


def _register() -> None:
    # Subcommand modules attach themselves to `app` on import.
    from scanflow.cli import (  # noqa: F401
        calibrate,
        inspect,
        run,
        serve,
        settings,
        simulate,
        up,
        version,
    )
