"""`scanflow run`: the simulator through the in-process pipeline, summary and written files."""

from __future__ import annotations

import json
from pathlib import Path

from scanflow.cli import _register, app
from scanflow.frontend import load_tum
from scanflow.maps.export import load_map
from typer.testing import CliRunner

from .conftest import assert_usage_error


def test_run_simulator_writes_map_and_trajectory(tmp_path: Path) -> None:
    _register()
    result = CliRunner().invoke(
        app, ["run", "--duration", "2", "--json", "--map-out", str(tmp_path)]
    )
    assert result.exit_code == 0, result.output
    summary = json.loads(result.output)
    assert summary["scans"] == 20 and summary["deskew_sources"] == {"odometry": 20}
    assert summary["statuses"]["initialised"] == 1
    assert summary["rechecked"] == 0  # the simulator's matches never score low (BENCHMARKS.md)
    stamps, poses = load_tum(tmp_path / "trajectory.tum")
    assert len(stamps) == 20 and poses.shape == (20, 3)
    assert not load_map(tmp_path / "map.npz").is_empty
    assert {p.name for p in tmp_path.iterdir()} >= {"map.png", "map.yaml", "map.pgm"}


def test_run_rejects_a_missing_log(tmp_path: Path) -> None:
    _register()
    result = CliRunner().invoke(app, ["run", "--log", str(tmp_path / "nope.log")])
    assert result.exit_code == 2 and "no log at" in result.output


def test_run_localises_on_a_prior_map_without_changing_it(tmp_path: Path, monkeypatch) -> None:
    _register()
    args = ["run", "--duration", "3", "--json"]
    first = CliRunner().invoke(app, [*args, "--map-out", str(tmp_path)])
    assert first.exit_code == 0, first.output
    monkeypatch.setenv("SCANFLOW_FRONTEND_UPDATE_MAP", "false")
    again = CliRunner().invoke(app, [*args, "--prior-map", str(tmp_path / "map.npz")])
    assert again.exit_code == 0, again.output
    mapped, localised = json.loads(first.output), json.loads(again.output)
    assert localised["statuses"].get("localised") == 1
    assert "initialised" not in localised["statuses"]
    assert localised["inserted"] == 0 and localised["prior_map"].endswith("map.npz")
    # The same run, now placed on its own earlier map: it ends where it ended then.
    gap = [a - b for a, b in zip(localised["final_pose"], mapped["final_pose"], strict=True)]
    assert abs(gap[0]) < 0.1 and abs(gap[1]) < 0.1 and abs(gap[2]) < 0.02


def test_run_names_a_missing_prior_map(tmp_path: Path) -> None:
    _register()
    result = CliRunner().invoke(app, ["run", "--prior-map", str(tmp_path / "none.npz")])
    assert result.exit_code == 2 and "no file at" in result.output


def test_run_localising_only_without_a_prior_map_is_a_usage_error(monkeypatch) -> None:
    """SCANFLOW_FRONTEND_UPDATE_MAP=false and no map: named at start (before, a traceback)."""
    monkeypatch.setenv("SCANFLOW_FRONTEND_UPDATE_MAP", "false")
    assert_usage_error(["run", "--duration", "0.5", "--json"], "update_map=false")


def test_run_with_loop_closure_writes_the_optimised_map_and_trajectory(tmp_path: Path) -> None:
    """Two laps of the simulator's tour: closures are found and reported, and every scan's
    optimised pose is written."""
    _register()
    result = CliRunner().invoke(
        app, ["run", "--duration", "60", "--loop-closure", "--json", "--map-out", str(tmp_path)]
    )
    assert result.exit_code == 0, result.output
    summary = json.loads(result.output)
    assert summary["loop_closure"]["closures"] > 0
    assert summary["loop_closure"]["keyframes"] == summary["inserted"]
    assert summary["loop_closure"]["culled"] == 0
    stamps, poses = load_tum(tmp_path / "trajectory.tum")
    assert len(stamps) == summary["scans"] == 600
    assert summary["final_pose"] == [round(float(v), 4) for v in poses[-1]]
    assert not load_map(tmp_path / "map.npz").is_empty
    plain = CliRunner().invoke(app, ["run", "--duration", "2", "--json"])
    assert "loop_closure" not in json.loads(plain.output)
    # The human summary's loop-closure line is there whenever loop closure is on: 2 s do.
    human = CliRunner().invoke(app, ["run", "--duration", "2", "--loop-closure"])
    assert human.exit_code == 0 and "loop closure: " in human.output


def test_run_with_culling_reports_the_inserts_hung_from_keyframes() -> None:
    """SCANFLOW_BACKEND_CULL_M reaches `scanflow run`: fewer keyframes than inserts, the rest
    counted as culled, and the loops still close."""
    _register()
    result = CliRunner().invoke(
        app, ["run", "--duration", "60", "--loop-closure", "--json"],
        env={"SCANFLOW_BACKEND_CULL_M": "0.3"},
    )
    assert result.exit_code == 0, result.output
    summary = json.loads(result.output)["loop_closure"]
    assert summary["culled"] > 0 and summary["closures"] > 0
    assert summary["keyframes"] + summary["culled"] == json.loads(result.output)["inserted"]


def test_run_closes_loops_on_a_prior_map_and_keeps_it(tmp_path: Path) -> None:
    """The same run again on its own earlier map, with loop closure: it extends the map with
    its keyframes, drawn on the prior map, which the written map still holds."""
    _register()
    first = CliRunner().invoke(
        app, ["run", "--duration", "3", "--json", "--map-out", str(tmp_path / "first")]
    )
    assert first.exit_code == 0, first.output
    prior = tmp_path / "first" / "map.npz"
    both = CliRunner().invoke(app, [
        "run", "--duration", "3", "--json", "--loop-closure", "--prior-map", str(prior),
        "--map-out", str(tmp_path / "again"),
    ])
    assert both.exit_code == 0, both.output
    summary = json.loads(both.output)
    assert summary["prior_map"] == str(prior) and summary["statuses"].get("localised") == 1
    assert summary["loop_closure"]["keyframes"] == summary["inserted"] > 0
    before, after = load_map(prior), load_map(tmp_path / "again" / "map.npz")
    assert after.extent.union(before.extent) == after.extent  # drawn on the prior map
    mapped = json.loads(first.output)
    gap = [a - b for a, b in zip(summary["final_pose"], mapped["final_pose"], strict=True)]
    assert abs(gap[0]) < 0.1 and abs(gap[1]) < 0.1 and abs(gap[2]) < 0.02


def test_run_refuses_a_bad_seed_or_duration_without_a_traceback() -> None:
    for option, value in (("--seed", "-1"), ("--duration", "inf")):
        assert_usage_error(["run", option, value, "--json"], value)


def test_run_refuses_an_unreadable_log_or_a_file_as_map_out_without_a_traceback(
    tmp_path: Path,
) -> None:
    """A directory that is no ROS 2 bag, a ROS 1 bag that cannot be opened, and a --map-out
    that is a file: each a message naming it and exit 2 (before, a traceback and exit 1)."""
    _register()
    (tmp_path / "bag.bag").write_bytes(b"#ROSBAG V2.0\njunk")
    (tmp_path / "taken").write_text("")
    for args, named in (
        (["--log", str(tmp_path)], "not a ROS 2 bag"),
        (["--log", str(tmp_path / "bag.bag")], "cannot open bag"),
        (["--duration", "0.5", "--map-out", str(tmp_path / "taken")], "not a directory"),
    ):
        result = CliRunner().invoke(app, ["run", *args, "--json"], env={"COLUMNS": "400"})
        assert result.exit_code == 2, result.output
        assert isinstance(result.exception, SystemExit)
        assert named in result.output


def test_run_refuses_a_map_out_it_cannot_make_before_the_run(tmp_path: Path) -> None:
    """A --map-out under a file: a usage error naming it at start (before, a traceback after
    the whole run, its map and trajectory lost)."""
    (tmp_path / "taken").write_text("")
    assert_usage_error(
        ["run", "--duration", "0.5", "--json", "--map-out", str(tmp_path / "taken" / "out")],
        "cannot make",
    )


def circle_log(path: Path, scans: int, bad_after: tuple[int, ...]) -> Path:
    """A CARMEN log of `scans` FLASER records (3 m all round, the robot still) with a
    malformed line after each scan index in `bad_after`."""
    ranges = " ".join(["3.0"] * 180)
    lines = []
    for i in range(scans):
        stamp = 10.0 + 0.2 * i
        lines.append(f"FLASER 180 {ranges} 0 0 0 0 0 0 {stamp} host {stamp}")
        if i in bad_after:
            lines.append("FLASER 180 1.0 oops")
    path.write_text("\n".join(lines) + "\n")
    return path


def test_run_counts_and_shows_the_unreadable_records_it_skipped(tmp_path: Path) -> None:
    """Skipped lines are no longer silent: counted in the summary, the first shown by number."""
    _register()
    log = circle_log(tmp_path / "run.log", 6, bad_after=(1, 3))
    result = CliRunner().invoke(app, ["run", "--log", str(log), "--json"])
    assert result.exit_code == 0, result.output
    summary = json.loads(result.stdout)
    assert summary["scans"] == 6 and summary["skipped_records"] == 2
    assert "log_error" not in summary
    text = CliRunner().invoke(app, ["run", "--log", str(log)])
    assert text.exit_code == 0, text.output
    assert "warning: 2 unreadable records of the log skipped" in text.stderr
    assert f"{log}:3: " in text.stderr and f"{log}:6: " in text.stderr


def test_run_keeps_what_it_read_of_a_bag_that_breaks_off(tmp_path: Path, monkeypatch) -> None:
    """A bag damaged past some point: the scans before it are tracked, summarised and
    written, the break is named, and the exit status is 1 (not a usage error's 2 with the
    run thrown away)."""
    import scanflow.cli.run as run_module
    from scanflow.io.rosbag import BagFormatError, BagScan
    from scanflow.sim import SimConfig, simulate

    frames = list(simulate(SimConfig(duration_s=1.0, seed=0)))

    def broken_bag(path: Path, **_options: object):
        for frame in frames[:6]:
            yield BagScan(frame.scan, "/scan", frame.scan.stamp_s)
        raise BagFormatError(f"{path}: the bag cannot be read after 10.5 s: ReaderError: cut")

    bag = tmp_path / "cut.bag"
    bag.write_bytes(b"#ROSBAG V2.0\n")
    monkeypatch.setattr(run_module, "BagReader", broken_bag)
    _register()
    out = tmp_path / "out"
    result = CliRunner().invoke(app, ["run", "--log", str(bag), "--json", "--map-out", str(out)])
    assert result.exit_code == 1, result.output
    summary = json.loads(result.stdout)
    assert summary["scans"] == 6 and "cannot be read after 10.5 s" in summary["log_error"]
    assert len(load_tum(out / "trajectory.tum")[0]) == 6
    assert "error: the log broke off" in result.stderr


def test_run_of_a_log_with_no_scan_is_an_error_naming_it(tmp_path: Path) -> None:
    """A file that holds no scan (here only lines CARMEN does not know): exit 1 naming it,
    not an empty summary and exit 0; its trajectory (empty) is still written."""
    _register()
    log = tmp_path / "notes.log"
    log.write_text("hello\nworld\n")
    out = tmp_path / "out"
    result = CliRunner().invoke(app, ["run", "--log", str(log), "--json", "--map-out", str(out)])
    assert result.exit_code == 1, result.output
    assert json.loads(result.stdout)["scans"] == 0
    assert f"error: no scans in {log}" in result.stderr
    assert [p.name for p in out.iterdir()] == ["trajectory.tum"]


def test_run_that_inserts_nothing_writes_its_trajectory_and_no_map(tmp_path: Path) -> None:
    """Scans that are all rejected (no valid beam): no map to draw, said so, the trajectory
    written (before, a traceback from drawing the empty map)."""
    _register()
    log = circle_log(tmp_path / "blind.log", 4, bad_after=())
    log.write_text(log.read_text().replace(" 3.0", " 0.0"))
    out = tmp_path / "out"
    result = CliRunner().invoke(app, ["run", "--log", str(log), "--map-out", str(out)])
    assert result.exit_code == 0, result.output
    assert "no map written" in result.stderr
    assert [p.name for p in out.iterdir()] == ["trajectory.tum"]
    assert len(load_tum(out / "trajectory.tum")[0]) == 4
