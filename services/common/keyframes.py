"""Keyframes off the wire: what the map server serves and a resuming matcher rebuilds from."""

from __future__ import annotations

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
