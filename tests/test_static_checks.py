"""The static checks pass on the code as it is: ruff's lint and mypy's types (both configured in
pyproject.toml), so an annotation that does not hold fails the suite like any other test."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def run_tool(*args: str, env: dict[str, str] | None = None) -> tuple[int, str]:
    """Exit code and output of `python -m <args>` with this Python (its ruff, its mypy), run
    from the repository root."""
    done = subprocess.run(
        [sys.executable, "-m", *args], cwd=ROOT, env=env, capture_output=True, text=True,
        timeout=240,
    )
    return done.returncode, done.stdout + done.stderr


def test_ruff_finds_nothing() -> None:
    code, output = run_tool("ruff", "check", ".")
    assert code == 0, f"ruff check . exited {code}:\n{output}"


@pytest.mark.slow  # 12-30 s of one core: every module checked afresh
@pytest.mark.second_lane  # beside the container tests, on the core they leave idle
def test_mypy_finds_no_type_error(tmp_path: Path) -> None:
    """mypy over pyproject's `files` (core library, services, benches) as on a fresh clone: a
    cache of its own, and `scanflow` read from this repository's shared/ (MYPYPATH), not from
    wherever the package is installed."""
    env = {**os.environ, "MYPYPATH": str(ROOT / "shared")}
    code, output = run_tool("mypy", "--cache-dir", str(tmp_path / "mypy-cache"), env=env)
    assert code == 0, f"mypy exited {code}:\n{output}"
