"""Shared inputs of the bench tests."""

from __future__ import annotations

import math
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
from scanflow.geometry import Pose2D
from scanflow.io.carmen import Keyframe
from scanflow.scan import LaserScan

REPO = Path(__file__).resolve().parents[2]


def run_bench(
    module: str, *args: str, timeout_s: float = 300.0, check: bool = False
) -> subprocess.CompletedProcess[str]:
    """`python -m bench.<module> ARGS` from the repository's root, its output captured as text
    (`check`: a non-zero exit raises)."""
    return subprocess.run(
        [sys.executable, "-m", f"bench.{module}", *args],
        cwd=REPO, capture_output=True, text=True, timeout=timeout_s, check=check,
    )


def usage_error(
    main: Callable[[list[str]], None], capsys: pytest.CaptureFixture[str], *args: str
) -> str:
    """What a bench's `main(ARGS)` says on stderr as it exits with argparse's usage error
    (exit code 2): in this process, as a subprocess would spend seconds importing."""
    with pytest.raises(SystemExit) as stop:
        main(list(args))
    assert stop.value.code == 2
    return capsys.readouterr().err


@pytest.fixture
def frames() -> list[Keyframe]:
    """Seven log records of a robot driving 10 cm per scan past a sloped wall."""
    ranges = np.linspace(1.0, 4.0, 180)
    return [
        Keyframe(
            LaserScan(ranges, -math.pi / 2, math.pi / 180, stamp_s=0.1 * i),
            Pose2D(0.1 * i, 0.0, 0.0), Pose2D(0.1 * i, 0.0, 0.0),
        )
        for i in range(7)
    ]
