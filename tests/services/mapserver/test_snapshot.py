"""Map server snapshots: saved and loaded, keyframes in chunks, damaged files skipped."""

from __future__ import annotations

import json

import numpy as np
import pytest
from scanflow.geometry import Pose2D
from scanflow.maps.export import load_npz, save_npz
from scanflow.maps.occupancy import OccupancyGrid, OccupancyParams
from scanflow.wire import MapInsertMessage

from services.mapserver.robot import RobotMap
from services.mapserver.snapshot import load_snapshots, remove_snapshot, save_snapshot


def test_snapshot_round_trip(tmp_path, new_robot, insert, pose):
    robot = new_robot()
    for seq in range(3):
        robot.insert(insert(seq, Pose2D(0.1 * seq, 0.0, 0.0)))
        robot.apply(pose(seq, Pose2D(0.1 * seq, 0.0, 0.0)))
    save_snapshot(tmp_path, robot.snapshot())
    (snap,), skipped = load_snapshots(tmp_path)
    again = new_robot(snap)
    assert again.last_seq == 2 and again.state == robot.state and skipped == []
    assert again.last_insert_seq == 2  # the next insert names its predecessor: checked
    np.testing.assert_array_equal(again.map.grid.log_odds, robot.map.grid.log_odds)
    np.testing.assert_array_equal(again.trajectory.poses, robot.trajectory.poses)
    assert not list(tmp_path.glob(".*"))  # no temporary files left behind


def test_a_snapshot_is_one_file_that_loads_as_a_map(tmp_path, new_robot, insert, pose):
    robot = new_robot()
    robot.insert(insert(0))
    robot.apply(pose(0))
    save_snapshot(tmp_path, robot.snapshot())
    (path,) = tmp_path.iterdir()  # map and trajectory together: no crash can split them
    assert path.name == "r.snapshot.npz"
    np.testing.assert_array_equal(load_npz(path).log_odds, robot.map.grid.log_odds)


def test_an_unreadable_snapshot_is_skipped_and_named_not_a_crash(tmp_path, new_robot, insert, pose):
    robot = new_robot()
    robot.insert(insert(0))
    robot.apply(pose(0))
    save_snapshot(tmp_path, robot.snapshot())
    (tmp_path / "s.snapshot.npz").write_bytes(b"not a zip file")
    save_npz(robot.map.grid, tmp_path / "m.snapshot.npz")  # a map without a trajectory
    snaps, skipped = load_snapshots(tmp_path)
    assert [s.robot_id for s in snaps] == ["r"]
    assert len(skipped) == 2 and "robot m" in skipped[0] and "robot s" in skipped[1]


@pytest.mark.parametrize("cut", [0, 0.5, -10])
def test_a_snapshot_cut_short_is_skipped_and_named_not_a_crash(tmp_path, cut, kept_robot):
    """A disk that filled or a kill mid-copy: the map server starts without that robot (an
    audit saw it exit 1 on a BadZipFile, a crash loop under `restart: unless-stopped`)."""
    robot = kept_robot(range(5))
    save_snapshot(tmp_path, robot.snapshot(), 2)
    path = tmp_path / "r.snapshot.npz"
    data = path.read_bytes()
    path.write_bytes(data[: int(len(data) * cut) if cut >= 0 else cut])
    snaps, skipped = load_snapshots(tmp_path)
    assert snaps == [] and len(skipped) == 1 and "robot r: snapshot not loaded" in skipped[0]


def test_a_chunk_cut_short_costs_the_keyframes_not_the_map(tmp_path, kept_robot):
    robot = kept_robot(range(5))
    save_snapshot(tmp_path, robot.snapshot(), 2)
    chunk = next((tmp_path / "r.keyframes").iterdir())
    chunk.write_bytes(chunk.read_bytes()[:100])
    (snap,), skipped = load_snapshots(tmp_path)
    assert snap.keyframes is None and snap.last_seq == 4
    assert len(skipped) == 1 and "keyframes not loaded" in skipped[0], skipped


def test_snapshots_keep_the_keyframes_so_a_restart_can_follow_the_next_redraw(
    tmp_path, insert, pose, redraw
):
    robot = RobotMap("r", lambda: OccupancyGrid(OccupancyParams()), keep_keyframes=True)
    robot.insert(insert(0))
    robot.insert(MapInsertMessage(
        "r", 4, 0.4, Pose2D(1.0, 0.0, 0.2), np.array([[3.0, 0.5]]), np.array([[0.0, 9.0]]),
        Pose2D(0.2, 0.0, 0.1),
    ))
    robot.apply(pose(4))
    robot.redraw(redraw([0, 4], [Pose2D(), Pose2D(1.0, 0.1, 0.2)], np.zeros((5, 3)), 4),
                 OccupancyParams())
    save_snapshot(tmp_path, robot.snapshot())
    (snap,), skipped = load_snapshots(tmp_path)
    assert skipped == [] and snap.redrawn_seq == 4
    resumed = RobotMap("r", lambda: OccupancyGrid(OccupancyParams()), snap, keep_keyframes=True)
    assert resumed.keyframes.seqs == [0, 4]
    loop_closure_off = RobotMap("r", lambda: OccupancyGrid(OccupancyParams()), snap)
    assert loop_closure_off.keyframes is None  # not kept (nor grown) while the setting is off
    for got, want in zip(resumed.keyframes.nodes, robot.keyframes.nodes, strict=True):
        assert (got.stamp_s, got.mount) == (want.stamp_s, want.mount)
        np.testing.assert_array_equal(got.points, want.points)
        np.testing.assert_array_equal(got.no_return, want.no_return)
    again = redraw([0, 4], [Pose2D(0.0, 0.2, 0.0), Pose2D(1.0, 0.3, 0.2)], np.zeros((5, 3)), 4)
    robot.redraw(again, OccupancyParams())
    resumed.redraw(again, OccupancyParams())
    np.testing.assert_array_equal(resumed.map.grid.log_odds, robot.map.grid.log_odds)


def test_broken_keyframes_cost_the_keyframes_not_the_map_naming_why(tmp_path, insert, pose):
    robot = RobotMap("r", lambda: OccupancyGrid(OccupancyParams()), keep_keyframes=True)
    robot.insert(insert(0))
    robot.apply(pose(0))
    save_snapshot(tmp_path, robot.snapshot())
    path = next(tmp_path.iterdir())
    with np.load(path) as data:
        arrays = dict(data)
    arrays["keyframes_hit_counts"] = np.array([7])
    np.savez(path, **arrays)
    (snap,), skipped = load_snapshots(tmp_path)
    assert snap.keyframes is None and snap.last_seq == 0
    assert "hit_counts must be >= 0 and add up to the rows of hits" in skipped[0]


def assert_same_keyframes(got, want) -> None:
    assert got.seqs == want.seqs and got.poses == want.poses
    for a, b in zip(got.nodes, want.nodes, strict=True):
        assert (a.stamp_s, a.mount) == (b.stamp_s, b.mount)
        assert a.points.tobytes() == b.points.tobytes()
        assert a.no_return.tobytes() == b.no_return.tobytes()


def test_keyframe_scans_are_written_once_by_chunks_and_read_back(tmp_path, kept_robot):
    """11 keyframes, 4 to a file: two files, written by the first snapshot and left as they
    are by the next (a scan never changes); the snapshot holds the last three's scans."""
    robot = kept_robot(range(0, 22, 2))
    save_snapshot(tmp_path, robot.snapshot(), 4)
    chunks = sorted((tmp_path / "r.keyframes").iterdir())
    assert [p.name.split("-", 1)[1] for p in chunks] == ["4-000000.npz", "4-000001.npz"]
    written = [p.stat().st_mtime_ns for p in chunks]
    robot.keyframes.moved(np.array([[0.0, 0.1 * k, 0.0] for k in range(11)]))  # a redraw
    save_snapshot(tmp_path, robot.snapshot(), 4)
    assert [p.stat().st_mtime_ns for p in chunks] == written
    (snap,), skipped = load_snapshots(tmp_path)
    assert skipped == []
    assert_same_keyframes(snap.keyframes, robot.keyframes)
    with np.load(tmp_path / "r.snapshot.npz") as data:
        assert int(data["keyframes_stored"]) == 8 and data["keyframes_hit_counts"].size == 3


def test_a_new_run_writes_its_own_chunks_and_drops_the_old_ones(tmp_path, insert, kept_robot):
    robot = kept_robot(range(10, 16))
    save_snapshot(tmp_path, robot.snapshot(), 2)
    old = set((tmp_path / "r.keyframes").iterdir())
    assert len(old) == 3
    for seq in range(5):  # the stream started again: the seqs went back
        robot.insert(insert(seq))
    save_snapshot(tmp_path, robot.snapshot(), 2)
    new = set((tmp_path / "r.keyframes").iterdir())
    assert len(new) == 2 and not new & old
    (snap,), _ = load_snapshots(tmp_path)
    assert snap.keyframes.seqs == [0, 1, 2, 3, 4]
    assert_same_keyframes(snap.keyframes, robot.keyframes)


def test_a_lost_chunk_costs_the_keyframes_not_the_map(tmp_path, kept_robot):
    robot = kept_robot(range(5))
    save_snapshot(tmp_path, robot.snapshot(), 2)
    next((tmp_path / "r.keyframes").iterdir()).unlink()
    (snap,), skipped = load_snapshots(tmp_path)
    assert snap.keyframes is None and snap.last_seq == 4
    np.testing.assert_array_equal(snap.grid.log_odds, robot.map.grid.log_odds)
    assert len(skipped) == 1 and "keyframes not loaded" in skipped[0], skipped
    assert "cannot follow this run's redraws" in skipped[0]


def test_another_file_size_writes_new_files_and_drops_the_old(tmp_path, kept_robot):
    """SCANFLOW_MAPSERVER_KEYFRAMES_PER_FILE changed between two restarts of the same run."""
    robot = kept_robot(range(9))
    save_snapshot(tmp_path, robot.snapshot(), 2)
    save_snapshot(tmp_path, robot.snapshot(), 3)
    names = sorted(p.name.split("-", 1)[1] for p in (tmp_path / "r.keyframes").iterdir())
    assert names == ["3-000000.npz", "3-000001.npz", "3-000002.npz"]
    (snap,), skipped = load_snapshots(tmp_path)
    assert skipped == []
    assert_same_keyframes(snap.keyframes, robot.keyframes)


def test_a_snapshot_written_before_chunks_still_loads(tmp_path, kept_robot):
    """Files from before the chunks hold every scan inline, and no `stored` or `run`."""
    robot = kept_robot(range(3))
    save_snapshot(tmp_path, robot.snapshot())
    path = tmp_path / "r.snapshot.npz"
    with np.load(path) as data:
        arrays = {k: data[k] for k in data.files if k not in ("keyframes_stored", "keyframes_run")}
    np.savez_compressed(path, **arrays)
    (snap,), skipped = load_snapshots(tmp_path)
    assert skipped == []
    assert_same_keyframes(snap.keyframes, robot.keyframes)


def test_a_snapshot_file_whose_name_is_no_robot_id_is_skipped(tmp_path, new_robot, insert, pose):
    """Written by something else (or before ids were checked): never served as a robot."""
    robot = new_robot()
    robot.insert(insert(0))
    robot.apply(pose(0))
    save_snapshot(tmp_path, robot.snapshot())
    (tmp_path / "r.snapshot.npz").rename(tmp_path / "*.snapshot.npz")
    snaps, skipped = load_snapshots(tmp_path)
    assert snaps == [] and "robot *" in skipped[0] and "invalid" in skipped[0]


def _meta_with(path, **changes) -> dict:
    with np.load(path) as data:
        meta = json.loads(str(data["meta"]))
    meta.update(changes)
    return {"meta": np.array(json.dumps(meta))}


@pytest.mark.parametrize("damage", [
    "newer_params", "box_not_a_list", "meta_not_a_map", "last_seq_not_one", "per_file_zero",
    "poses_not_numbers", "stamps_not_a_row",
])
def test_a_foreign_or_other_version_snapshot_is_skipped_and_named_the_others_load(
    tmp_path, damage, new_robot, insert, pose, kept_robot
):
    """A file of another scanflow version, or edited by hand, whose arrays read but do not fit:
    an escaping TypeError, AttributeError or ZeroDivisionError stopped the map server at start
    (a restart loop), and poses that were no numbers stopped it building the robot's map."""
    other = new_robot()
    other.insert(insert(0))
    other.apply(pose(0))
    save_snapshot(tmp_path / "ok", other.snapshot())
    robot = kept_robot(range(5))
    save_snapshot(tmp_path, robot.snapshot(), 2)
    path = tmp_path / "r.snapshot.npz"
    (tmp_path / "ok" / "r.snapshot.npz").rename(tmp_path / "ok.snapshot.npz")
    with np.load(path) as data:
        params = json.loads(str(data["meta"]))["params"]
    change = {
        "newer_params": lambda: _meta_with(path, params={**params, "p_unknown": 0.5}),
        "box_not_a_list": lambda: _meta_with(path, box=3),
        "meta_not_a_map": lambda: {"meta": np.array("[1, 2]")},
        "last_seq_not_one": lambda: {"last_seq": np.array([4, 5])},
        "per_file_zero": lambda: {"keyframes_per_file": np.int64(0)},
        "poses_not_numbers": lambda: {"poses": np.array([["a", "b", "c"]])},
        "stamps_not_a_row": lambda: {"stamps_s": np.zeros((1, 1))},
    }[damage]()
    with np.load(path) as data:
        arrays = {**{k: data[k] for k in data.files}, **change}
    np.savez_compressed(path, **arrays)
    snaps, skipped = load_snapshots(tmp_path)
    loaded = {s.robot_id: s for s in snaps}
    assert "ok" in loaded and len(skipped) == 1 and "robot r:" in skipped[0], skipped
    if damage == "per_file_zero":  # only the keyframes' files are unreadable
        assert loaded["r"].keyframes is None and "keyframes not loaded" in skipped[0]
    else:
        assert "r" not in loaded and "snapshot not loaded" in skipped[0]
    for snap in snaps:  # what loads, the map server can build a robot's map of
        RobotMap(snap.robot_id, lambda: OccupancyGrid(OccupancyParams()), snap, True)


def test_a_skipped_snapshot_is_set_aside_not_overwritten_by_the_fresh_run(
    tmp_path, new_robot, insert, pose
):
    """A snapshot this version cannot read (a newer scanflow's, after a rollback) is the robot's
    whole map: the robot starts afresh, and its first snapshot used to replace the file."""
    robot = new_robot()
    robot.insert(insert(0))
    robot.apply(pose(0))
    save_snapshot(tmp_path, robot.snapshot())
    path = tmp_path / "r.snapshot.npz"
    with np.load(path) as data:
        arrays = {k: data[k] for k in data.files}
    np.savez_compressed(path, **{**arrays, **_meta_with(path, version=99)})
    unreadable = path.read_bytes()
    snaps, skipped = load_snapshots(tmp_path)
    assert snaps == [] and len(skipped) == 1 and "robot r: snapshot not loaded" in skipped[0]
    fresh = new_robot()
    fresh.insert(insert(0))
    fresh.apply(pose(0))
    save_snapshot(tmp_path, fresh.snapshot())
    kept = [p for p in tmp_path.iterdir() if p.read_bytes() == unreadable]
    assert len(kept) == 1 and kept[0].name in skipped[0], skipped  # named in the log
    (snap,), skipped = load_snapshots(tmp_path)  # the set-aside file is not read again
    assert snap.robot_id == "r" and skipped == []


def test_a_retired_robots_snapshot_and_keyframe_files_go_and_no_start_loads_it(
    tmp_path, kept_robot
):
    """The robot's snapshot, the one of the run it replaced and its keyframes' files go;
    another robot's files stay, and so does a snapshot set aside as unreadable (no start
    loads it; it may be all of a map a newer version can read)."""
    robot = kept_robot(range(5))
    save_snapshot(tmp_path, robot.snapshot(), 2)  # the snapshot and two files of keyframes
    other = RobotMap("r2", robot.new_grid, keep_keyframes=True)
    other.insert(MapInsertMessage("r2", 0, 0.0, Pose2D(), np.ones((2, 2)), np.zeros((0, 2))))
    other.last_seq = 0
    save_snapshot(tmp_path, other.snapshot(), 1)
    (tmp_path / "r.snapshot.npz.unreadable").write_bytes(b"a newer version's")
    (tmp_path / "r.snapshot.npz.previous").write_bytes(b"the run it replaced")
    assert remove_snapshot(tmp_path, "r") == 4
    assert sorted(p.name for p in tmp_path.iterdir()) == [
        "r.snapshot.npz.unreadable", "r2.keyframes", "r2.snapshot.npz"]
    assert [s.robot_id for s in load_snapshots(tmp_path)[0]] == ["r2"]
    assert remove_snapshot(tmp_path, "r") == 0  # nothing left: no error
    assert remove_snapshot(tmp_path / "none", "r") == 0
