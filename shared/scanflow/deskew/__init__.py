"""Motion compensation (deskewing) of rotating 2D lidar scans.

`deskew(scan, sources, reference)` re-expresses every beam in the frame of one reference pose,
with poses from an `OdometryBuffer`, a `ConstantVelocityModel`, or none; the result says which.
The result carries the valid beams as `points` and the no-return beams as `no_return_points`.
"""

from scanflow.deskew.buffer import OdometryBuffer
from scanflow.deskew.compensate import (
    DEFAULT_REFERENCE,
    NO_RETURN_RANGE_M,
    REFERENCES,
    DeskewResult,
    Reference,
    deskew,
    motion_free_reason,
)
from scanflow.deskew.source import DeskewError, PoseSource, choose_source
from scanflow.deskew.velocity import ConstantVelocityModel

__all__ = [
    "DEFAULT_REFERENCE",
    "NO_RETURN_RANGE_M",
    "REFERENCES",
    "ConstantVelocityModel",
    "DeskewError",
    "DeskewResult",
    "OdometryBuffer",
    "PoseSource",
    "Reference",
    "choose_source",
    "deskew",
    "motion_free_reason",
]
