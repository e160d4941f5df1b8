"""Where the benchmarks and their tests find the real logs: $SCANFLOW_DATA_DIR, else the
`shared/data` folder beside the checkout (never imported by product code)."""

from __future__ import annotations

import os
from pathlib import Path

from scanflow.io.carmen import Keyframe, load_keyframes

_BESIDE = Path(__file__).resolve().parents[1] / ".." / "shared" / "data"
DATA_DIR = Path(os.environ.get("SCANFLOW_DATA_DIR", _BESIDE))


def corrected_log(name: str) -> Path:
    """The corrected CARMEN log `name` (intel, aces, freiburg-079) in DATA_DIR."""
    return DATA_DIR / f"{name}-corrected.log.gz"


def log_keyframes(path: Path, limit: int | None = None) -> list[Keyframe]:
    """The log's keyframes (`load_keyframes`), the first `limit` of them when one is given."""
    frames = load_keyframes(path)
    return frames[:limit] if limit else frames
