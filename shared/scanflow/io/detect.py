"""Tell a log's format from its content and open the matching reader.

ROS 1 bags start with `#ROSBAG V2.0`; ROS 2 bags are directories holding `metadata.yaml`;
anything else readable (plain or gzip text) is treated as a CARMEN log.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Literal

from scanflow.io.carmen import CarmenLaser, CarmenOdom, CarmenReader
from scanflow.io.rosbag import BagOdom, BagReader, BagScan
from scanflow.scan import LaserScan, Odometry

LogFormat = Literal["carmen", "rosbag1", "rosbag2"]
ROSBAG1_MAGIC = b"#ROSBAG V2.0"


def detect_format(path: str | Path) -> LogFormat:
    """The format of the log at `path`; raises FileNotFoundError when there is nothing there."""
    p = Path(path)
    if p.is_dir():
        if (p / "metadata.yaml").is_file():
            return "rosbag2"
        raise ValueError(f"path {p} is a directory without metadata.yaml, not a ROS 2 bag")
    if not p.is_file():
        raise FileNotFoundError(f"no log at path {p}")
    with p.open("rb") as f:
        head = f.read(len(ROSBAG1_MAGIC))
    return "rosbag1" if head == ROSBAG1_MAGIC else "carmen"


def open_log(
    path: str | Path,
    *,
    robot_id: str | None = None,
    strict: bool = False,
    on_error: Callable[[str], None] | None = None,
) -> CarmenReader | BagReader:
    """A reader for any supported log; iterate it, then read its `errors` / `error_count`.
    `on_error` hears of each record skipped as it happens, as "path:line: reason" (CARMEN)
    or "path: reason" (bags)."""
    if detect_format(path) == "carmen":
        return CarmenReader(path, robot_id=robot_id or "robot", strict=strict,
                            on_error=carmen_error_handler(on_error))
    return BagReader(path, robot_id=robot_id, strict=strict, on_error=on_error)


def carmen_error_handler(
    on_error: Callable[[str], None] | None,
) -> Callable[[str, int, str], None] | None:
    """The CARMEN readers' (path, line, reason) callback that hands `on_error` one message."""
    if on_error is None:
        return None
    return lambda path, line_no, reason: on_error(f"{path}:{line_no}: {reason}")


def record_payload(record: CarmenLaser | CarmenOdom | BagScan | BagOdom) -> LaserScan | Odometry:
    """The scan or odometry sample a reader record carries, whatever the format."""
    if isinstance(record, CarmenLaser | BagScan):
        return record.scan
    return record.odom
