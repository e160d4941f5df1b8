"""The simulated lidar a benchmark runs on, given as `--lidar BEAMS,FOV_DEG,RANGE_M` by every
bench that simulates (e.g. 181,180,80: an outdoor SICK; the simulator's own is 360,270,30)."""

from __future__ import annotations

import argparse

Lidar = tuple[int, float, float]  # beams, field of view (deg), maximum range (m)


def parse_lidar(text: str) -> Lidar:
    """'BEAMS,FOV_DEG,RANGE_M' -> (beams, fov deg, range m)."""
    try:
        beams, fov_deg, range_m = text.split(",")
        return int(beams), float(fov_deg), float(range_m)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(
            f"--lidar takes BEAMS,FOV_DEG,RANGE_M (e.g. 181,180,80), got {text!r}") from exc


def add_lidar_option(parser: argparse.ArgumentParser) -> None:
    """`--lidar`, default None: the simulator's own lidar."""
    parser.add_argument("--lidar", type=parse_lidar, default=None,
                        help="simulated lidar BEAMS,FOV_DEG,RANGE_M (default: the simulator's "
                        "360,270,30)")


def sim_lidar_fields(lidar: Lidar | None) -> dict[str, float]:
    """`SimConfig` fields for `lidar` (none: its defaults)."""
    return dict(zip(("beams", "fov_deg", "range_max_m"), lidar, strict=True)) if lidar else {}
