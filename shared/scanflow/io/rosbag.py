"""ROS 1 and ROS 2 bag reader (no ROS installation, via the pure-Python `rosbags` package).

Streams, in bag time order:
- `sensor_msgs/msg/LaserScan` -> `LaserScan`: `header.stamp` -> `stamp_s` (first beam, as in
  ROS), `scan_time` -> `scan_duration_s`, `time_increment` > 0 -> measured per-beam offsets
  `i * time_increment` (otherwise offsets are left to be assumed uniform), intensities kept
  when there is one per beam;
- `nav_msgs/msg/Odometry` -> `Odometry` (pose yaw from the quaternion, twist as velocity);
- `tf2_msgs/msg/TFMessage` (or ROS 1 `tf/tfMessage`) transforms `odom_frame -> base_frame`
  -> `Odometry` without velocity.
By default (`topics=None`) all LaserScan and Odometry topics are read, and the tf topics only
when the bag has no Odometry topic (so odometry is never counted twice).

Frame names match with a leading "/" and a namespace ignored ("/robot1/odom" is "odom").
The robot id is `robot_id` when given, else the first segment of a namespaced topic
("/robot1/scan" -> "robot1"), else "robot". Messages that make an invalid scan (e.g.
range_max below range_min) are skipped and recorded in `BagReader.errors` (or raise
`BagFormatError` with `strict=True`).
"""

from __future__ import annotations

import math
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from rosbags.highlevel import AnyReader, AnyReaderError
from rosbags.interfaces import Connection
from rosbags.typesys import Stores, get_typestore

from scanflow.geometry import Pose2D
from scanflow.scan import LaserScan, Odometry, ScanError

SCAN_TYPE = "sensor_msgs/msg/LaserScan"
ODOM_TYPE = "nav_msgs/msg/Odometry"
TF_TYPES = ("tf2_msgs/msg/TFMessage", "tf/msg/tfMessage")
MAX_RECORDED_ERRORS = 1000


class BagFormatError(ValueError):
    """A bag message that cannot be turned into a scan or odometry sample (strict mode)."""


@dataclass(frozen=True)
class BagScan:
    """A laser scan read from a bag, with its topic and bag (receive) time."""

    scan: LaserScan
    topic: str
    bag_time_s: float


@dataclass(frozen=True)
class BagOdom:
    """An odometry sample read from a bag (nav_msgs/Odometry or a tf transform)."""

    odom: Odometry
    topic: str
    bag_time_s: float


def stamp_to_s(stamp: Any) -> float:
    """A ROS time (sec, nanosec) in seconds."""
    return float(stamp.sec) + 1e-9 * float(stamp.nanosec)


def yaw_from_quaternion(q: Any) -> float:
    """Heading (rotation about z) of a quaternion with fields x, y, z, w."""
    return math.atan2(2.0 * (q.w * q.z + q.x * q.y), 1.0 - 2.0 * (q.y * q.y + q.z * q.z))


def _bare_frame(frame_id: str) -> str:
    return frame_id.rsplit("/", 1)[-1]


def _topic_robot(topic: str) -> str:
    segments = [s for s in topic.split("/") if s]
    return segments[0] if len(segments) > 1 else "robot"


def scan_from_msg(msg: Any, robot_id: str, seq: int) -> LaserScan:
    """sensor_msgs/LaserScan -> LaserScan (see the module docstring for the field mapping)."""
    ranges = np.asarray(msg.ranges, dtype=np.float32)
    intensities = np.asarray(msg.intensities, dtype=np.float32)
    offsets = np.arange(ranges.size) * msg.time_increment if msg.time_increment > 0 else None
    return LaserScan(
        ranges_m=ranges,
        angle_min_rad=msg.angle_min,
        angle_increment_rad=msg.angle_increment,
        range_min_m=max(0.0, float(msg.range_min)),
        range_max_m=msg.range_max,
        stamp_s=stamp_to_s(msg.header.stamp),
        scan_duration_s=max(0.0, float(msg.scan_time)),
        beam_time_offsets_s=offsets,
        robot_id=robot_id,
        frame_id=msg.header.frame_id or "laser",
        intensities=intensities if intensities.size == ranges.size else None,
        seq=seq,
    )


def odom_from_msg(msg: Any, robot_id: str, seq: int) -> Odometry:
    """nav_msgs/Odometry -> Odometry (planar part: x, y, yaw; v_x, v_y, omega)."""
    p = msg.pose.pose
    t = msg.twist.twist
    pose = Pose2D(p.position.x, p.position.y, yaw_from_quaternion(p.orientation))
    velocity = (t.linear.x, t.linear.y, t.angular.z)
    return Odometry(stamp_to_s(msg.header.stamp), pose, velocity, robot_id, seq)


class BagReader:
    """Iterates the scans and odometry of one ROS 1 (.bag) or ROS 2 (directory) bag."""

    def __init__(
        self,
        path: str | Path,
        *,
        topics: Sequence[str] | None = None,
        robot_id: str | None = None,
        odom_frame: str = "odom",
        base_frame: str = "base_link",
        strict: bool = False,
    ) -> None:
        self.path = Path(path)
        self.topics = None if topics is None else list(topics)
        self.robot_id = robot_id
        self.odom_frame = odom_frame
        self.base_frame = base_frame
        self.strict = strict
        self.errors: list[str] = []
        self.error_count = 0

    def _selected(self, connections: Sequence[Connection]) -> list[Connection]:
        if self.topics is not None:
            missing = set(self.topics) - {c.topic for c in connections}
            if missing:
                raise BagFormatError(f"{self.path}: topics not in the bag: {sorted(missing)}")
            return [c for c in connections if c.topic in self.topics]
        wanted = {SCAN_TYPE, ODOM_TYPE}
        if not any(c.msgtype == ODOM_TYPE for c in connections):
            wanted.update(TF_TYPES)
        return [c for c in connections if c.msgtype in wanted]

    def __iter__(self) -> Iterator[BagScan | BagOdom]:
        reader = AnyReader([self.path], default_typestore=get_typestore(Stores.ROS2_HUMBLE))
        try:
            reader.open()
        except AnyReaderError as exc:
            raise BagFormatError(f"cannot open bag {self.path}: {exc}") from exc
        try:
            connections = self._selected(reader.connections)
            counts = {SCAN_TYPE: 0, ODOM_TYPE: 0}
            for conn, time_ns, raw in reader.messages(connections=connections):
                robot = self.robot_id or _topic_robot(conn.topic)
                bag_time_s = time_ns * 1e-9
                try:
                    msg = reader.deserialize(raw, conn.msgtype)
                    if conn.msgtype == SCAN_TYPE:
                        scan = scan_from_msg(msg, robot, counts[SCAN_TYPE])
                        yield BagScan(scan, conn.topic, bag_time_s)
                        counts[SCAN_TYPE] += 1
                    elif conn.msgtype == ODOM_TYPE:
                        odom = odom_from_msg(msg, robot, counts[ODOM_TYPE])
                        yield BagOdom(odom, conn.topic, bag_time_s)
                        counts[ODOM_TYPE] += 1
                    elif conn.msgtype in TF_TYPES:
                        for odom in self._tf_odometry(msg, robot, counts[ODOM_TYPE]):
                            yield BagOdom(odom, conn.topic, bag_time_s)
                            counts[ODOM_TYPE] += 1
                except (ScanError, ValueError) as exc:
                    self._report(f"{conn.topic} @ {bag_time_s:.9f} s: {exc}")
        finally:
            reader.close()

    def _tf_odometry(self, msg: Any, robot_id: str, seq: int) -> Iterator[Odometry]:
        for tf in msg.transforms:
            parent, child = _bare_frame(tf.header.frame_id), _bare_frame(tf.child_frame_id)
            if parent != self.odom_frame or child != self.base_frame:
                continue
            tr, q = tf.transform.translation, tf.transform.rotation
            pose = Pose2D(tr.x, tr.y, yaw_from_quaternion(q))
            yield Odometry(stamp_to_s(tf.header.stamp), pose, None, robot_id, seq)
            seq += 1

    def _report(self, reason: str) -> None:
        if self.strict:
            raise BagFormatError(f"{self.path}: {reason}")
        self.error_count += 1
        if len(self.errors) < MAX_RECORDED_ERRORS:
            self.errors.append(reason)


def read_bag(path: str | Path, **options: Any) -> Iterator[BagScan | BagOdom]:
    """Stream scans and odometry of a ROS 1 or ROS 2 bag in time order; options as `BagReader`."""
    return iter(BagReader(path, **options))
