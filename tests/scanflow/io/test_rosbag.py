"""ROS bag loader: bags written with rosbags itself (ROS 1 and ROS 2) read back exactly."""

from __future__ import annotations

import functools
import math
from collections.abc import Callable
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from rosbags.rosbag1 import Writer as Writer1
from rosbags.rosbag2 import StoragePlugin
from rosbags.rosbag2 import Writer as Writer2
from rosbags.typesys import Stores, get_types_from_msg, get_typestore
from scanflow.geometry import IDENTITY, Pose2D
from scanflow.io.detect import detect_format, open_log, record_payload
from scanflow.io.rosbag import (
    MAX_TILT_RAD,
    BagFormatError,
    BagOdom,
    BagReader,
    BagScan,
    TransformTree,
    read_bag,
    yaw_from_quaternion,
)

SCAN, ODOM, TF = "sensor_msgs/msg/LaserScan", "nav_msgs/msg/Odometry", "tf2_msgs/msg/TFMessage"
N_BEAMS = 8
Vec3 = tuple[float, float, float]
Link = tuple[str, str, Vec3, Vec3]  # parent, child, translation, (roll, pitch, yaw)


def quaternion_xyzw(roll: float, pitch: float, yaw: float) -> tuple[float, float, float, float]:
    """The quaternion of Rz(yaw) * Ry(pitch) * Rx(roll) (the ROS RPY convention)."""
    cr, sr = math.cos(roll / 2), math.sin(roll / 2)
    cp, sp = math.cos(pitch / 2), math.sin(pitch / 2)
    cy, sy = math.cos(yaw / 2), math.sin(yaw / 2)
    return (
        sr * cp * cy - cr * sp * sy,
        cr * sp * cy + sr * cp * sy,
        cr * cp * sy - sr * sp * cy,
        cr * cp * cy + sr * sp * sy,
    )


def rpy_matrix(xyz: Vec3, rpy: Vec3) -> np.ndarray:
    """4x4 transform from elementary rotations, independent of any quaternion code."""
    (cr, sr), (cp, sp), (cy, sy) = ((math.cos(a), math.sin(a)) for a in rpy)
    rx = np.array([[1, 0, 0], [0, cr, -sr], [0, sr, cr]])
    ry = np.array([[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]])
    rz = np.array([[cy, -sy, 0], [sy, cy, 0], [0, 0, 1]])
    m = np.eye(4)
    m[:3, :3] = rz @ ry @ rx
    m[:3, 3] = xyz
    return m


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

    def scan(
        self, stamp_s: float, ranges: np.ndarray, time_increment: float, frame: str = "base_laser"
    ) -> Any:
        return self._t(SCAN)(
            header=self.header(stamp_s, frame),
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

    def static_tf(self, stamp_s: float, links: list[Link]) -> Any:
        """A TFMessage with 3D transforms (parent, child, xyz, roll-pitch-yaw)."""
        stamped = self._t("geometry_msgs/msg/TransformStamped")
        transforms = [
            stamped(
                header=self.header(stamp_s, parent),
                child_frame_id=child,
                transform=self._t("geometry_msgs/msg/Transform")(
                    translation=self._vec("geometry_msgs/msg/Vector3", *xyz),
                    rotation=self._t("geometry_msgs/msg/Quaternion")(
                        **dict(zip("xyzw", quaternion_xyzw(*rpy), strict=True))
                    ),
                ),
            )
            for parent, child, xyz, rpy in links
        ]
        return self._t(TF)(transforms=transforms)

    def _vec(self, name: str, x: float, y: float, z: float) -> Any:
        return self._t(name)(x=x, y=y, z=z)

    def odom(
        self, stamp_s: float, pose: Pose2D, v: tuple[float, float, float], child: str = "base_link"
    ) -> Any:
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
            child_frame_id=child,
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


def robot_records(
    scan_topics: list[str], tf_topic: str, frames: list[str], odom_topic: str | None = None
) -> list[tuple[str, str, float, Build]]:
    """A scan on each of `scan_topics`, then an odom -> base_link transform of each frame
    namespace in `frames` ("" for bare frames) on `tf_topic`, or an Odometry message per
    namespace on `odom_topic`; twice."""
    out: list[tuple[str, str, float, Build]] = []
    for i in range(2):
        t = 100.0 + 0.1 * i
        for topic in scan_topics:
            out.append((topic, SCAN, t, lambda f, t=t: f.scan(t, np.full(N_BEAMS, 2.0), 0.0)))
        for k, ns in enumerate(frames):
            at, pose, base = t + 0.01, Pose2D(k, 0.1 * i, 0.0), f"{ns}base_link"
            if odom_topic is None:
                args = (at, pose, f"{ns}odom", base)
                out.append((tf_topic, TF, at, lambda f, a=args: f.tf(*a)))
            else:
                args = (at, pose, (0.0, 0.0, 0.0), base)
                out.append((odom_topic, ODOM, at, lambda f, a=args: f.odom(*a)))
    return out


def robots_of(path: Path, **options: Any) -> tuple[list[str], dict[str, list[float]]]:
    """The scans' robots, and each robot's odometry x positions, as the reader names them."""
    scans, odom_x = [], {}
    for record in BagReader(path, **options):
        if isinstance(record, BagScan):
            scans.append(record.scan.robot_id)
        else:
            odom_x.setdefault(record.odom.robot_id, []).append(record.odom.pose.x)
    return scans, odom_x


@pytest.mark.parametrize("kind", ["ros1", "ros2-mcap"])
def test_a_namespaced_robot_gets_the_odometry_of_a_global_tf_or_odom_topic(
    tmp_path: Path, kind: str
) -> None:
    """Scans on /robot1/scan with odometry on the global /tf (or /odom): both are robot1's.
    Named after their topics alone, the odometry went to "robot" and robot1 had none."""
    for name, records in [
        ("tf", robot_records(["/robot1/scan"], "/tf", [""])),
        ("odom", robot_records(["/robot1/scan"], "/tf", [""], odom_topic="/odom")),
    ]:
        scans, odom_x = robots_of(write_records(tmp_path / name, kind, records))
        assert scans == ["robot1", "robot1"]
        assert odom_x == {"robot1": [0.0, 0.0]}


@pytest.mark.parametrize("kind", ["ros1", "ros2-mcap"])
def test_each_robot_of_a_shared_tf_gets_its_own_odometry_by_frame_namespace(
    tmp_path: Path, kind: str
) -> None:
    """Two robots' scans under their namespaces and one global /tf with robot1/odom ->
    robot1/base_link and robot2/...: each robot gets its own transforms (they were all
    "robot"'s, two robots' poses in one stream)."""
    records = robot_records(["/robot1/scan", "/robot2/scan"], "/tf", ["robot1/", "robot2/"])
    scans, odom_x = robots_of(write_records(tmp_path, kind, records))
    assert sorted(scans) == ["robot1", "robot1", "robot2", "robot2"]
    assert odom_x == {"robot1": [0.0, 0.0], "robot2": [1.0, 1.0]}


def test_global_odometry_stays_apart_when_the_scans_are_of_several_robots(
    tmp_path: Path,
) -> None:
    """A global scan topic beside a namespaced one, or bare frames shared by two robots: no
    robot is the one, so global odometry stays "robot"'s, as the global scans are; a frame
    namespace no scan topic names does not make a robot; a given robot_id takes everything."""
    both = robot_records(["/scan", "/robot2/scan"], "/tf", [""])
    scans, odom_x = robots_of(write_records(tmp_path / "a", "ros1", both))
    assert sorted(scans) == ["robot", "robot", "robot2", "robot2"]
    assert odom_x == {"robot": [0.0, 0.0]}
    stray = robot_records(["/robot1/scan", "/robot2/scan"], "/tf", ["robot3/"])
    assert robots_of(write_records(tmp_path / "b", "ros1", stray))[1] == {"robot": [0.0, 0.0]}
    shared = robot_records(["/robot1/scan", "/robot2/scan"], "/tf", ["robot1/", "robot2/"])
    scans, odom_x = robots_of(write_records(tmp_path / "c", "ros1", shared), robot_id="r")
    assert scans == ["r"] * 4 and odom_x == {"r": [0.0, 1.0, 0.0, 1.0]}


def test_topic_selection(bag: Path) -> None:
    records = list(read_bag(bag, topics=["/robot2/scan"], robot_id="r2"))
    assert len(records) == 1 and records[0].scan.robot_id == "r2"
    with pytest.raises(BagFormatError, match="/nope"):
        list(read_bag(bag, topics=["/nope"]))


def test_an_empty_topic_selection_reads_nothing(bag: Path) -> None:
    """No topics selected is no records, not every topic: rosbags reads all connections when
    given none to filter on."""
    assert list(read_bag(bag, topics=[])) == []


def test_detect_and_open_any_log(bag: Path) -> None:
    assert detect_format(bag) == ("rosbag1" if bag.suffix == ".bag" else "rosbag2")
    payloads = [record_payload(r) for r in open_log(bag)]
    assert len(payloads) == 9


def test_broken_bag_raises_a_format_error(tmp_path: Path) -> None:
    path = tmp_path / "broken.bag"
    path.write_bytes(b"#ROSBAG V2.0\n" + b"\x00" * 64)
    with pytest.raises(BagFormatError, match=r"broken\.bag"):
        list(read_bag(path))


@pytest.mark.filterwarnings("ignore:overflow:RuntimeWarning")  # a damaged quaternion's norm
def test_a_damaged_or_cut_bag_gives_its_records_or_a_format_error_naming_it(bag: Path) -> None:
    """Bytes overwritten or cut off anywhere in the storage file: reading ends or raises
    BagFormatError naming the bag, never what rosbags' parsers or sqlite hit on the way
    (AssertionError, KeyError, UnicodeDecodeError, apsw.CorruptError, ...)."""
    storage = bag if bag.is_file() else next(p for p in bag.iterdir() if p.suffix != ".yaml")
    data = np.frombuffer(storage.read_bytes(), dtype=np.uint8)
    rng = np.random.default_rng(7)
    damaged = [data[:cut] for cut in range(0, data.size, max(1, data.size // 50))]
    # 50 seeded overwrites beside the cuts: in every kind they still reach each error type
    # that the 150 of before reached through the parsers (ros1: AssertionError, KeyError,
    # UnicodeDecodeError, ReaderError; sqlite3: KeyError, UnicodeDecodeError, and CorruptError
    # from the cuts; mcap: KeyError, UnicodeDecodeError), in half the reads.
    for _ in range(50):
        copy = data.copy()
        copy[rng.integers(data.size, size=3)] = rng.integers(256, size=3)
        damaged.append(copy)
    for version in damaged:
        storage.write_bytes(version.tobytes())
        try:
            list(read_bag(bag))
        except BagFormatError as exc:
            assert str(bag) in str(exc)


# Sensor mounts from tf: bags written with a /tf_static (or /tf) chain down to the scan frame.

Build = Callable[[MessageFactory], Any]
BAG_KINDS = ["ros1", "ros2-sqlite3", "ros2-mcap"]


def write_records(tmp_path: Path, kind: str, records: list[tuple[str, str, float, Build]]) -> Path:
    """A bag of one kind holding (topic, type, bag time, message builder) records (a builder
    may return the raw bytes to store)."""
    tmp_path.mkdir(parents=True, exist_ok=True)
    if kind == "ros1":
        store = get_typestore(Stores.ROS1_NOETIC)
        store.register(get_types_from_msg("geometry_msgs/TransformStamped[] transforms", TF))
        writer: Any = Writer1(tmp_path / "mount.bag")
        serialize = store.serialize_ros1
    else:
        store = get_typestore(Stores.ROS2_HUMBLE)
        plugin = StoragePlugin.MCAP if kind.endswith("mcap") else StoragePlugin.SQLITE3
        writer = Writer2(tmp_path / "mount_bag", version=9, storage_plugin=plugin)
        serialize = store.serialize_cdr
    factory = MessageFactory(store)
    with writer:
        conns: dict[str, Any] = {}
        for topic, msgtype, stamp, build in records:
            if topic not in conns:
                conns[topic] = writer.add_connection(topic, msgtype, typestore=store)
            message = build(factory)
            data = message if isinstance(message, bytes) else serialize(message, msgtype)
            writer.write(conns[topic], int(stamp * 1e9), data)
    return writer.path


def scans_and_odometry(frame: str = "laser") -> list[tuple[str, str, float, Build]]:
    """Three scans in `frame` at 100.0, 100.1, 100.2 s and an odom -> base_link tf after each."""
    out: list[tuple[str, str, float, Build]] = []
    for i in range(3):
        t = 100.0 + 0.1 * i
        ranges = np.linspace(1.0, 4.0, N_BEAMS) + i
        out.append(("/scan", SCAN, t, lambda f, t=t, r=ranges: f.scan(t, r, 0.001, frame)))
        pose = Pose2D(0.1 * i, 0.0, 0.05 * i)
        out.append(("/tf", TF, t + 0.01, lambda f, t=t, p=pose: f.tf(t, p, "odom", "base_link")))
    return out


def static_tf(stamp: float, links: list[Link], topic: str = "/tf_static") -> tuple:
    return (topic, TF, stamp, lambda f: f.static_tf(stamp, links))


def read_scans(path: Path, **options: Any) -> tuple[list[BagScan], BagReader]:
    reader = BagReader(path, **options)
    return [r for r in reader if isinstance(r, BagScan)], reader


def base_points(scan_angles: np.ndarray, ranges: np.ndarray, matrix: np.ndarray) -> np.ndarray:
    """Beam endpoints in the sensor plane moved into the base frame in 3D, seen from above."""
    sensor = np.column_stack((ranges * np.cos(scan_angles), ranges * np.sin(scan_angles)))
    homogeneous = np.column_stack((sensor, np.zeros(len(sensor)), np.ones(len(sensor))))
    return (homogeneous @ matrix.T)[:, :2]


CHAIN: list[Link] = [
    ("/base_link", "base_laser_link", (0.2, 0.05, 0.3), (0.0, 0.0, 0.3)),
    ("base_laser_link", "laser", (0.1, -0.02, 0.05), (0.0, 0.0, -0.5)),
]


@pytest.mark.parametrize("kind", BAG_KINDS)
def test_mount_is_the_static_chain_even_when_recorded_after_scans(
    tmp_path: Path, kind: str
) -> None:
    # Each link in its own /tf_static message, both after the first scan in bag time.
    records = [*scans_and_odometry(), static_tf(100.05, CHAIN[:1]), static_tf(100.15, CHAIN[1:])]
    path = write_records(tmp_path, kind, sorted(records, key=lambda r: r[2]))
    scans, reader = read_scans(path)
    expected = Pose2D(0.2, 0.05, 0.3) * Pose2D(0.1, -0.02, -0.5)
    assert len(scans) == 3 and reader.error_count == 0
    for rec in scans:
        np.testing.assert_allclose(rec.scan.mount.to_array(), expected.to_array(), atol=1e-12)
        assert rec.scan.angle_increment_rad > 0
    odoms = [r for r in read_bag(path) if isinstance(r, BagOdom)]
    assert len(odoms) == 3  # odom -> base_link on /tf is still the odometry


def test_no_transform_to_the_scan_frame_gives_identity(bag: Path) -> None:
    # The shared sample bags hold only odom -> base_link and map -> odom.
    assert all(r.scan.mount == IDENTITY for r in read_bag(bag) if isinstance(r, BagScan))


def test_scan_in_the_base_frame_gives_identity(tmp_path: Path) -> None:
    records = [*scans_and_odometry("base_link"), static_tf(99.0, CHAIN)]
    scans, _ = read_scans(write_records(tmp_path, "ros2-sqlite3", records))
    assert [r.scan.mount for r in scans] == [IDENTITY] * 3


def test_namespaced_chain_stops_at_the_bare_base_frame(tmp_path: Path) -> None:
    links: list[Link] = [
        ("robot1/base_link", "robot1/laser", (0.3, 0.0, 0.1), (0.0, 0.0, 0.2)),
        ("robot2/base_link", "robot2/laser", (-0.3, 0.0, 0.1), (0.0, 0.0, 0.0)),
    ]
    records = [*scans_and_odometry("/robot1/laser"), static_tf(99.0, links)]
    scans, _ = read_scans(write_records(tmp_path, "ros2-mcap", records))
    assert {r.scan.mount for r in scans} == {Pose2D(0.3, 0.0, 0.2)}


@pytest.mark.parametrize("kind", ["ros1", "ros2-sqlite3"])
def test_fixed_transform_on_tf_first_one_wins_and_tf_static_overrides(
    tmp_path: Path, kind: str
) -> None:
    """ROS 1 static_transform_publisher sends base_link -> laser on /tf, over and over."""
    first = ("base_link", "laser", (0.25, 0.0, 0.2), (0.0, 0.0, 0.1))
    later = ("base_link", "laser", (0.5, 0.5, 0.2), (0.0, 0.0, 1.0))
    records = [
        *scans_and_odometry(),
        static_tf(100.02, [first], "/tf"),
        static_tf(100.12, [later], "/tf"),
    ]
    ordered = sorted(records, key=lambda r: r[2])
    scans, _ = read_scans(write_records(tmp_path / "a", kind, ordered))
    assert {r.scan.mount for r in scans} == {Pose2D(0.25, 0.0, 0.1)}
    static = ("base_link", "laser", (-0.1, 0.0, 0.2), (0.0, 0.0, math.pi / 2))
    ordered = sorted([*records, static_tf(100.3, [static])], key=lambda r: r[2])
    scans, _ = read_scans(write_records(tmp_path / "b", kind, ordered))
    assert {r.scan.mount for r in scans} == {Pose2D(-0.1, 0.0, math.pi / 2)}


@pytest.mark.parametrize(
    ("xyz", "rpy", "mirrored"),
    [
        ((0.3, -0.1, 0.4), (0.0, 0.0, 0.7), False),
        ((0.3, -0.1, 0.4), (0.01, -0.01, 0.7), False),  # within MAX_TILT_RAD: the plane's yaw
        ((0.2, 0.1, 0.5), (math.pi, 0.0, 0.4), True),  # upside down: rolled
        ((0.2, 0.1, 0.5), (0.0, math.pi, -2.0), True),  # upside down: pitched
    ],
)
def test_mounted_beams_land_where_the_3d_transform_puts_them(
    tmp_path: Path, xyz: Vec3, rpy: Vec3, mirrored: bool
) -> None:
    link = ("base_link", "laser", xyz, rpy)
    records = [*scans_and_odometry(), static_tf(99.0, [link])]
    scans, reader = read_scans(write_records(tmp_path, "ros2-sqlite3", records))
    assert len(scans) == 3 and reader.error_count == 0
    # As the factory writes them: float32 fields.
    angles = -1.5 + np.arange(N_BEAMS) * float(np.float32(3.0 / (N_BEAMS - 1)))
    tilt = (rpy[0] % math.pi) ** 2 + (rpy[1] % math.pi) ** 2  # 0 when level or upside down
    for rec in scans:
        scan = rec.scan
        assert (scan.angle_increment_rad < 0) == mirrored
        np.testing.assert_allclose(scan.time_offsets_s, np.arange(N_BEAMS) * 0.001, rtol=1e-6)
        got = scan.mount.transform_points(scan.points())
        want = base_points(angles, scan.ranges_m.astype(np.float64), rpy_matrix(xyz, rpy))
        # Exact when level or flipped; a small tilt errs by second order: range * tilt^2.
        np.testing.assert_allclose(got, want, atol=1e-9 + float(scan.ranges_m.max()) * tilt)


def test_tilted_scan_frame_is_an_error_naming_it(tmp_path: Path) -> None:
    link = ("base_link", "tilted_laser", (0.2, 0.0, 0.3), (0.0, MAX_TILT_RAD + 0.05, 0.0))
    path = write_records(
        tmp_path, "ros2-sqlite3", [*scans_and_odometry("tilted_laser"), static_tf(99.0, [link])]
    )
    scans, reader = read_scans(path)
    assert scans == [] and reader.error_count == 3
    assert all("'tilted_laser'" in e and "tilted" in e for e in reader.errors)
    assert len([r for r in read_bag(path) if isinstance(r, BagOdom)]) == 3
    with pytest.raises(BagFormatError, match="tilted_laser"):
        list(read_bag(path, strict=True))


def test_broken_static_transform_is_reported(tmp_path: Path) -> None:
    def zero_quaternion(f: MessageFactory) -> Any:
        msg = f.static_tf(99.0, CHAIN[:1])
        rotation = msg.transforms[0].transform.rotation
        rotation.x = rotation.y = rotation.z = rotation.w = 0.0
        return msg

    records = [*scans_and_odometry(), ("/tf_static", TF, 99.0, zero_quaternion)]
    scans, reader = read_scans(write_records(tmp_path, "ros2-sqlite3", records))
    assert len(scans) == 3 and reader.error_count == 1
    assert "/tf_static" in reader.errors[0] and "quaternion" in reader.errors[0]


def _tf_message(links: list[tuple[str, str, np.ndarray]]) -> Any:
    """A duck-typed TFMessage (what TransformTree reads) from 4x4 matrices."""
    transforms = []
    for parent, child, m in links:
        x, y, z, w = _matrix_quaternion(m[:3, :3])
        transforms.append(
            SimpleNamespace(
                header=SimpleNamespace(frame_id=parent),
                child_frame_id=child,
                transform=SimpleNamespace(
                    translation=SimpleNamespace(x=m[0, 3], y=m[1, 3], z=m[2, 3]),
                    rotation=SimpleNamespace(x=x, y=y, z=z, w=w),
                ),
            )
        )
    return SimpleNamespace(transforms=transforms)


def _matrix_quaternion(r: np.ndarray) -> tuple[float, float, float, float]:
    """(x, y, z, w) of a rotation matrix, from the eigenvector of its 4x4 symmetric form."""
    k = np.array(
        [
            [r[0, 0] - r[1, 1] - r[2, 2], r[1, 0] + r[0, 1], r[2, 0] + r[0, 2], r[2, 1] - r[1, 2]],
            [r[1, 0] + r[0, 1], r[1, 1] - r[0, 0] - r[2, 2], r[2, 1] + r[1, 2], r[0, 2] - r[2, 0]],
            [r[2, 0] + r[0, 2], r[2, 1] + r[1, 2], r[2, 2] - r[0, 0] - r[1, 1], r[1, 0] - r[0, 1]],
            [r[2, 1] - r[1, 2], r[0, 2] - r[2, 0], r[1, 0] - r[0, 1], r[0, 0] + r[1, 1] + r[2, 2]],
        ]
    )
    _, vectors = np.linalg.eigh(k / 3.0)
    return tuple(vectors[:, -1])


LEVEL_OR_FLIPPED_LINK = st.tuples(
    st.tuples(*[st.floats(-2.0, 2.0)] * 3),
    st.sampled_from([(0.0, 0.0), (math.pi, 0.0), (0.0, math.pi)]),
    st.floats(-math.pi, math.pi),
)


@given(st.lists(LEVEL_OR_FLIPPED_LINK, min_size=1, max_size=4))
def test_any_level_or_flipped_chain_places_the_scan_plane_exactly(links: list) -> None:
    """Composed through up to four links, each level or upside down, the mount (and mirroring)
    puts points of the sensor's plane where the 3D chain does."""
    frames = ["base_link"] + [f"f{i}" for i in range(len(links))]
    matrices = [rpy_matrix(xyz, (*rp, yaw)) for xyz, rp, yaw in links]
    tree = TransformTree("base_link")
    tree.add(_tf_message(list(zip(frames[:-1], frames[1:], matrices, strict=True))), override=True)
    mount = tree.mount(frames[-1])
    chain = functools.reduce(np.matmul, matrices)
    points = np.array([[1.0, 0.0], [0.0, 2.0], [-1.5, 0.5]])
    sensor = points * [1.0, -1.0] if mount.mirrored else points
    want = base_points(np.arctan2(points[:, 1], points[:, 0]), np.hypot(*points.T), chain)
    np.testing.assert_allclose(mount.pose.transform_points(sensor), want, atol=1e-9)
    assert mount.mirrored == (chain[2, 2] < 0)


def _cut(build: Build, msgtype: str, ros1: bool) -> Build:
    """`build`'s message serialized, then cut to its first 20 bytes: a damaged message."""

    def cut(f: MessageFactory) -> bytes:
        serialize = f.store.serialize_ros1 if ros1 else f.store.serialize_cdr
        return bytes(serialize(build(f), msgtype)[:20])

    return cut


@pytest.mark.parametrize("kind", BAG_KINDS)
@pytest.mark.parametrize(
    ("topic", "msgtype", "stamp", "build"),
    [
        ("/scan", SCAN, 99.9, lambda f: f.scan(99.9, np.ones(N_BEAMS), 0.0, "laser")),  # 1st
        ("/scan", SCAN, 100.05, lambda f: f.scan(100.05, np.ones(N_BEAMS), 0.0, "laser")),
        ("/tf_static", TF, 99.0, lambda f: f.static_tf(99.0, CHAIN)),
    ],
)
def test_a_message_that_does_not_deserialize_is_reported_and_skipped(
    tmp_path: Path, kind: str, topic: str, msgtype: str, stamp: float, build: Build
) -> None:
    """A damaged message (cut short) is a bad record, not the end of the bag (without an
    Odometry topic a tf_static message is read twice, for the mounts and as possible
    odometry: both report it)."""
    damaged = (topic, msgtype, stamp, _cut(build, msgtype, kind == "ros1"))
    records = sorted([*scans_and_odometry(), damaged], key=lambda r: r[2])
    path = write_records(tmp_path, kind, records)
    heard: list[str] = []
    scans, reader = read_scans(path, on_error=heard.append)
    assert len(scans) == 3 and reader.error_count >= 1
    assert all(e.startswith(f"{topic} @ {stamp:.2f}") for e in reader.errors)
    assert heard == [f"{path}: {e}" for e in reader.errors]  # as it happens, the bag named
    with pytest.raises(BagFormatError, match=f"{topic} @ {stamp:.2f}"):
        list(read_bag(path, strict=True))


@given(
    st.floats(-3.0, 3.0),
    st.tuples(st.floats(-0.2, 0.2), st.floats(-0.2, 0.2)),
    st.floats(0.5, 2.0),
)
def test_yaw_of_a_quaternion_does_not_depend_on_its_norm(
    yaw: float, roll_pitch: tuple[float, float], scale: float
) -> None:
    """Recorded quaternions are not always of norm 1 (float32 fields, drivers' own maths);
    their yaw is that of the rotation they stand for, as tf2 normalises them."""
    x, y, z, w = (scale * c for c in quaternion_xyzw(*roll_pitch, yaw))
    q = SimpleNamespace(x=x, y=y, z=z, w=w)
    assert yaw_from_quaternion(q) == pytest.approx(yaw, abs=1e-9)


def test_a_zero_quaternion_has_no_yaw() -> None:
    with pytest.raises(ValueError, match="quaternion"):
        yaw_from_quaternion(SimpleNamespace(x=0.0, y=0.0, z=0.0, w=0.0))
