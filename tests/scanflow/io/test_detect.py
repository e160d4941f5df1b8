"""Log format detection from content, the reader each format opens, and record payloads."""

from __future__ import annotations

import gzip
from pathlib import Path

import numpy as np
import pytest
from scanflow.geometry import Pose2D
from scanflow.io.carmen import CarmenLaser, CarmenOdom, CarmenReader
from scanflow.io.detect import ROSBAG1_MAGIC, detect_format, open_log, record_payload
from scanflow.io.rosbag import BagFormatError, BagOdom, BagReader, BagScan
from scanflow.scan import LaserScan, Odometry

CARMEN_LINES = (
    "FLASER 3 1.0 2.0 3.0 0.5 0.25 0.1 0.5 0.25 0.1 10.0 host 10.0\n"
    "ODOM 0.5 0.25 0.1 0 0 0 10.05 host 10.05\n"
)


def test_detect_errors(tmp_path: Path) -> None:
    with pytest.raises(FileNotFoundError, match="missing"):
        detect_format(tmp_path / "missing")
    with pytest.raises(ValueError, match=r"metadata\.yaml"):
        detect_format(tmp_path)
    text = tmp_path / "x.log"
    text.write_text("ODOM 0 0 0 0 0 0 1 h 1\n")
    assert detect_format(text) == "carmen"


@pytest.mark.parametrize(
    ("head", "expected"),
    [
        pytest.param(b"#ROSBAG V2.0\n", "rosbag1", id="magic-line"),
        pytest.param(b"#ROSBAG V2.0" + bytes(range(256)), "rosbag1", id="magic-then-binary"),
        pytest.param(b"#ROSBAG V2.0", "rosbag1", id="magic-alone"),
        pytest.param(b"#ROSBAG V2", "carmen", id="magic-prefix-only"),
        pytest.param(b"#ROSBAG V1.2\n", "carmen", id="other-version"),
        pytest.param(b" #ROSBAG V2.0\n", "carmen", id="magic-not-first"),
        pytest.param(b"#rosbag v2.0\n", "carmen", id="lower-case"),
        pytest.param(b"", "carmen", id="empty"),
        pytest.param(gzip.compress(b"#ROSBAG V2.0\n", mtime=0), "carmen", id="gzipped-magic"),
    ],
)
def test_a_file_is_a_ros1_bag_exactly_when_it_opens_with_the_magic(
    tmp_path: Path, head: bytes, expected: str
) -> None:
    path = tmp_path / "some.log"
    path.write_bytes(head)
    assert detect_format(path) == expected
    assert detect_format(str(path)) == expected  # str paths too


def test_the_file_name_does_not_decide_the_format(tmp_path: Path) -> None:
    bag_named = tmp_path / "run.bag"
    bag_named.write_text(CARMEN_LINES)
    assert detect_format(bag_named) == "carmen"
    log_named = tmp_path / "run.log"
    log_named.write_bytes(ROSBAG1_MAGIC + b"\n")
    assert detect_format(log_named) == "rosbag1"


def test_a_directory_is_a_ros2_bag_only_with_a_metadata_file(tmp_path: Path) -> None:
    bag = tmp_path / "bag"
    bag.mkdir()
    (bag / "bag_0.mcap").write_bytes(b"")
    with pytest.raises(ValueError, match=r"bag .*metadata\.yaml"):
        detect_format(bag)
    (bag / "metadata.yaml").mkdir()  # a directory of that name is not the file
    with pytest.raises(ValueError, match=r"metadata\.yaml"):
        detect_format(bag)
    other = tmp_path / "other"
    other.mkdir()
    (other / "metadata.yaml").write_text("rosbag2_bagfile_information: {}\n")
    assert detect_format(other) == "rosbag2"
    assert detect_format(str(other)) == "rosbag2"


@pytest.mark.parametrize("packed", [False, True])
def test_open_log_reads_a_carmen_log_with_the_given_robot_id(tmp_path: Path, packed: bool) -> None:
    path = tmp_path / "run.log"
    data = CARMEN_LINES.encode()
    path.write_bytes(gzip.compress(data) if packed else data)
    reader = open_log(path, robot_id="r9", strict=True)
    assert isinstance(reader, CarmenReader) and reader.strict
    laser, odom = (record_payload(r) for r in reader)
    assert isinstance(laser, LaserScan) and isinstance(odom, Odometry)
    np.testing.assert_allclose(laser.ranges_m, [1.0, 2.0, 3.0])
    assert laser.robot_id == odom.robot_id == "r9"
    assert odom.pose == Pose2D(0.5, 0.25, 0.1) and odom.stamp_s == 10.05
    default = open_log(path)
    assert isinstance(default, CarmenReader)
    assert default.robot_id == "robot" and not default.strict


def test_open_log_tells_on_error_of_each_skipped_carmen_line_with_its_number(
    tmp_path: Path,
) -> None:
    path = tmp_path / "run.log"
    path.write_text("FLASER 3 1.0 oops\n" + CARMEN_LINES + "ODOM 1 2\n")
    heard: list[str] = []
    reader = open_log(path, on_error=heard.append)
    assert len(list(reader)) == 2 and reader.error_count == 2
    assert [m.split(": ", 1)[0] for m in heard] == [f"{path}:1", f"{path}:4"]
    assert heard == [f"{e.path}:{e.line_no}: {e.reason}" for e in reader.errors]


def test_open_log_gives_bags_a_bag_reader_with_the_options(tmp_path: Path) -> None:
    ros1 = tmp_path / "broken.bag"
    ros1.write_bytes(ROSBAG1_MAGIC + b"\n" + b"\x00" * 32)
    ros2 = tmp_path / "bag2"
    ros2.mkdir()
    (ros2 / "metadata.yaml").write_text("not: a bag\n")
    for path in (ros1, ros2):
        reader = open_log(path, robot_id="r3", strict=True)
        assert isinstance(reader, BagReader)
        assert (reader.path, reader.robot_id, reader.strict) == (path, "r3", True)
        default = open_log(str(path))
        assert isinstance(default, BagReader)
        assert default.robot_id is None and not default.strict  # robots named from the topics
    with pytest.raises(BagFormatError, match=r"broken\.bag"):
        list(open_log(ros1))


def test_open_log_refuses_what_detect_format_refuses(tmp_path: Path) -> None:
    with pytest.raises(FileNotFoundError):
        open_log(tmp_path / "missing.log")
    with pytest.raises(ValueError, match=r"metadata\.yaml"):
        open_log(tmp_path)


def test_record_payload_is_the_scan_or_the_odometry_of_any_record() -> None:
    scan = LaserScan(ranges_m=np.ones(4), angle_min_rad=0.0, angle_increment_rad=0.1)
    odom = Odometry(stamp_s=1.0, pose=Pose2D(1.0, 2.0, 0.3))
    records = [
        (CarmenLaser(scan, None, None, line_no=3), scan),
        (CarmenOdom(odom, line_no=4), odom),
        (BagScan(scan, "/scan", 1.0), scan),
        (BagOdom(odom, "/odom", 1.0), odom),
    ]
    for record, payload in records:
        assert record_payload(record) is payload
