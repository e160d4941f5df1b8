"""bench.lidar: one `--lidar BEAMS,FOV_DEG,RANGE_M` for every bench that simulates."""

import argparse

import pytest
from scanflow.sim import SimConfig

from bench.lidar import add_lidar_option, parse_lidar, sim_lidar_fields


def test_the_option_gives_the_simulator_s_fields_or_none() -> None:
    parser = argparse.ArgumentParser()
    add_lidar_option(parser)
    lidar = parser.parse_args(["--lidar", "181,180,80"]).lidar
    assert lidar == (181, 180.0, 80.0)
    config = SimConfig(world="campus", **sim_lidar_fields(lidar))
    assert (config.beams, config.fov_deg, config.range_max_m) == (181, 180.0, 80.0)
    assert sim_lidar_fields(parser.parse_args([]).lidar) == {}


@pytest.mark.parametrize("text", ["181,180", "181,180,80,1", "many,180,80", ""])
def test_bad_input_is_named(text: str) -> None:
    with pytest.raises(argparse.ArgumentTypeError, match="BEAMS,FOV_DEG,RANGE_M"):
        parse_lidar(text)
