"""The map server's kept keyframes: a new run on a resumed map starts them afresh."""

from __future__ import annotations

from scanflow.maps.occupancy import OccupancyGrid, OccupancyParams

from services.mapserver import replies
from services.mapserver.robot import RobotMap
from services.mapserver.snapshot import load_snapshots, save_snapshot


def test_a_new_run_on_a_resumed_map_starts_the_kept_keyframes_afresh(tmp_path, insert, pose):
    """The robot's seqs start again at 0 on a map resumed from a snapshot: its tracker keeps
    only the new run's keyframes, and so does the map server (still strictly increasing, so
    the snapshot and the keyframes query keep working)."""
    robot = RobotMap("r", lambda: OccupancyGrid(OccupancyParams()), keep_keyframes=True)
    for seq in (3, 7):
        robot.insert(insert(seq))
    robot.apply(pose(7))
    save_snapshot(tmp_path, robot.snapshot())
    (snap,), _ = load_snapshots(tmp_path)
    resumed = RobotMap("r", lambda: OccupancyGrid(OccupancyParams()), snap, keep_keyframes=True)
    resumed.insert(insert(0))
    resumed.apply(pose(0))
    assert resumed.keyframes.seqs == [0]
    save_snapshot(tmp_path, resumed.snapshot())
    assert replies.resume(resumed).keyframes.seqs.tolist() == [0]
