"""CARMEN loader: real logs against independent counts, layouts, malformed lines, keyframes."""

from __future__ import annotations

import gzip
import itertools
import math
from pathlib import Path

import numpy as np
import pytest
from scanflow.geometry import IDENTITY, Pose2D
from scanflow.io.carmen import (
    MAX_MOUNT_OFFSET_M,
    CarmenFormatError,
    CarmenLaser,
    CarmenOdom,
    CarmenReader,
    detect_sentinel_m,
    load_keyframes,
    old_laser_layout,
    read_carmen,
)

REAL_LOGS = {
    "aces-corrected.log.gz": (440, 180),
    "intel-corrected.log.gz": (910, 180),
    "freiburg-079-corrected.log.gz": (4791, 360),
}


def _pose_tokens(p: Pose2D) -> str:
    return f"{p.x!r} {p.y!r} {p.theta!r}"


def flaser(
    ranges: list[float], pose: Pose2D, odom: Pose2D | None = None, stamp: float = 1.0
) -> str:
    body = " ".join(repr(float(r)) for r in ranges)
    odom = pose if odom is None else odom
    return (
        f"FLASER {len(ranges)} {body} {_pose_tokens(pose)} {_pose_tokens(odom)} "
        f"{stamp!r} host {stamp!r}"
    )


def odom_line(p: Pose2D, stamp: float = 1.0, tv: float = 0.0, rv: float = 0.0) -> str:
    return f"ODOM {_pose_tokens(p)} {tv!r} {rv!r} 0 {stamp!r} host {stamp!r}"


def write_log(tmp_path: Path, lines: list[str], name: str = "test.log") -> Path:
    path = tmp_path / name
    path.write_text("\n".join(lines) + "\n")
    return path


def independent_counts(path: Path) -> tuple[int, int, int]:
    """Laser records, ODOM records and "no return" readings (>= 50 m), counted from the text."""
    lasers = odoms = no_return = 0
    with gzip.open(path, "rt") as f:
        for line in f:
            if line.startswith("FLASER"):
                lasers += 1
                tokens = line.split()
                n = int(tokens[1])
                no_return += int(np.count_nonzero(np.array(tokens[2 : 2 + n], float) >= 50.0))
            elif line.startswith("ODOM"):
                odoms += 1
    return lasers, odoms, no_return


@pytest.mark.parametrize("name", sorted(REAL_LOGS))
def test_real_logs_match_independent_counts(real_log, name: str) -> None:
    path = real_log(name)
    expected_scans, beams = REAL_LOGS[name]
    lasers, odoms, no_return = independent_counts(path)
    assert lasers == expected_scans
    reader = CarmenReader(path)
    scans = odom_count = dropped = no_returns = 0
    for rec in reader:
        if isinstance(rec, CarmenLaser):
            scan = rec.scan
            assert scan.beam_count == beams
            assert rec.pose is not None and rec.odom_pose is not None
            assert scan.seq == scans
            dropped += scan.dropped_count
            no_returns += scan.no_return_count
            scans += 1
        else:
            odom_count += 1
    assert (scans, odom_count) == (lasers, odoms)
    assert dropped == no_returns == no_return  # the sentinel readings come out as no return
    assert reader.error_count == 0
    assert reader.skipped["NEFF"] == lasers


@pytest.mark.parametrize("name", sorted(REAL_LOGS))
def test_real_log_beam_angles(real_log, name: str) -> None:
    _, beams = REAL_LOGS[name]
    first = next(r for r in read_carmen(real_log(name)) if isinstance(r, CarmenLaser))
    step_deg = 180.0 / beams
    angles_deg = np.degrees(first.scan.angles_rad)
    assert angles_deg[0] == pytest.approx(-90.0)
    assert angles_deg[-1] == pytest.approx(90.0 - step_deg)
    np.testing.assert_allclose(np.diff(angles_deg), step_deg)
    assert first.scan.range_max_m == 50.0


@pytest.mark.parametrize(
    ("n", "step_deg", "last_deg"),
    [(180, 1.0, 89.0), (181, 1.0, 90.0), (360, 0.5, 89.5), (361, 0.5, 90.0)],
)
def test_old_laser_layout_from_count(n: int, step_deg: float, last_deg: float) -> None:
    angle_min, step = old_laser_layout(n)
    assert math.degrees(angle_min) == pytest.approx(-90.0)
    assert math.degrees(step) == pytest.approx(step_deg)
    assert math.degrees(angle_min + (n - 1) * step) == pytest.approx(last_deg)


def test_flaser_and_odom_fields(tmp_path: Path) -> None:
    pose, odom = Pose2D(1.0, 2.0, 0.5), Pose2D(1.1, 2.1, 0.4)
    ranges = [1.0] * 179 + [60.0]
    path = write_log(
        tmp_path,
        ["PARAM laser_max 50 host 0", "# a comment", flaser(ranges, pose, odom, stamp=12.5),
         "NEFF 3", odom_line(Pose2D(3.0, 4.0, 0.1), stamp=13.0, tv=0.4, rv=-0.2)],
    )  # fmt: skip
    reader = CarmenReader(path, robot_id="r7")
    laser, odo = list(reader)
    assert isinstance(laser, CarmenLaser) and isinstance(odo, CarmenOdom)
    assert laser.pose == pose and laser.odom_pose == odom
    assert laser.line_no == 3 and odo.line_no == 5
    assert laser.scan.stamp_s == 12.5 and laser.scan.robot_id == "r7"
    assert laser.scan.valid_count == 179  # 60 m is at/above the 50 m limit
    assert odo.odom.pose == Pose2D(3.0, 4.0, 0.1)
    assert odo.odom.velocity == (0.4, 0.0, -0.2)
    assert odo.odom.stamp_s == 13.0 and odo.odom.robot_id == "r7"
    assert dict(reader.skipped) == {"PARAM": 1, "#": 1, "NEFF": 1}


def test_single_timestamp_variant(tmp_path: Path) -> None:
    line = flaser([1.0] * 180, Pose2D()).rsplit(" ", 3)[0] + " 7.25"
    laser, odo = list(read_carmen(write_log(tmp_path, [line, "ODOM 0 0 0 0 0 0 8.5"])))
    assert laser.scan.stamp_s == 7.25
    assert odo.odom.stamp_s == 8.5


def test_gzip_detected_by_magic_bytes(tmp_path: Path) -> None:
    lines = [flaser([1.0, 2.0] * 90, Pose2D(1, 2, 3)), odom_line(Pose2D(1, 1, 1))]
    plain = write_log(tmp_path, lines)
    packed = tmp_path / "packed.log"  # no .gz suffix: detection must use the content
    packed.write_bytes(gzip.compress(plain.read_bytes()))
    a, b = list(read_carmen(plain)), list(read_carmen(packed))
    assert len(a) == len(b) == 2
    np.testing.assert_array_equal(a[0].scan.ranges_m, b[0].scan.ranges_m)
    assert a[1].odom.pose == b[1].odom.pose


def _damaged_gzip(tmp_path: Path, how: str) -> tuple[Path, int]:
    """A gzip log of 400 records cut short ("truncated") or with bytes flipped midway
    ("corrupt"), and how many lines come before the damage at least."""
    lines = [flaser([1.0 + i % 7, 2.0] * 90, Pose2D(i, 0, 0), stamp=float(i)) for i in range(400)]
    packed = gzip.compress(("\n".join(lines) + "\n").encode())
    cut = len(packed) // 2
    data = packed[:cut] if how == "truncated" else (
        packed[:cut] + bytes(b ^ 0xFF for b in packed[cut:cut + 64]) + packed[cut + 64:])
    path = tmp_path / f"{how}.log.gz"
    path.write_bytes(data)
    return path, 50


@pytest.mark.parametrize("how", ["truncated", "corrupt"])
def test_a_damaged_gzip_gives_its_good_part_and_names_where_it_breaks(tmp_path, how) -> None:
    path, at_least = _damaged_gzip(tmp_path, how)
    reader = CarmenReader(path)
    records = list(reader)
    assert at_least <= len(records) < 400
    assert [r.scan.stamp_s for r in records] == [float(i) for i in range(len(records))]
    error = reader.errors[-1]  # after any garbled lines the corrupt stream gave first
    assert "cannot be read past here" in error.reason and error.line_no > len(records)
    with pytest.raises(CarmenFormatError, match=rf"{how}\.log\.gz:\d+: "):  # its first error
        list(read_carmen(path, strict=True))
    assert len(load_keyframes(path)) == len(records)


MALFORMED = {
    "too few ranges": "FLASER 180 1 2 3",
    "bad range": flaser([1.0] * 180, Pose2D()).replace(" 1.0 ", " abc ", 1),
    "bad count": "FLASER x 1 2",
    "negative count": "FLASER -3 1 2 3 0 0 0 0 0 0 1 h 1",
    "nan pose": flaser([1.0] * 180, Pose2D()).replace("0.0 0.0 0.0", "nan 0.0 0.0", 1),
    "extra tokens": flaser([1.0] * 180, Pose2D()) + " 5 6",
    "short odom": "ODOM 1 2 3",
    "bad odom": "ODOM 1 2 x 0 0 0 1 h 1",
    "truncated robotlaser": "ROBOTLASER1 0 -1.57 3.14 0.0175 50 0.01 0 3 1 1",
}


def test_malformed_lines_are_skipped_and_reported(tmp_path: Path) -> None:
    good = flaser([1.0] * 180, Pose2D())
    lines = [good, *MALFORMED.values(), good]
    seen: list[tuple[str, int, str]] = []
    reader = CarmenReader(
        write_log(tmp_path, lines), on_error=lambda p, n, r: seen.append((p, n, r))
    )
    records = list(reader)
    assert [r.line_no for r in records] == [1, len(lines)]
    bad_lines = list(range(2, len(lines)))
    assert [e.line_no for e in reader.errors] == bad_lines
    assert [n for _, n, _ in seen] == bad_lines
    assert reader.error_count == len(MALFORMED)
    assert all(e.path.endswith("test.log") for e in reader.errors)
    assert "abc" in reader.errors[1].reason


@pytest.mark.parametrize("label", sorted(MALFORMED))
def test_strict_mode_names_file_and_line(tmp_path: Path, label: str) -> None:
    path = write_log(tmp_path, [flaser([1.0] * 180, Pose2D()), MALFORMED[label]])
    with pytest.raises(CarmenFormatError, match=r"test\.log:2: "):
        list(read_carmen(path, strict=True))


def robotlaser(ranges: list[float], remissions: list[float], stamp: float = 3.0) -> str:
    r = " ".join(map(repr, ranges))
    m = " ".join(map(repr, remissions))
    return (
        f"ROBOTLASER1 0 -2.0 4.0 0.01 30.0 0.01 0 {len(ranges)} {r} {len(remissions)} {m}"
        f" 1.0 2.0 0.3 0.9 2.0 0.3 0.5 0.1 0.2 0.3 0.0 {stamp!r} host {stamp!r}"
    )


def test_robotlaser1_explicit_layout_pose_and_remissions(tmp_path: Path) -> None:
    ranges = [1.0, 2.0, 35.0, 3.0]
    (rec,) = list(read_carmen(write_log(tmp_path, [robotlaser(ranges, [5.0, 6.0, 7.0, 8.0])])))
    scan = rec.scan
    assert rec.record_type == "ROBOTLASER1"
    assert scan.angle_min_rad == -2.0 and scan.angle_increment_rad == 0.01
    assert scan.range_max_m == 30.0  # the record's own maximum range is below 50 m
    np.testing.assert_array_equal(scan.valid_mask, [True, True, False, True])
    np.testing.assert_array_equal(scan.intensities, [5.0, 6.0, 7.0, 8.0])
    assert rec.pose == Pose2D(1.0, 2.0, 0.3)
    assert rec.odom_pose == Pose2D(0.9, 2.0, 0.3)
    assert scan.stamp_s == 3.0


def test_rawlaser1_has_no_pose(tmp_path: Path) -> None:
    line = "RAWLASER1 0 -1.5 3.0 0.5 20.0 0.01 0 3 1.5 2.5 25.0 0 4.0 host 4.5"
    (rec,) = list(read_carmen(write_log(tmp_path, [line])))
    assert rec.pose is None and rec.odom_pose is None
    assert rec.scan.intensities is None
    assert rec.scan.stamp_s == 4.5
    np.testing.assert_allclose(rec.scan.angles_rad, [-1.5, -1.0, -0.5])
    assert rec.scan.valid_count == 2


def test_remission_count_mismatch_is_an_error(tmp_path: Path) -> None:
    path = write_log(tmp_path, [robotlaser([1.0, 2.0, 3.0], [1.0, 2.0])])
    with pytest.raises(CarmenFormatError, match="num_remissions"):
        list(read_carmen(path, strict=True))


def _sentinel_log(tmp_path: Path, sentinel: float | None) -> Path:
    rng = np.random.default_rng(3)
    lines = []
    for i in range(40):
        ranges = rng.uniform(0.5, 20.0, 180)
        if sentinel is not None:
            ranges[rng.choice(180, 12, replace=False)] = sentinel
        lines.append(flaser(list(np.round(ranges, 2)), Pose2D(i * 0.1, 0, 0), stamp=float(i)))
    return write_log(tmp_path, lines)


def test_sentinel_below_default_limit_is_detected_and_masked(tmp_path: Path) -> None:
    path = _sentinel_log(tmp_path, 32.77)
    assert detect_sentinel_m(path) == pytest.approx(32.77)
    scans = [r.scan for r in read_carmen(path)]
    assert all(s.range_max_m == pytest.approx(32.77) for s in scans)
    assert sum(s.dropped_count for s in scans) == 40 * 12


def test_no_sentinel_in_spread_readings(tmp_path: Path) -> None:
    path = _sentinel_log(tmp_path, None)
    assert detect_sentinel_m(path) is None
    assert all(r.scan.range_max_m == 50.0 for r in read_carmen(path))


def test_explicit_max_range_overrides_the_rule(tmp_path: Path) -> None:
    path = _sentinel_log(tmp_path, 32.77)
    assert all(r.scan.range_max_m == 10.0 for r in read_carmen(path, max_range_m=10.0))
    with pytest.raises(ValueError, match="max_range_m"):
        CarmenReader(path, max_range_m=0.0)


def _random_pose(rng: np.random.Generator, step: float) -> Pose2D:
    return Pose2D(*rng.uniform(-step, step, 2), rng.uniform(-0.5, 0.5))


MOUNT = Pose2D(0.3, -0.1, 0.2)


def test_keyframe_odometry_chains_the_raw_increments(tmp_path: Path) -> None:
    """A log written the way corrected logs are: the ODOM stream re-anchored at every record."""
    rng = np.random.default_rng(11)
    true = [Pose2D(5.0, -2.0, 1.0)]
    raw = [Pose2D(0.3, 0.1, -0.2)]  # the wheel odometry, in its own frame
    for _ in range(7):
        true.append(true[-1] * _random_pose(rng, 0.5))
        raw.append(raw[-1] * _random_pose(rng, 0.5))
    lines: list[str] = []
    for i, corrected in enumerate(true):
        lines.append(flaser([2.0] * 180, corrected, stamp=float(i)))
        if i + 1 == len(true):
            break
        lines.append(odom_line(corrected, stamp=0.0))  # the anchor
        mid = raw[i].interpolate(raw[i + 1], 0.5)
        for sample in (mid, raw[i + 1]):
            lines.append(odom_line(corrected * sample.relative_to(raw[i]), stamp=i + 0.5))
    frames = load_keyframes(write_log(tmp_path, lines))
    assert [f.true_pose for f in frames] == true
    assert {f.scan.mount for f in frames} == {IDENTITY}
    for a, b, ra, rb in zip(frames, frames[1:], raw, raw[1:], strict=False):
        got = b.odom_pose.relative_to(a.odom_pose).to_array()
        np.testing.assert_allclose(got, rb.relative_to(ra).to_array(), atol=1e-9)
    assert frames[0].odom_pose == true[0]


def test_keyframes_skip_malformed_lines_and_tell_on_error(tmp_path: Path) -> None:
    good = flaser([1.0] * 180, Pose2D())
    seen: list[tuple[str, int, str]] = []
    path = write_log(tmp_path, [good, MALFORMED["truncated robotlaser"], good])
    frames = load_keyframes(path, on_error=lambda p, n, r: seen.append((p, n, r)))
    assert len(frames) == 2
    assert [(p, n) for p, n, _ in seen] == [(str(path), 2)]


def test_keyframe_without_odom_uses_stored_odom_difference(tmp_path: Path) -> None:
    o0, o1 = Pose2D(1, 1, 0.2), Pose2D(1.5, 1.2, 0.4)
    path = write_log(
        tmp_path,
        [flaser([2.0] * 180, Pose2D(), o0), "NEFF 1", flaser([2.0] * 180, Pose2D(1, 0, 0), o1)],
    )
    a, b = load_keyframes(path)
    np.testing.assert_allclose(
        b.odom_pose.relative_to(a.odom_pose).to_array(), o1.relative_to(o0).to_array(), atol=1e-12
    )


def test_keyframes_of_a_real_log_follow_the_ground_truth(real_log) -> None:
    frames = load_keyframes(real_log("aces-corrected.log.gz"))
    assert len(frames) == 440
    errors = [
        b.true_pose.relative_to(a.true_pose).relative_to(b.odom_pose.relative_to(a.odom_pose))
        for a, b in itertools.pairwise(frames)
    ]
    # Odometry drifts, but step by step it agrees with the corrected poses to decimetres.
    assert np.median([e.translation_norm() for e in errors]) < 0.15
    assert np.median([abs(e.theta) for e in errors]) < 0.1


# Sensor mounts: per record for ROBOTLASER1; FLASER / RLASER carry none (PARAM not applied).


def robotlaser_at(laser: Pose2D, robot: Pose2D, stamp: float = 3.0) -> str:
    return (
        f"ROBOTLASER1 0 -1.5 3.0 0.5 30.0 0.01 0 3 1.0 2.0 3.0 0 {_pose_tokens(laser)} "
        f"{_pose_tokens(robot)} 0.5 0.1 0.2 0.3 0.0 {stamp!r} host {stamp!r}"
    )


def test_robotlaser1_mount_is_the_laser_pose_relative_to_the_robot(tmp_path: Path) -> None:
    robot = Pose2D(3.0, -1.0, 2.0)
    laser = robot * MOUNT
    (rec,) = list(read_carmen(write_log(tmp_path, [robotlaser_at(laser, robot)])))
    np.testing.assert_allclose(rec.scan.mount.to_array(), MOUNT.to_array(), atol=1e-12)
    assert rec.pose == laser and rec.odom_pose == robot  # stored poses unchanged
    (frame,) = load_keyframes(write_log(tmp_path, [robotlaser_at(laser, robot)]))
    np.testing.assert_allclose(frame.true_pose.to_array(), robot.to_array(), atol=1e-12)


def test_robotlaser1_mount_beyond_the_limit_is_malformed(tmp_path: Path) -> None:
    robot = Pose2D(1.0, 1.0, 0.5)
    far = robotlaser_at(robot * Pose2D(MAX_MOUNT_OFFSET_M + 0.5, 0.0, 0.0), robot)
    reader = CarmenReader(write_log(tmp_path, [far, robotlaser_at(robot, robot)]))
    (rec,) = list(reader)
    assert rec.line_no == 2 and rec.scan.mount.translation_norm() < 1e-12
    assert [e.line_no for e in reader.errors] == [1] and "laser_pose" in reader.errors[0].reason
    with pytest.raises(CarmenFormatError, match=r"test\.log:1: .*laser_pose"):
        list(read_carmen(write_log(tmp_path, [far]), strict=True))


def test_flaser_and_rlaser_ignore_the_param_offsets(tmp_path: Path) -> None:
    """PARAM laser offsets are not applied (module docstring): the mount stays identity."""
    scan = flaser([1.0] * 180, Pose2D())
    lines = [
        "PARAM robot_frontlaser_offset 0.3 nohost 0",
        "PARAM robot_rearlaser_angular_offset 3.14159 nohost 0",
        scan,
        scan.replace("FLASER", "RLASER", 1),
    ]
    reader = CarmenReader(write_log(tmp_path, lines))
    assert [r.scan.mount for r in reader] == [IDENTITY, IDENTITY]
    assert reader.error_count == 0 and reader.skipped["PARAM"] == 2


@pytest.mark.parametrize(
    "name", ["aces-corrected.log.gz", "intel-corrected.log.gz", "freiburg-079-corrected.log.gz"]
)
def test_real_logs_are_at_the_origin_and_keyframes_keep_the_stored_poses(real_log, name) -> None:
    """FLASER logs carry no mount (freiburg-079's PARAM offset is not applied): the keyframes
    are the stored poses, bit for bit."""
    path = real_log(name)
    stored = [r.pose for r in read_carmen(path) if isinstance(r, CarmenLaser)]
    frames = load_keyframes(path)
    assert {f.scan.mount for f in frames} == {IDENTITY}
    assert [f.true_pose for f in frames] == stored
    assert frames[0].odom_pose == stored[0]
