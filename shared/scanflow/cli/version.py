"""`scanflow version`: print the package version."""

import typer

from scanflow import __version__
from scanflow.cli import app


@app.command()
def version() -> None:
    """Print the scanflow version."""
    typer.echo(__version__)
