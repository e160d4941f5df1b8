"""Atomic per-robot snapshots in the data directory: the map (native .npz) and the trajectory.

A restart loads them back and carries on from the last pose seq it had applied.
"""

from __future__ import annotations

import io
import os
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray
from scanflow.maps.export import load_npz, save_npz
from scanflow.maps.occupancy import OccupancyGrid


@dataclass
class Snapshot:
    """What survives a restart for one robot."""

    robot_id: str
    grid: OccupancyGrid
    stamps_s: NDArray[np.float64]
    poses: NDArray[np.float64]
    last_seq: int


def _paths(data_dir: Path, robot_id: str) -> tuple[Path, Path]:
    return data_dir / f"{robot_id}.map.npz", data_dir / f"{robot_id}.trajectory.npz"


def save_snapshot(data_dir: Path, snap: Snapshot) -> None:
    """Write the map, then the trajectory and last seq; each file replaced atomically."""
    data_dir.mkdir(parents=True, exist_ok=True)
    map_path, trajectory_path = _paths(data_dir, snap.robot_id)
    save_npz(snap.grid, map_path)
    buffer = io.BytesIO()
    np.savez(buffer, stamps_s=snap.stamps_s, poses=snap.poses, last_seq=np.int64(snap.last_seq))
    fd, tmp = tempfile.mkstemp(dir=data_dir, prefix=f".{trajectory_path.name}.")
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(buffer.getvalue())
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, trajectory_path)
    finally:
        Path(tmp).unlink(missing_ok=True)


def load_snapshots(data_dir: Path) -> tuple[list[Snapshot], list[str]]:
    """Every complete robot snapshot in `data_dir` (none if the directory does not exist), and
    why any other was skipped: a crash between the two writes of a robot's first snapshot
    leaves a map without a trajectory, which must not stop the service from starting."""
    snaps, skipped = [], []
    for map_path in sorted(data_dir.glob("*.map.npz")):
        robot_id = map_path.name.removesuffix(".map.npz")
        _, trajectory_path = _paths(data_dir, robot_id)
        try:
            with np.load(trajectory_path, allow_pickle=False) as data:
                stamps_s, poses = data["stamps_s"], data["poses"]
                last_seq = int(data["last_seq"])
            grid = load_npz(map_path)
        except (OSError, KeyError, ValueError) as exc:
            skipped.append(f"robot {robot_id}: snapshot not loaded ({type(exc).__name__}: {exc})")
            continue
        snaps.append(Snapshot(robot_id, grid, stamps_s, poses, last_seq))
    return snaps, skipped
