"""What ingest publishes: a time-ordered stream of scans and odometry from a log or the simulator.

Tests and benchmarks feed the in-process front end from the same functions, so both sides of
a comparison see exactly the same input.
"""

from __future__ import annotations

import dataclasses
import itertools
from collections import defaultdict
from collections.abc import Callable, Iterable, Iterator
from pathlib import Path

from scanflow import keys
from scanflow.geometry import IDENTITY, Pose2D
from scanflow.scan import LaserScan, Odometry
from scanflow.wire import OdometryMessage, ScanMessage

Event = LaserScan | Odometry


def bus_message(event: Event, prefix: str = keys.DEFAULT_PREFIX) -> tuple[str, bytes]:
    """The key and payload `event` is published as: a scan on its robot's raw scan key, an
    odometry sample on its odom key (ingest's, and any robot client's, wire form)."""
    if isinstance(event, LaserScan):
        return keys.raw_scan(event.robot_id, prefix), ScanMessage(event).encode()
    return keys.odom(event.robot_id, prefix), OdometryMessage(event).encode()


def sim_events(
    duration_s: float, seed: int, robot_id: str, mount: Pose2D = IDENTITY,
    world: str = "rooms", odom_scale_error: float = 0.01, odom_yaw_noise: float = 0.002,
) -> Iterator[Event]:
    """The built-in simulator (its lidar at `mount` on the robot, in `world`, with wheel
    odometry off by `odom_scale_error` and `odom_yaw_noise` in heading): each frame's
    odometry samples, then its (distorted) scan."""
    from scanflow.sim import SimConfig, simulate

    config = SimConfig(
        world=world, duration_s=duration_s, seed=seed, robot_id=robot_id, mount=mount,
        odom_scale_error=odom_scale_error, odom_yaw_noise=odom_yaw_noise,
    )
    for frame in simulate(config):
        yield from frame.odometry
        yield frame.scan


def log_events(
    path: str | Path, robot_id: str, on_error: Callable[[str], None] | None = None
) -> Iterator[Event]:
    """A recorded log. CARMEN logs give keyframes with their continuous wheel odometry
    (the raw ODOM stream re-anchors at every laser record, see the data README); ROS bags
    give their scan and odometry messages in bag order. Each record skipped as unreadable
    is passed to `on_error` (see `open_log`); a bag that breaks off raises BagFormatError."""
    from scanflow.io.carmen import load_keyframes
    from scanflow.io.detect import carmen_error_handler, detect_format, open_log, record_payload

    if detect_format(path) == "carmen":
        frames = load_keyframes(path, robot_id=robot_id, on_error=carmen_error_handler(on_error))
        for frame in frames:
            yield Odometry(stamp_s=frame.scan.stamp_s, pose=frame.odom_pose, robot_id=robot_id)
            yield frame.scan
        return
    for record in open_log(path, robot_id=robot_id, on_error=on_error):
        yield record_payload(record)


def numbered(events: Iterable[Event]) -> Iterator[Event]:
    """Renumber `seq` per robot and per kind from 0, as published on the bus."""
    counters: dict[tuple[str, type], itertools.count[int]] = defaultdict(itertools.count)
    for event in events:
        yield dataclasses.replace(event, seq=next(counters[(event.robot_id, type(event))]))


def mounted(events: Iterable[Event], mount: Pose2D) -> Iterator[Event]:
    """Every scan with its lidar declared at `mount` on the robot (odometry as it is)."""
    for event in events:
        yield dataclasses.replace(event, mount=mount) if isinstance(event, LaserScan) else event


def limited(events: Iterable[Event], max_scans: int | None) -> Iterator[Event]:
    """Stop after `max_scans` scans (None: no limit), keeping the odometry before each."""
    scans = 0
    for event in events:
        if max_scans is not None and scans >= max_scans:
            return
        if isinstance(event, LaserScan):
            scans += 1
        yield event


def source_events(
    log: str | None,
    robot_id: str,
    sim_duration_s: float,
    sim_seed: int,
    limit: int | None,
    mount: Pose2D | None = None,
    *,
    sim_world: str = "rooms",
    sim_odom_scale_error: float = 0.01,
    sim_odom_yaw_noise: float = 0.002,
    on_error: Callable[[str], None] | None = None,
) -> Iterator[Event]:
    """The numbered, limited stream of one replay of the configured source; `mount` (when
    given) places the simulator's lidar, or overrides what a log says about its lidar;
    `on_error` hears of a log's unreadable records (see `log_events`)."""
    if log is None:
        raw = sim_events(
            sim_duration_s, sim_seed, robot_id, mount or IDENTITY, sim_world,
            sim_odom_scale_error, sim_odom_yaw_noise,
        )
    else:
        raw = log_events(log, robot_id, on_error)
        raw = raw if mount is None else mounted(raw, mount)
    return numbered(limited(raw, limit))
