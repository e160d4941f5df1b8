"""Where the real CARMEN logs live: ../shared/data beside the repository, or $SCANFLOW_DATA_DIR."""

from __future__ import annotations

import os
from pathlib import Path

import pytest


def data_dir() -> Path:
    """The shared data folder, from $SCANFLOW_DATA_DIR or beside the repository."""
    env = os.environ.get("SCANFLOW_DATA_DIR")
    return Path(env) if env else Path(__file__).resolve().parents[3] / ".." / "shared" / "data"


@pytest.fixture
def real_log():
    """Path of one real log by name; skips when the shared data is not present."""

    def find(name: str) -> Path:
        path = data_dir() / name
        if not path.is_file():
            pytest.skip(f"real log {name} not found in {data_dir()} (set SCANFLOW_DATA_DIR)")
        return path

    return find
