"""ROS bag loader: bags written with rosbags itself (ROS 1 and ROS 2) read back exactly."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from rosbags.rosbag1 import Writer as Writer1
from rosbags.rosbag2 import StoragePlugin
from rosbags.rosbag2 import Writer as Writer2
from rosbags.typesys import Stores, get_types_from_msg, get_typestore
from scanflow.geometry import Pose2D
from scanflow.io.detect import detect_format, open_log, record_payload
from scanflow.io.rosbag import BagFormatError, BagOdom, BagScan, read_bag

SCAN, ODOM, TF = "sensor_msgs/msg/LaserScan", "nav_msgs/msg/Odometry", "tf2_msgs/msg/TFMessage"
N_BEAMS = 8


class MessageFactory:
    """Builds LaserScan / Odometry / TFMessage objects for one typestore (ROS 1 or ROS 2)."""

    def __init__(self, store: Any) -> None:
        self.store = store
        self.ros1 = "seq" in store.types["std_msgs/msg/Header"].__dataclass_fields__

    def _t(self, name: str) -> Any:
        return self.store.types[name]

    def header(self, stamp_s: float, frame_id: str) -> Any:
        sec = math.floor(stamp_s)
        stamp = self._t("builtin_interfaces/msg/Time")(
            sec=sec, nanosec=round((stamp_s - sec) * 1e9)
        )
        extra = {"seq": 0} if self.ros1 else {}
        return self._t("std_msgs/msg/Header")(stamp=stamp, frame_id=frame_id, **extra)

    def scan(self, stamp_s: float, ranges: np.ndarray, time_increment: float) -> Any:
        return self._t(SCAN)(
            header=self.header(stamp_s, "base_laser"),
            angle_min=-1.5,
            angle_max=1.5,
            angle_increment=3.0 / (N_BEAMS - 1),
            time_increment=time_increment,
            scan_time=0.1,
            range_min=0.1,
            range_max=30.0,
            ranges=ranges.astype(np.float32),
            intensities=np.arange(N_BEAMS, dtype=np.float32),
        )

    def _quat(self, yaw: float) -> Any:
        q = self._t("geometry_msgs/msg/Quaternion")
        return q(x=0.0, y=0.0, z=math.sin(yaw / 2), w=math.cos(yaw / 2))

    def _vec(self, name: str, x: float, y: float, z: float) -> Any:
        return self._t(name)(x=x, y=y, z=z)

    def odom(self, stamp_s: float, pose: Pose2D, v: tuple[float, float, float]) -> Any:
        p = self._t("geometry_msgs/msg/Pose")(
            position=self._vec("geometry_msgs/msg/Point", pose.x, pose.y, 0.0),
            orientation=self._quat(pose.theta),
        )
        twist = self._t("geometry_msgs/msg/Twist")(
            linear=self._vec("geometry_msgs/msg/Vector3", v[0], v[1], 0.0),
            angular=self._vec("geometry_msgs/msg/Vector3", 0.0, 0.0, v[2]),
        )
        return self._t(ODOM)(
            header=self.header(stamp_s, "odom"),
            child_frame_id="base_link",
            pose=self._t("geometry_msgs/msg/PoseWithCovariance")(pose=p, covariance=np.zeros(36)),
            twist=self._t("geometry_msgs/msg/TwistWithCovariance")(
                twist=twist, covariance=np.zeros(36)
            ),
        )

    def tf(self, stamp_s: float, pose: Pose2D, parent: str, child: str) -> Any:
        transform = self._t("geometry_msgs/msg/Transform")(
            translation=self._vec("geometry_msgs/msg/Vector3", pose.x, pose.y, 0.0),
            rotation=self._quat(pose.theta),
        )
        stamped = self._t("geometry_msgs/msg/TransformStamped")(
            header=self.header(stamp_s, parent), child_frame_id=child, transform=transform
        )
        return self._t(TF)(transforms=[stamped])


def _samples() -> list[tuple[str, str, float, Any]]:
    """(topic, type, stamp, payload args): two robots' scans, odometry, and tf."""
    rng = np.random.default_rng(5)
    out: list[tuple[str, str, float, Any]] = []
    for i in range(4):
        t = 100.0 + 0.1 * i
        ranges = rng.uniform(0.5, 20.0, N_BEAMS)
        ranges[i] = np.inf if i % 2 else 0.0  # a "no return" either way
        out.append(("/scan", SCAN, t, (ranges, 0.001 if i % 2 else 0.0)))
        out.append(("/odom", ODOM, t + 0.05, (Pose2D(i * 0.1, 0.02 * i, 0.3 * i), (0.5, 0.0, 0.2))))
        out.append(("/tf", TF, t + 0.06, (Pose2D(i * 0.2, 0.0, -0.1 * i), "odom", "base_link")))
        out.append(("/tf", TF, t + 0.07, (Pose2D(), "map", "odom")))
    out.append(("/robot2/scan", SCAN, 100.5, (np.full(N_BEAMS, 3.0), 0.0)))
    return out


def _message(factory: MessageFactory, msgtype: str, stamp: float, args: Any) -> Any:
    builder = {SCAN: factory.scan, ODOM: factory.odom, TF: factory.tf}[msgtype]
    return builder(stamp, *args)


def write_ros1_bag(path: Path, with_odom: bool = True) -> Path:
    store = get_typestore(Stores.ROS1_NOETIC)
    # rosbags' ROS 1 store lacks TFMessage; ROS 1 defines it the same way.
    store.register(get_types_from_msg("geometry_msgs/TransformStamped[] transforms", TF))
    factory = MessageFactory(store)
    with Writer1(path) as writer:
        conns: dict[str, Any] = {}
        for topic, msgtype, stamp, args in _samples():
            if msgtype == ODOM and not with_odom:
                continue
            if topic not in conns:
                conns[topic] = writer.add_connection(topic, msgtype, typestore=store)
            data = store.serialize_ros1(_message(factory, msgtype, stamp, args), msgtype)
            writer.write(conns[topic], int(stamp * 1e9), data)
    return path


def write_ros2_bag(path: Path, storage: StoragePlugin = StoragePlugin.SQLITE3) -> Path:
    store = get_typestore(Stores.ROS2_HUMBLE)
    factory = MessageFactory(store)
    with Writer2(path, version=9, storage_plugin=storage) as writer:
        conns: dict[str, Any] = {}
        for topic, msgtype, stamp, args in _samples():
            if topic not in conns:
                conns[topic] = writer.add_connection(topic, msgtype, typestore=store)
            data = store.serialize_cdr(_message(factory, msgtype, stamp, args), msgtype)
            writer.write(conns[topic], int(stamp * 1e9), data)
    return path


@pytest.fixture(params=["ros1", "ros2-sqlite3", "ros2-mcap"])
def bag(request, tmp_path: Path) -> Path:
    if request.param == "ros1":
        return write_ros1_bag(tmp_path / "test.bag")
    storage = StoragePlugin.MCAP if request.param.endswith("mcap") else StoragePlugin.SQLITE3
    return write_ros2_bag(tmp_path / "test_bag", storage)


def _expected(topic_type: str) -> list[tuple[str, str, float, Any]]:
    return [s for s in _samples() if s[1] == topic_type]


def test_scans_read_back_exactly(bag: Path) -> None:
    scans = [r for r in read_bag(bag) if isinstance(r, BagScan)]
    expected = _expected(SCAN)
    assert [r.topic for r in scans] == [e[0] for e in expected]
    for rec, (topic, _, stamp, (ranges, time_inc)) in zip(scans, expected, strict=True):
        scan = rec.scan
        np.testing.assert_array_equal(scan.ranges_m, ranges.astype(np.float32))
        np.testing.assert_array_equal(scan.intensities, np.arange(N_BEAMS))
        assert scan.stamp_s == pytest.approx(stamp, abs=1e-9)
        assert rec.bag_time_s == pytest.approx(stamp, abs=1e-9)
        assert scan.angle_min_rad == pytest.approx(-1.5)
        assert scan.angle_increment_rad == pytest.approx(3.0 / (N_BEAMS - 1))
        assert scan.range_min_m == pytest.approx(0.1) and scan.range_max_m == pytest.approx(30.0)
        assert scan.scan_duration_s == pytest.approx(0.1)
        assert scan.frame_id == "base_laser"
        assert scan.robot_id == ("robot2" if topic.startswith("/robot2") else "robot")
        assert scan.beam_times_assumed == (time_inc == 0.0)
        if time_inc:
            np.testing.assert_allclose(scan.time_offsets_s, np.arange(N_BEAMS) * time_inc)
    assert [r.scan.valid_count for r in scans[:4]] == [N_BEAMS - 1] * 4


def test_odometry_topic_preferred_over_tf(bag: Path) -> None:
    odoms = [r for r in read_bag(bag) if isinstance(r, BagOdom)]
    expected = _expected(ODOM)
    assert [r.topic for r in odoms] == ["/odom"] * len(expected)
    for rec, (_, _, stamp, (pose, velocity)) in zip(odoms, expected, strict=True):
        np.testing.assert_allclose(rec.odom.pose.to_array(), pose.to_array(), atol=1e-9)
        np.testing.assert_allclose(rec.odom.velocity, velocity)
        assert rec.odom.stamp_s == pytest.approx(stamp, abs=1e-9)
    assert [r.odom.seq for r in odoms] == list(range(len(expected)))


def test_records_come_in_time_order(bag: Path) -> None:
    times = [r.bag_time_s for r in read_bag(bag)]
    assert times == sorted(times) and len(times) == 9


def test_tf_odom_to_base_link_when_no_odometry_topic(tmp_path: Path) -> None:
    path = write_ros1_bag(tmp_path / "tf_only.bag", with_odom=False)
    odoms = [r.odom for r in read_bag(path) if isinstance(r, BagOdom)]
    expected = [s for s in _samples() if s[1] == TF and s[3][1] == "odom"]
    assert len(odoms) == len(expected)
    for odom, (_, _, stamp, (pose, _, _)) in zip(odoms, expected, strict=True):
        np.testing.assert_allclose(odom.pose.to_array(), pose.to_array(), atol=1e-9)
        assert odom.velocity is None
        assert odom.stamp_s == pytest.approx(stamp, abs=1e-9)


def test_topic_selection(bag: Path) -> None:
    records = list(read_bag(bag, topics=["/robot2/scan"], robot_id="r2"))
    assert len(records) == 1 and records[0].scan.robot_id == "r2"
    with pytest.raises(BagFormatError, match="/nope"):
        list(read_bag(bag, topics=["/nope"]))


def test_detect_and_open_any_log(bag: Path) -> None:
    assert detect_format(bag) == ("rosbag1" if bag.suffix == ".bag" else "rosbag2")
    payloads = [record_payload(r) for r in open_log(bag)]
    assert len(payloads) == 9


def test_detect_errors(tmp_path: Path) -> None:
    with pytest.raises(FileNotFoundError, match="missing"):
        detect_format(tmp_path / "missing")
    with pytest.raises(ValueError, match=r"metadata\.yaml"):
        detect_format(tmp_path)
    text = tmp_path / "x.log"
    text.write_text("ODOM 0 0 0 0 0 0 1 h 1\n")
    assert detect_format(text) == "carmen"


def test_broken_bag_raises_a_format_error(tmp_path: Path) -> None:
    path = tmp_path / "broken.bag"
    path.write_bytes(b"#ROSBAG V2.0\n" + b"\x00" * 64)
    with pytest.raises(BagFormatError, match=r"broken\.bag"):
        list(read_bag(path))
