"""The simulated lidar a benchmark runs on, given as `--lidar BEAMS,FOV_DEG,RANGE_M[,RATE_HZ[,
BEARING_NOISE_DEG]]` by every bench that simulates (e.g. 181,180,80: an outdoor SICK;
1081,270,30,40: a Hokuyo UTM-30LX; 360,360,12,10,0.3: an RPLidar whose driver bins its samples;
the simulator's own is 360,270,30,10,0)."""

from __future__ import annotations

import argparse
from typing import TypedDict

from scanflow.sim import SimConfig


class Lidar(TypedDict, total=False):
    """SimConfig's lidar fields: `parse_lidar` gives the first three, maybe the rest."""

    beams: int
    fov_deg: float
    range_max_m: float
    rate_hz: float
    bearing_noise_deg: float


LIDAR_FIELDS = ("beams", "fov_deg", "range_max_m", "rate_hz", "bearing_noise_deg")


def parse_lidar(text: str) -> Lidar:
    """'BEAMS,FOV_DEG,RANGE_M[,RATE_HZ[,BEARING_NOISE_DEG]]' -> SimConfig's lidar fields."""
    try:
        values = [float(v) for v in text.split(",")]
        if not 3 <= len(values) <= len(LIDAR_FIELDS) or values[0] != int(values[0]):
            raise ValueError(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(
            "--lidar takes BEAMS,FOV_DEG,RANGE_M[,RATE_HZ[,BEARING_NOISE_DEG]] (e.g. 181,180,80 "
            f"or 360,360,12,10,0.3), got {text!r}") from exc
    fields: Lidar = {"beams": int(values[0]), "fov_deg": values[1], "range_max_m": values[2]}
    if len(values) > 3:
        fields["rate_hz"] = values[3]
    if len(values) > 4:
        fields["bearing_noise_deg"] = values[4]
    return fields


def add_lidar_option(parser: argparse.ArgumentParser) -> None:
    """`--lidar`, default None: the simulator's own lidar."""
    parser.add_argument("--lidar", type=parse_lidar, default=None,
                        help="simulated lidar BEAMS,FOV_DEG,RANGE_M[,RATE_HZ[,BEARING_NOISE_DEG]] "
                        "(default: the simulator's 360,270,30,10,0)")


def sim_lidar_fields(lidar: Lidar | None) -> Lidar:
    """`SimConfig` fields for `lidar` (none: its defaults)."""
    return lidar.copy() if lidar else {}


def lidar_report(config: SimConfig) -> dict[str, float]:
    """The simulated lidar a report was measured with: every field `--lidar` sets."""
    return {name: getattr(config, name) for name in LIDAR_FIELDS}
