"""`scanflow version`: prints the version the installed package's metadata reports."""

from __future__ import annotations

import subprocess
import sys
from importlib import metadata

from scanflow.cli import _register, app
from typer.testing import CliRunner


def test_version_prints_the_installed_package_version() -> None:
    _register()
    result = CliRunner().invoke(app, ["version"])
    assert result.exit_code == 0, result.output
    assert result.output == f"{metadata.version('scanflow')}\n"


def test_python_m_scanflow_version_prints_the_same() -> None:
    """The entry point `python -m scanflow` registers the subcommand too (not only the tests)."""
    done = subprocess.run(
        [sys.executable, "-m", "scanflow", "version"], capture_output=True, text=True, timeout=60
    )
    assert done.returncode == 0, done.stderr
    assert done.stdout == f"{metadata.version('scanflow')}\n"
