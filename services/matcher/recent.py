"""A robot's last inserts, kept by its matcher to send again to a map server that missed some.

A map server finds a missed insert by the chain of `MapInsertMessage.previous_seq` (a link to
the router that dropped, a map server restarted from a snapshot a few seconds old) and asks
for what it lacks (services.common.resend). Past the last few, a robot tracked with loop
closure still has its keyframes: its back end keeps each (`keyframe_inserts`), all but the
inserts it culled as keyframes. Without a back end, or when it culled some of them, the
matcher sends its whole map instead (`map_state`): the map server takes it in place of the
inserts it missed.
"""

from __future__ import annotations

import threading
from bisect import bisect_left, bisect_right
from collections import deque
from collections.abc import Sequence

import numpy as np
from scanflow.backend import Mapper
from scanflow.frontend import Frontend
from scanflow.maps.export import npz_arrays, npz_bytes
from scanflow.wire import MapInsertMessage, MapRedrawMessage, MapStateMessage

from services.common.keyframes import keyframes_message
from services.common.resend import FIRST

_BEFORE_RESUME = FIRST - 1  # the unknown insert a resumed run's first followed: never asked for


class RecentInserts:
    """The last `capacity` encoded inserts of one robot's run `run` (its token, which the
    run's every insert, redraw, map state and estimate carries), with the chain's last seq.

    A run `resumed` from the map server's map starts mid-chain: its first insert names no
    previous one, yet is not the run's first, so it never answers "from the run's first"
    (FIRST): that asker gets the keyframes or the whole map, not a map missing the start."""

    def __init__(self, capacity: int, run: int, resumed: bool = False) -> None:
        self.run = run
        self._kept: deque[tuple[int, int, bytes]] = deque(maxlen=capacity)  # seq, previous
        self._unlinked = _BEFORE_RESUME if resumed else FIRST  # what a first insert follows
        self._lock = threading.Lock()  # the worker adds while a resend query reads
        self.last_seq: int | None = None  # the run's last insert (None: none yet, or unknown)
        self.scan_seq: int | None = None  # the tracker's last scan
        self.map_seq: int | None = None  # the last scan in the tracker's map
        # The last redraw, for its corrected path (kept until the next: 32 bytes per scan).
        self.redrawn: MapRedrawMessage | None = None

    def tracked(self, seq: int, inserted: bool, redraw: MapRedrawMessage | None = None) -> None:
        """The tracker took scan `seq`, into its map if `inserted`, and redrew its map after
        it if `redraw`. Called under the lock that guards the tracker, so that `map_state`
        sees its map and these at one instant."""
        self.scan_seq = seq
        if inserted:
            self.map_seq = seq
        if redraw is not None:
            self.redrawn = redraw

    def add(self, seq: int, previous_seq: int | None, payload: bytes) -> None:
        """Keep the insert of `seq` (encoded as `payload`) that followed `previous_seq`."""
        with self._lock:
            previous = self._unlinked if previous_seq is None else previous_seq
            self._kept.append((seq, previous, payload))
            self.last_seq = seq

    def kept(self) -> int:
        """How many inserts are kept."""
        with self._lock:
            return len(self._kept)

    def between(self, after: int, through: int) -> list[bytes]:
        """The inserts after seq `after` through seq `through`, in order; LookupError naming
        what is kept when they are not all here."""
        with self._lock:
            kept = list(self._kept)
        start = next((i for i, (_, previous, _) in enumerate(kept) if previous == after), None)
        end = next((i for i, (seq, _, _) in enumerate(kept) if seq == through), None)
        if start is None or end is None or end < start:
            span = f"seqs {kept[0][0]}..{kept[-1][0]}" if kept else "none"
            raise LookupError(
                f"the inserts after seq {after} through {through} are not all kept here "
                f"(the last {len(kept)} inserts: {span})"
            )
        return [payload for _, _, payload in kept[start : end + 1]]


def map_state(
    robot_id: str, frontend: Frontend, recent: RecentInserts, mapper: Mapper | None = None
) -> MapStateMessage:
    """The tracker's whole map (every insert through `recent.map_seq`), its path as the map
    server has it (the last redraw's, then the front end's estimates) and, with a back end,
    its keyframes where they are drawn; call it under the lock that guards the tracker.
    LookupError when it has inserted nothing."""
    if recent.scan_seq is None or recent.map_seq is None:
        raise LookupError(f"robot {robot_id}: this matcher has put no scan into its map")
    stamps, poses = frontend.trajectory.stamps_s, frontend.trajectory.poses
    redraw = recent.redrawn
    if redraw is not None and len(redraw.stamps_s):
        later = stamps > redraw.stamps_s[-1]
        stamps = np.concatenate((redraw.stamps_s, stamps[later]))
        poses = np.concatenate((redraw.poses, poses[later]))
    kept = None if mapper is None else keyframes_message(
        robot_id, mapper.keyframe_seqs, mapper.nodes, mapper.drawn_poses()
    )
    return MapStateMessage(
        robot_id, recent.scan_seq, recent.map_seq, npz_bytes(npz_arrays(frontend.map.grid)),
        stamps, poses, kept, recent.run,
    )


def keyframe_inserts(
    mapper: Mapper, robot_id: str, run: int, after: int, through: int
) -> tuple[list[MapInsertMessage], int]:
    """The inserts of run `run` after seq `after` (-1: from the first) through seq `through`,
    rebuilt from the back end's keyframes at the poses they are drawn at now: the pose each went
    in at, or where the last redraw put it. Inserts the back end culled as keyframes (`cull_m`)
    are not kept: they are left out, the chain linking the keyframes around them, and how many
    it knows of is returned beside (`culled_between`)."""
    culled = culled_between(mapper, after, through)
    seqs = mapper.keyframe_seqs
    inserts, previous = [], None if after == FIRST else after
    for k in range(bisect_right(seqs, after), bisect_right(seqs, through)):
        node = mapper.nodes[k]
        inserts.append(MapInsertMessage(
            robot_id, seqs[k], node.stamp_s, mapper.drawn_pose(k), node.points, node.no_return,
            node.mount, previous, run=run,
        ))
        previous = seqs[k]
    return inserts, culled


def culled_between(mapper: Mapper, after: int, through: int) -> int:
    """How many of the inserts after seq `after` through seq `through` the back end culled as
    keyframes. LookupError when `after` or `through` is neither a keyframe nor culled; a
    resumed back end knows no culled seqs from before its restart, so an `after` from then is
    taken as one."""
    seqs, culled = mapper.keyframe_seqs, mapper.culled_seqs
    for name, seq in (("after", after), ("through", through)):
        held = _holds(seqs, seq) or _holds(culled, seq)
        if not held and not (name == "after" and (seq == FIRST or _before_restart(mapper, seq))):
            span = f"seqs {seqs[0]}..{seqs[-1]}" if seqs else "none"
            raise LookupError(
                f"the back end's keyframes ({len(seqs)}: {span}) and culled inserts "
                f"({len(culled)}) do not hold seq {seq} ({name})"
            )
    return bisect_right(culled, through) - bisect_right(culled, after)


def _before_restart(mapper: Mapper, seq: int) -> bool:
    """Whether `seq` may be an insert of the run a resumed back end carried on: older than
    every insert since."""
    resumed, seqs, culled = mapper.resumed_keyframes, mapper.keyframe_seqs, mapper.culled_seqs
    if not resumed:
        return False
    since = ([seqs[resumed]] if len(seqs) > resumed else []) + ([culled[0]] if culled else [])
    return not since or seq < min(since)


def _holds(ordered: Sequence[int], seq: int) -> bool:
    i = bisect_left(ordered, seq)
    return i < len(ordered) and ordered[i] == seq
