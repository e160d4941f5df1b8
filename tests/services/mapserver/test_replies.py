"""The map server's replies: a region query's cells and bounds, the exported files."""

from __future__ import annotations

import io
import zipfile
from dataclasses import replace

import pytest
from scanflow.maps.occupancy import OccupancyGrid, OccupancyParams

from services.mapserver import replies
from services.mapserver.robot import RobotMap


def test_a_region_apart_from_the_map_has_no_cells_and_bad_bounds_are_named(new_robot, insert):
    robot = new_robot()
    robot.insert(insert(0))
    inside = replies.region(robot, (0.0, -1.0, 2.5, 1.5))
    assert inside.occupancy.size > 0
    for far in ((1000.0, 1000.0, 1001.0, 1001.0), (-900.0, -900.0, -899.0, -899.0),
                (1000.0, 0.0, 1001.0, 0.5)):
        assert replies.region(robot, far).occupancy.shape == (0, 0)
    with pytest.raises(ValueError, match="must be finite"):
        replies.region(robot, (float("nan"), 0.0, 1.0, 1.0))
    with pytest.raises(ValueError, match="x0 <= x1"):
        replies.region(robot, (2.0, 0.0, 1.0, 1.0))


def test_the_zip_export_is_the_yaml_and_pgm_exports_of_one_revision(new_robot, insert):
    robot = new_robot()
    robot.insert(insert(0))
    archive = zipfile.ZipFile(io.BytesIO(replies.image(robot, "zip").data))
    assert archive.read("r.yaml") == replies.image(robot, "yaml").data
    assert archive.read("r.pgm") == replies.image(robot, "pgm").data
    with pytest.raises(ValueError, match="png, pgm, yaml, zip or npz"):
        replies.image(robot, "tiff")


def test_the_yaml_names_the_pgm_of_a_robot_id_with_a_dot(insert) -> None:
    """`<id>.pgm` whole: written through a file path, 'r.1' lost its '.1' as a suffix."""
    robot = RobotMap("r.1", lambda: OccupancyGrid(OccupancyParams()))
    robot.insert(replace(insert(0), robot_id="r.1"))
    assert b"image: r.1.pgm\n" in replies.image(robot, "yaml").data
