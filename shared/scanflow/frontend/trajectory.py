"""The estimated trajectory: stamps and poses in growable arrays, exportable in TUM format.

TUM lines are `stamp x y z qx qy qz qw` (evo, rpg tools); a planar pose has z = 0 and the
quaternion of a rotation by theta about z: (0, 0, sin(theta/2), cos(theta/2)). Memory is
32 bytes per pose; nothing per scan beyond that.
"""

from __future__ import annotations

import os
import warnings
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from scanflow.geometry import Pose2D, normalize_angles

_INITIAL_CAPACITY = 256


class TrajectoryStore:
    """Append-only (stamp_s, x, y, theta) rows with amortised doubling growth."""

    def __init__(self) -> None:
        self._rows = np.empty((_INITIAL_CAPACITY, 4))
        self._count = 0

    @classmethod
    def of(cls, stamps_s: NDArray[np.float64], poses: NDArray[np.float64]) -> TrajectoryStore:
        """A store holding `poses` (N, 3) at `stamps_s` (N,), e.g. a saved or corrected path."""
        store = cls()
        n = len(stamps_s)
        store._rows = np.empty((max(n, _INITIAL_CAPACITY), 4))
        store._rows[:n, 0] = stamps_s
        store._rows[:n, 1:] = np.asarray(poses).reshape(n, 3)
        store._count = n
        return store

    def __len__(self) -> int:
        return self._count

    def append(self, stamp_s: float, pose: Pose2D) -> None:
        """Add one row (stamp_s, x, y, theta), doubling the buffer when it is full."""
        if self._count == len(self._rows):
            grown = np.empty((2 * len(self._rows), 4))
            grown[: self._count] = self._rows
            self._rows = grown
        self._rows[self._count] = (stamp_s, pose.x, pose.y, pose.theta)
        self._count += 1

    @property
    def stamps_s(self) -> NDArray[np.float64]:
        """(N,) stamps, a read-only view."""
        view = self._rows[: self._count, 0]
        view.flags.writeable = False
        return view

    @property
    def poses(self) -> NDArray[np.float64]:
        """(N, 3) rows of x, y, theta, a read-only view."""
        view = self._rows[: self._count, 1:]
        view.flags.writeable = False
        return view

    @property
    def nbytes(self) -> int:
        """Bytes held by the row buffer, spare capacity included."""
        return self._rows.nbytes

    def save_tum(self, path: Path | str) -> Path:
        """Write the trajectory as a TUM file at `path`, atomically; returns the path."""
        return save_tum(path, self.stamps_s, self.poses)


def tum_text(stamps_s: NDArray[np.float64], poses: NDArray[np.float64]) -> str:
    """TUM lines for (N,) stamps and (N, 3) planar poses."""
    stamps_s = np.asarray(stamps_s, dtype=np.float64).reshape(-1)
    poses = np.asarray(poses, dtype=np.float64)
    if poses.shape != (len(stamps_s), 3):
        raise ValueError(f"poses must have shape ({len(stamps_s)}, 3), got {poses.shape}")
    half = 0.5 * poses[:, 2]
    zeros = np.zeros(len(stamps_s))
    rows = np.column_stack(
        (stamps_s, poses[:, 0], poses[:, 1], zeros, zeros, zeros, np.sin(half), np.cos(half))
    )
    return "".join(
        f"{row[0]:.6f} " + " ".join(f"{v:.9g}" for v in row[1:]) + "\n" for row in rows
    )


def save_tum(path: Path | str, stamps_s: NDArray[np.float64], poses: NDArray[np.float64]) -> Path:
    """Write a TUM file atomically (temporary file, then rename)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_text(tum_text(stamps_s, poses))
    os.replace(tmp, path)
    return path


def load_tum(path: Path | str) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """(stamps_s, (N, 3) x y theta) from a planar TUM file (comments '#' skipped); an empty
    one, as an empty trajectory is saved, gives no poses."""
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", "loadtxt: input contained no data", UserWarning)
        data = np.loadtxt(path, comments="#", ndmin=2)
    if data.size == 0:
        return np.zeros(0), np.zeros((0, 3))
    if data.shape[1] != 8:
        raise ValueError(f"{path}: TUM rows need 8 columns, got {data.shape[1]}")
    theta = normalize_angles(2.0 * np.arctan2(data[:, 6], data[:, 7]))
    return data[:, 0], np.column_stack((data[:, 1], data[:, 2], theta))
