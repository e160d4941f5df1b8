"""Atomic per-robot snapshots in the data directory: map and trajectory in one native .npz.

One file, replaced atomically, so a crash leaves either the previous snapshot or the new one,
never a map without its trajectory. The file is a map in scanflow's native format (`load_npz`
reads it) with the trajectory and the last applied pose seq beside the map arrays, and, with
loop closure on, the keyframes (a later redraw needs their scans); a restart loads it back and
carries on from that seq. The keyframes' scans, which never change and grow with the run, are
written once, by chunks, into `<robot>.keyframes/`: a snapshot costs the same late in a long
run as early (20,000 keyframes took 3.2 s per snapshot when each rewrote them all).
"""

from __future__ import annotations

import functools
import math
import zipfile
import zlib
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scanflow import keys
from scanflow.backend import ScanNode
from scanflow.config import MapServerSettings
from scanflow.geometry import Pose2D
from scanflow.maps.export import grid_from_npz, npz_arrays, write_npz
from scanflow.maps.occupancy import OccupancyGrid
from scanflow.wire import MAX_COUNT, KeyframesMessage

from services.common.keyframes import scan_nodes
from services.mapserver.keyframes import FIELDS, Keyframes

# What a damaged file raises as it is read: a missing or cut one, a broken zip or deflate stream,
# an array or key that is not there (a file cut short, a disk that filled, a foreign file), or
# arrays and a map header that read but do not fit (another scanflow version, a file edited).
UNREADABLE = (
    OSError, KeyError, ValueError, EOFError, zipfile.BadZipFile, zlib.error, TypeError,
    AttributeError, IndexError, ArithmeticError,
)

SUFFIX = ".snapshot.npz"
PREVIOUS = ".previous"  # after SUFFIX: the map of the run the robot's current one replaced
_PER_FILE = "keyframes_per_file"
PER_FILE: int = MapServerSettings.model_fields["keyframes_per_file"].default


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
    last_odom: tuple[float, Pose2D] | None = None  # (stamp, odometry pose) of the last estimate
    run: int = 0  # the tracker's run the map is of (0: unknown)
    ended_runs: tuple[int, ...] = ()  # the runs it replaced (their late messages are dropped)


def snapshot_path(data_dir: Path, robot_id: str) -> Path:
    """Where the robot's snapshot is: `<data_dir>/<robot_id>.snapshot.npz`."""
    return data_dir / f"{robot_id}{SUFFIX}"


def save_snapshot(data_dir: Path, snap: Snapshot, per_file: int = PER_FILE) -> None:
    """Write the robot's map, trajectory and last seq as one file, replaced atomically. The
    keyframes' scans go `per_file` to a file of their own, each written once (a scan never
    changes): the snapshot holds their seqs and poses, and the scans of the last few."""
    data_dir.mkdir(parents=True, exist_ok=True)
    arrays: dict[str, ArrayLike] = dict(npz_arrays(snap.grid))  # int64 scalars join them
    arrays.update(
        stamps_s=snap.stamps_s, poses=snap.poses, last_seq=np.int64(snap.last_seq),
        redrawn_seq=np.int64(snap.redrawn_seq), last_insert_seq=np.int64(snap.last_insert_seq),
        run=np.int64(snap.run), ended_runs=np.array(snap.ended_runs, dtype=np.int64),
    )
    if snap.last_odom is not None:
        stamp_s, odom = snap.last_odom
        arrays["last_odom"] = np.array([stamp_s, *odom.to_array()])
    chunks: set[Path] = set()
    if snap.keyframes is not None:
        stored, chunks = _save_chunks(data_dir, snap.robot_id, snap.keyframes, per_file)
        arrays.update(snap.keyframes.arrays(snap.robot_id, stored))
        arrays[_PER_FILE] = np.int64(per_file)
    write_npz(snapshot_path(data_dir, snap.robot_id), arrays)
    folder = _chunk_dir(data_dir, snap.robot_id)  # files no snapshot refers to any more
    for path in folder.glob("*.npz") if folder.is_dir() else ():
        if path not in chunks:
            path.unlink(missing_ok=True)


def keep_previous(data_dir: Path, robot_id: str) -> Path | None:
    """Move the robot's last snapshot aside as `<robot>.snapshot.npz.previous` (replacing an
    older one), when a new run replaces its map: a run replaced by mistake (a matcher that
    could not resume in time starts a map of its own) can still be read as a map (`load_npz`;
    renamed to `.npz`, by `load_map` too). Where it went; None when there was none. The
    keyframes' files are the new run's to replace."""
    path = snapshot_path(data_dir, robot_id)
    if not path.exists():
        return None
    kept = path.with_name(f"{path.name}{PREVIOUS}")
    path.replace(kept)
    return kept


def remove_snapshot(data_dir: Path, robot_id: str) -> int:
    """Delete the robot's snapshot and the replaced run's (`.previous`), then its keyframes'
    files (a retired robot: a restart must not bring it back); how many files went. A
    snapshot set aside as unreadable stays: no start loads it. OSError naming the file that
    could not be deleted."""
    removed = 0
    path = snapshot_path(data_dir, robot_id)
    if path.exists():  # first: without it no start loads the robot, whatever is left below
        path.unlink()
        removed += 1
    previous = path.with_name(f"{path.name}{PREVIOUS}")
    if previous.exists():
        previous.unlink()
        removed += 1
    folder = _chunk_dir(data_dir, robot_id)
    if folder.is_dir():
        for chunk in sorted(folder.iterdir()):
            chunk.unlink(missing_ok=True)
            removed += 1
        folder.rmdir()
    return removed


def _chunk_dir(data_dir: Path, robot_id: str) -> Path:
    return data_dir / f"{robot_id}.keyframes"


def _chunk_path(data_dir: Path, robot_id: str, run: str, per_file: int, index: int) -> Path:
    return _chunk_dir(data_dir, robot_id) / f"{run}-{per_file}-{index:06d}.npz"


def _save_chunks(
    data_dir: Path, robot_id: str, kept: Keyframes, per_file: int
) -> tuple[int, set[Path]]:
    """Write each full file of `per_file` keyframes' scans not on disk yet; how many
    keyframes the files hold, and the files."""
    full = len(kept) // per_file
    paths = [_chunk_path(data_dir, robot_id, kept.run, per_file, i) for i in range(full)]
    for i, path in enumerate(paths):
        if not path.exists():
            path.parent.mkdir(exist_ok=True)
            message = kept.message(robot_id, i * per_file, (i + 1) * per_file)
            write_npz(path, {name: getattr(message, name) for name in FIELDS}, compressed=False)
    return full * per_file, set(paths)


def _load_chunks(
    data_dir: Path, robot_id: str, per_file: int, run: str, seqs: list[int]
) -> list[ScanNode]:
    """The scans of keyframes `seqs` from the run's files of `per_file` (ValueError if one is
    missing or holds other keyframes)."""
    nodes: list[ScanNode] = []
    for i in range(math.ceil(len(seqs) / per_file)):
        path = _chunk_path(data_dir, robot_id, run, per_file, i)
        with np.load(path, allow_pickle=False) as data:
            arrays = {name: data[name] for name in FIELDS}
        message = KeyframesMessage(robot_id, **arrays)
        if message.seqs.tolist() != seqs[i * per_file:(i + 1) * per_file]:
            raise ValueError(f"{path.name} holds other keyframes than the snapshot names")
        nodes += scan_nodes(message)
    return nodes


def load_snapshots(data_dir: Path) -> tuple[list[Snapshot], list[str]]:
    """Every robot snapshot in `data_dir` (none if the directory does not exist), and why any
    other was skipped (unreadable, or not a snapshot): it must not stop the service starting,
    and is set aside (renamed) so that the robot's fresh run does not overwrite it."""
    snaps: list[Snapshot] = []
    skipped: list[str] = []
    for path in sorted(data_dir.glob(f"*{SUFFIX}")):
        robot_id = path.name.removesuffix(SUFFIX)
        try:
            keys.check_robot_id(robot_id)  # a file not written by a map server: never served
            with np.load(path, allow_pickle=False) as data:
                grid = grid_from_npz(data, path)
                stamps_s = np.asarray(data["stamps_s"], dtype=np.float64)
                poses = np.asarray(data["poses"], dtype=np.float64)
                if stamps_s.ndim != 1 or poses.shape != (len(stamps_s), 3):
                    raise ValueError(f"poses {poses.shape} do not fit stamps {stamps_s.shape}")
                last_seq = int(data["last_seq"])
                redrawn_seq = int(data.get("redrawn_seq", -1))
                # Older files: the inserts up to the last pose are likely in.
                last_insert_seq = int(data.get("last_insert_seq", last_seq))
                last_odom = _last_odom(data)
                run = int(data.get("run", 0))  # older files: unknown, the next run's taken on
                ended = tuple(int(r) for r in data.get("ended_runs", np.zeros(0, np.int64)))
                if not all(0 <= r <= MAX_COUNT for r in (run, *ended)):
                    raise ValueError(f"runs must be counts, got {run} and ended {ended}")
                keyframes = _keyframes(data_dir, robot_id, data, skipped)
        except UNREADABLE as exc:
            skipped.append(
                f"robot {robot_id}: snapshot not loaded ({type(exc).__name__}: {exc}); "
                f"{_set_aside(path)}"
            )
            continue
        snaps.append(Snapshot(
            robot_id, grid, stamps_s, poses, last_seq, keyframes, redrawn_seq, last_insert_seq,
            last_odom, run, ended,
        ))
    return snaps, skipped


def _set_aside(path: Path) -> str:
    """Rename a snapshot that cannot be loaded out of the way, so that the robot's fresh run
    does not overwrite it (it may be all of a map a newer version can read); says where."""
    aside, n = path.with_name(f"{path.name}.unreadable"), 0
    while aside.exists():  # one set aside at an earlier start stays too
        n += 1
        aside = path.with_name(f"{path.name}.unreadable.{n}")
    try:
        path.rename(aside)
    except OSError as exc:
        return f"not set aside ({type(exc).__name__}: {exc})"
    return f"set aside as {aside.name}"


def _last_odom(data: Mapping[str, NDArray[np.generic]]) -> tuple[float, Pose2D] | None:
    """The (stamp, odometry pose) a snapshot keeps, None in files without it (older ones)."""
    if "last_odom" not in data:
        return None
    values = np.asarray(data["last_odom"], dtype=np.float64)
    if values.shape != (4,) or not np.isfinite(values).all():
        raise ValueError(f"last_odom must be 4 finite numbers, got {values.tolist()}")
    return float(values[0]), Pose2D.from_array(values[1:])


def _keyframes(
    data_dir: Path, robot_id: str, data: Mapping[str, NDArray[np.generic]], skipped: list[str]
) -> Keyframes | None:
    """The snapshot's keyframes; None, named in `skipped`, when they (or a chunk file) cannot
    be read: the map and the path still can, only this run's redraws cannot be followed."""
    try:
        per_file = int(data.get(_PER_FILE, 1))
        chunks = functools.partial(_load_chunks, data_dir, robot_id, per_file)
        return Keyframes.from_arrays(robot_id, data, chunks)
    except UNREADABLE as exc:
        skipped.append(
            f"robot {robot_id}: keyframes not loaded ({type(exc).__name__}: {exc}); its map and "
            "path are, but the map server cannot follow this run's redraws"
        )
        return None
