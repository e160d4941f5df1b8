"""Shared checks of the command-line tests."""

from __future__ import annotations

from scanflow.cli import _register, app
from typer.testing import CliRunner


def assert_usage_error(args: list[str], named: str) -> None:
    """`scanflow ARGS` exits 2 with a message naming `named`: a usage error, not a traceback."""
    _register()
    result = CliRunner().invoke(app, args)
    assert result.exit_code == 2, result.output
    assert isinstance(result.exception, SystemExit)  # a message, not a traceback
    assert named in result.output
