"""The scans a robot's tracker inserted, kept (with loop closure on) so that the tracker's map
redraws can be repeated here, and so that a restarted matcher can rebuild its back end from
them: every keyframe with the pose it is drawn at."""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np
from numpy.typing import NDArray
from scanflow.backend.loops import ScanNode
from scanflow.geometry import Pose2D
from scanflow.wire import KeyframesMessage, MapInsertMessage

from services.common.keyframes import scan_nodes

_PREFIX = "keyframes_"


class Keyframes:
    """Inserted scans by seq, in insertion order, and their poses (16 bytes per point)."""

    def __init__(self) -> None:
        self.seqs: list[int] = []
        self.nodes: list[ScanNode] = []
        self.poses: list[Pose2D] = []  # where each is drawn in the map now

    def __len__(self) -> int:
        return len(self.seqs)

    def add(self, scan: MapInsertMessage) -> None:
        """Keep the scan; one whose seq does not follow the last (a new run of the robot on a
        map resumed from a snapshot) starts the kept keyframes afresh, as its tracker did."""
        if self.seqs and scan.seq <= self.seqs[-1]:
            self.seqs, self.nodes, self.poses = [], [], []
        self.seqs.append(scan.seq)
        self.nodes.append(ScanNode(scan.stamp_s, scan.points, scan.no_return_points, scan.mount))
        self.poses.append(scan.pose)

    def check(self, seqs: NDArray[np.int64]) -> None:
        """Raise, naming the first difference, unless `seqs` are exactly the kept scans."""
        if len(seqs) != len(self.seqs) or not np.array_equal(seqs, self.seqs):
            mine, theirs = np.asarray(self.seqs, dtype=np.int64), np.asarray(seqs)
            n = min(len(mine), len(theirs))
            differ = np.flatnonzero(mine[:n] != theirs[:n])
            at = int(differ[0]) if differ.size else n
            raise ValueError(
                f"the redraw names {len(theirs)} keyframes, this map server holds {len(mine)}; "
                f"they differ from keyframe {at} on (seq {_at(theirs, at)} vs {_at(mine, at)})"
            )

    def moved(self, poses: NDArray[np.float64]) -> None:
        """The keyframes are drawn at `poses` (N, 3) now (after a redraw)."""
        self.poses = [Pose2D.from_array(p) for p in poses]

    def message(self, robot_id: str) -> KeyframesMessage:
        def rows(name: str) -> NDArray[np.float64]:
            return np.concatenate([getattr(n, name) for n in self.nodes] or [np.zeros((0, 2))])

        def counts(name: str) -> NDArray[np.int64]:
            return np.array([len(getattr(n, name)) for n in self.nodes], dtype=np.int64)

        return KeyframesMessage(
            robot_id,
            np.asarray(self.seqs, dtype=np.int64),
            np.array([n.stamp_s for n in self.nodes], dtype=np.float64),
            np.array([p.to_array() for p in self.poses]).reshape(-1, 3),
            np.array([n.mount.to_array() for n in self.nodes]).reshape(-1, 3),
            counts("points"),
            rows("points"),
            counts("no_return"),
            rows("no_return"),
        )

    @classmethod
    def from_message(cls, message: KeyframesMessage) -> Keyframes:
        kept = cls()
        kept.seqs = message.seqs.tolist()
        kept.poses = [Pose2D.from_array(p) for p in message.poses]
        kept.nodes = scan_nodes(message)
        return kept

    def arrays(self, robot_id: str) -> dict[str, NDArray[np.generic]]:
        """The keyframes as named arrays (for a snapshot .npz)."""
        fields = self.message(robot_id)
        return {f"{_PREFIX}{name}": getattr(fields, name) for name in _ARRAYS}

    @classmethod
    def from_arrays(
        cls, robot_id: str, data: Mapping[str, NDArray[np.generic]]
    ) -> Keyframes | None:
        """The keyframes saved by `arrays` (None when the file holds none); KeyError or
        ValueError (the message's own checks) when they are incomplete or inconsistent."""
        if f"{_PREFIX}seqs" not in data:
            return None
        saved = {name: np.asarray(data[f"{_PREFIX}{name}"]) for name in _ARRAYS}
        return cls.from_message(KeyframesMessage(robot_id, **saved))


_ARRAYS = tuple(name for name in KeyframesMessage.WIRE if name != "robot_id")


def _at(seqs: NDArray[np.int64], i: int) -> str:
    return str(int(seqs[i])) if i < len(seqs) else "none"
