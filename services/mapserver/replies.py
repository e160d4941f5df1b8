"""What the map server's queryables answer: metadata, exported images, regions, trajectory,
and what a restarted matcher resumes from (with loop closure, the kept keyframes too)."""

from __future__ import annotations

import math
import time

import numpy as np
from scanflow.maps.export import map_file_bytes, npz_arrays, npz_bytes
from scanflow.maps.grid import CellBox
from scanflow.wire import (
    MAX_POSITION_M,
    MapImageMessage,
    MapMetaMessage,
    MapRegionMessage,
    ResumeMessage,
    TrajectoryMessage,
)
from scanflow.wire.maps import is_map_image_format

from services.mapserver.robot import RobotMap


def meta(robot: RobotMap) -> MapMetaMessage:
    """The robot's map geometry and revision, stamped with the wall clock now."""
    grid = robot.map.grid
    return MapMetaMessage.from_spec(robot.robot_id, grid.spec, robot.map.revision, time.time())


def image(robot: RobotMap, fmt: str) -> MapImageMessage:
    """The map exported by the library's writers: png, pgm or yaml (map_server), zip (that
    yaml and pgm together), npz (native), all built in memory (a resume asks for the npz under
    the map server's lock)."""
    grid = robot.map.grid
    if not is_map_image_format(fmt):
        raise ValueError(f"format must be png, pgm, yaml, zip or npz, got {fmt!r}")
    if fmt == "npz":
        data = npz_bytes(npz_arrays(grid))
    else:
        data = map_file_bytes(grid, fmt, robot.robot_id)
    return MapImageMessage(robot.robot_id, robot.map.revision, fmt, data)


def region(robot: RobotMap, bounds_m: tuple[float, float, float, float] | None) -> MapRegionMessage:
    """Occupancy (-1 unknown, 0..100) of the cells inside world box (x0, y0, x1, y1), or all."""
    grid = robot.map.grid
    head = meta(robot)
    extent = grid.extent
    if extent is None:
        return MapRegionMessage(head, 0, 0, np.zeros((0, 0), dtype=np.int8))
    box = extent
    if bounds_m is not None:
        x0, y0, x1, y1 = bounds_m
        if not all(math.isfinite(b) and abs(b) <= MAX_POSITION_M for b in bounds_m):
            raise ValueError(f"region bounds must be finite, within +-{MAX_POSITION_M:g} m, got "
                             f"{bounds_m}")
        if not (x0 <= x1 and y0 <= y1):
            raise ValueError(f"region bounds must have x0 <= x1 and y0 <= y1, got {bounds_m}")
        corners = grid.world_to_cells(np.array([[x0, y0], [x1, y1]]))
        box = CellBox.around(corners).intersection(extent)
        if box.is_empty or not extent.contains_box(box):  # apart from the map: no cells
            return MapRegionMessage(head, 0, 0, np.zeros((0, 0), dtype=np.int8))
    window = box.slices_in(extent)
    return MapRegionMessage(
        head, box.row0 - extent.row0, box.col0 - extent.col0, grid.to_int8()[window]
    )


def trajectory(robot: RobotMap) -> TrajectoryMessage:
    """The robot's whole trajectory as kept here: stamps and (N, 3) poses."""
    return TrajectoryMessage(robot.robot_id, robot.trajectory.stamps_s, robot.trajectory.poses)


def resume(robot: RobotMap) -> ResumeMessage:
    """The map (npz), the path and the kept keyframes (None when this server keeps none: loop
    closure is off here), all of one instant: the caller holds the map server's lock."""
    kept = None if robot.keyframes is None else robot.keyframes.message(robot.robot_id)
    return ResumeMessage(
        robot.robot_id, robot.map.revision, image(robot, "npz").data,
        robot.trajectory.stamps_s, robot.trajectory.poses, kept, robot.odom_at_path_end(),
        robot.run,
    )
