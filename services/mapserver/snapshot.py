"""Atomic per-robot snapshots in the data directory: map and trajectory in one native .npz.

One file, replaced atomically, so a crash leaves either the previous snapshot or the new one,
never a map without its trajectory. The file is a map in scanflow's native format (`load_npz`
reads it) with the trajectory and the last applied pose seq beside the map arrays, and, with
loop closure on, the keyframes' scans (a later redraw needs them); a restart loads it back and
carries on from that seq.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray
from scanflow.maps.export import grid_from_npz, npz_arrays, write_npz
from scanflow.maps.occupancy import OccupancyGrid

from services.mapserver.keyframes import Keyframes

SUFFIX = ".snapshot.npz"


@dataclass
class Snapshot:
    """What survives a restart for one robot."""

    robot_id: str
    grid: OccupancyGrid
    stamps_s: NDArray[np.float64]
    poses: NDArray[np.float64]
    last_seq: int
    keyframes: Keyframes | None = None
    redrawn_seq: int = -1  # the scan of the last redraw (its path already holds up to it)
    last_insert_seq: int = -1  # the last insert in the map (the next names the one before it)


def snapshot_path(data_dir: Path, robot_id: str) -> Path:
    return data_dir / f"{robot_id}{SUFFIX}"


def save_snapshot(data_dir: Path, snap: Snapshot) -> None:
    """Write the robot's map, trajectory and last seq as one file, replaced atomically."""
    data_dir.mkdir(parents=True, exist_ok=True)
    arrays = npz_arrays(snap.grid)
    arrays.update(
        stamps_s=snap.stamps_s, poses=snap.poses, last_seq=np.int64(snap.last_seq),
        redrawn_seq=np.int64(snap.redrawn_seq), last_insert_seq=np.int64(snap.last_insert_seq),
    )
    if snap.keyframes is not None:
        arrays.update(snap.keyframes.arrays(snap.robot_id))
    write_npz(snapshot_path(data_dir, snap.robot_id), arrays)


def load_snapshots(data_dir: Path) -> tuple[list[Snapshot], list[str]]:
    """Every robot snapshot in `data_dir` (none if the directory does not exist), and why any
    other was skipped (unreadable, or not a snapshot): it must not stop the service starting."""
    snaps, skipped = [], []
    for path in sorted(data_dir.glob(f"*{SUFFIX}")):
        robot_id = path.name.removesuffix(SUFFIX)
        try:
            with np.load(path, allow_pickle=False) as data:
                grid = grid_from_npz(data, path)
                stamps_s, poses = data["stamps_s"], data["poses"]
                if poses.shape != (len(stamps_s), 3):
                    raise ValueError(f"poses {poses.shape} do not fit {len(stamps_s)} stamps")
                last_seq = int(data["last_seq"])
                redrawn_seq = int(data.get("redrawn_seq", -1))
                # Older files: the inserts up to the last pose are likely in.
                last_insert_seq = int(data.get("last_insert_seq", last_seq))
                keyframes = Keyframes.from_arrays(robot_id, data)
        except (OSError, KeyError, ValueError) as exc:
            skipped.append(f"robot {robot_id}: snapshot not loaded ({type(exc).__name__}: {exc})")
            continue
        snaps.append(Snapshot(
            robot_id, grid, stamps_s, poses, last_seq, keyframes, redrawn_seq, last_insert_seq
        ))
    return snaps, skipped
