"""bench.lidar: one `--lidar BEAMS,FOV_DEG,RANGE_M[,RATE_HZ[,BEARING_NOISE_DEG]]` for every
bench that simulates."""

import argparse

import pytest
from scanflow.sim import SimConfig

from bench.lidar import add_lidar_option, lidar_report, parse_lidar, sim_lidar_fields


def test_the_option_gives_the_simulator_s_fields_or_none() -> None:
    parser = argparse.ArgumentParser()
    add_lidar_option(parser)
    lidar = parser.parse_args(["--lidar", "181,180,80"]).lidar
    assert lidar == {"beams": 181, "fov_deg": 180.0, "range_max_m": 80.0}
    config = SimConfig(world="campus", **sim_lidar_fields(lidar))
    assert (config.beams, config.fov_deg, config.range_max_m) == (181, 180.0, 80.0)
    assert lidar_report(config) == {**lidar, "rate_hz": 10.0, "bearing_noise_deg": 0.0}
    assert sim_lidar_fields(parser.parse_args([]).lidar) == {}


def test_a_rate_and_a_bearing_noise_may_follow() -> None:
    """A Hokuyo UTM-30LX at 40 Hz; an RPLidar whose driver bins its samples (0.3 deg)."""
    config = SimConfig(**sim_lidar_fields(parse_lidar("1081,270,30,40")))
    assert (config.beams, config.rate_hz, config.bearing_noise_deg) == (1081, 40.0, 0.0)
    rplidar = parse_lidar("360,360,12,10,0.3")
    assert lidar_report(SimConfig(**sim_lidar_fields(rplidar))) == rplidar


@pytest.mark.parametrize(
    "text", ["181,180", "181,180,80,10,0.3,1", "many,180,80", "181.5,180,80", ""]
)
def test_bad_input_is_named(text: str) -> None:
    with pytest.raises(argparse.ArgumentTypeError, match="BEAMS,FOV_DEG,RANGE_M"):
        parse_lidar(text)
