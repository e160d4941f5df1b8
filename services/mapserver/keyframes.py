"""The scans a robot's tracker inserted, kept (with loop closure on) so that the tracker's map
redraws can be repeated here, and so that a restarted matcher can rebuild its back end from
them: every keyframe with the pose it is drawn at."""

from __future__ import annotations

import secrets
from collections.abc import Callable, Mapping

import numpy as np
from numpy.typing import NDArray
from scanflow.backend.loops import ScanNode
from scanflow.geometry import Pose2D
from scanflow.wire import KeyframesMessage, MapInsertMessage

from services.common.keyframes import keyframes_message, scan_nodes

_PREFIX = "keyframes_"


class Keyframes:
    """Inserted scans by seq, in insertion order, and their poses (16 bytes per point)."""

    def __init__(self) -> None:
        self.seqs: list[int] = []
        self.nodes: list[ScanNode] = []
        self.poses: list[Pose2D] = []  # where each is drawn in the map now
        self.run = secrets.token_hex(4)  # names this run's keyframes on disk (a new run: anew)

    def __len__(self) -> int:
        return len(self.seqs)

    def add(self, scan: MapInsertMessage) -> None:
        """Keep the scan; one whose seq does not follow the last (a new run of the robot on a
        map resumed from a snapshot) starts the kept keyframes afresh, as its tracker did."""
        if self.seqs and scan.seq <= self.seqs[-1]:
            self.seqs, self.nodes, self.poses = [], [], []
            self.run = secrets.token_hex(4)
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

    def message(self, robot_id: str, first: int = 0, end: int | None = None) -> KeyframesMessage:
        """Keyframes first..end-1 (default: all) as one message."""
        poses = [p.to_array() for p in self.poses[first:end]]
        return keyframes_message(robot_id, self.seqs[first:end], self.nodes[first:end], poses)

    @classmethod
    def from_message(cls, message: KeyframesMessage) -> Keyframes:
        """The keyframes a KeyframesMessage carries, under a new run id."""
        kept = cls()
        kept.seqs = message.seqs.tolist()
        kept.poses = [Pose2D.from_array(p) for p in message.poses]
        kept.nodes = scan_nodes(message)
        return kept

    def arrays(self, robot_id: str, stored: int = 0) -> dict[str, NDArray[np.generic]]:
        """The keyframes as named arrays for a snapshot .npz: every seq and pose, and the scans
        of those past the first `stored` (the snapshot keeps those in files of their own).
        With `stored` 0 these are exactly the arrays of a whole `message`."""
        tail = self.message(robot_id, stored)
        arrays = {f"{_PREFIX}{name}": getattr(tail, name) for name in FIELDS}
        arrays.update({
            f"{_PREFIX}seqs": np.asarray(self.seqs, dtype=np.int64),
            f"{_PREFIX}poses": np.array([p.to_array() for p in self.poses]).reshape(-1, 3),
            f"{_PREFIX}stored": np.int64(stored),
            f"{_PREFIX}run": np.array(self.run),
        })
        return arrays

    @classmethod
    def from_arrays(
        cls,
        robot_id: str,
        data: Mapping[str, NDArray[np.generic]],
        stored: Callable[[str, list[int]], list[ScanNode]] = lambda run, seqs: [],
    ) -> Keyframes | None:
        """The keyframes saved by `arrays` (None when the file holds none); `stored(run,
        seqs)` gives the scans of the first keyframes, kept elsewhere. KeyError or ValueError
        (the message's own checks) when they are incomplete or inconsistent."""
        if f"{_PREFIX}seqs" not in data:
            return None
        seqs = np.asarray(data[f"{_PREFIX}seqs"]).tolist()
        poses = np.asarray(data[f"{_PREFIX}poses"])
        first = int(data.get(f"{_PREFIX}stored", 0))
        saved = {name: np.asarray(data[f"{_PREFIX}{name}"]) for name in FIELDS}
        tail = KeyframesMessage(
            robot_id, **{**saved, "seqs": np.asarray(seqs[first:], dtype=np.int64),
                         "poses": poses[first:]}
        )
        kept = cls.from_message(tail)
        if f"{_PREFIX}run" in data:
            kept.run = str(data[f"{_PREFIX}run"])
        kept.nodes = (stored(kept.run, seqs[:first]) if first else []) + kept.nodes
        kept.seqs, kept.poses = seqs, [Pose2D.from_array(p) for p in poses]
        if len(kept.nodes) != len(seqs):
            raise ValueError(f"{len(kept.nodes)} keyframe scans for {len(seqs)} keyframes")
        return kept


FIELDS = tuple(name for name in KeyframesMessage.WIRE if name != "robot_id")  # as arrays


def _at(seqs: NDArray[np.int64], i: int) -> str:
    return str(int(seqs[i])) if i < len(seqs) else "none"
