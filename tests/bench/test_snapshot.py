"""bench.snapshot: the first and the next snapshot of a run, its files and its load."""

from __future__ import annotations

from scanflow.io.carmen import Keyframe

from bench.snapshot import GROWTH, map_of, run


def test_a_run_is_snapshot_twice_and_loads_whole(frames: list[Keyframe]) -> None:
    row = run(frames, map_of(frames, 3), 40, per_file=16)
    assert row["keyframes"] == 40 and row["loaded_keyframes"] == 40 + GROWTH
    assert row["first_s"] > 0 and row["next_s"] > 0 and row["load_s"] > 0
    assert row["disk_mib"] > 0
