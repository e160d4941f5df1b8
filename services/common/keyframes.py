"""Keyframes on and off the wire: what the map server serves and keeps, what a resuming
matcher rebuilds from, and what a matcher's whole map carries."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scanflow.backend import ScanNode
from scanflow.geometry import Pose2D
from scanflow.wire import KeyframesMessage


def scan_nodes(message: KeyframesMessage) -> list[ScanNode]:
    """The message's keyframes as the back end keeps them (scans in the robot's frame)."""
    return [
        ScanNode(float(stamp), hits, misses, Pose2D.from_array(mount))
        for stamp, (hits, misses), mount in zip(
            message.stamps_s, message.scans(), message.mounts, strict=True
        )
    ]


def keyframes_message(
    robot_id: str, seqs: Sequence[int], nodes: Sequence[ScanNode], poses: ArrayLike
) -> KeyframesMessage:
    """Keyframes (the scans of `seqs`, drawn at `poses`, rows x y theta) as one message."""

    def rows(name: str) -> NDArray[np.float64]:
        return np.concatenate([getattr(n, name) for n in nodes] or [np.zeros((0, 2))])

    def counts(name: str) -> NDArray[np.int64]:
        return np.array([len(getattr(n, name)) for n in nodes], dtype=np.int64)

    return KeyframesMessage(
        robot_id,
        np.asarray(seqs, dtype=np.int64),
        np.array([n.stamp_s for n in nodes], dtype=np.float64),
        np.asarray(poses, dtype=np.float64).reshape(-1, 3),
        np.array([n.mount.to_array() for n in nodes]).reshape(-1, 3),
        counts("points"),
        rows("points"),
        counts("no_return"),
        rows("no_return"),
    )
