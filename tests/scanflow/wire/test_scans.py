"""Scan and deskewed scan messages: exact bits, field checks and errors naming the field."""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import numpy as np
import pytest
from scanflow import wire
from scanflow.geometry import Pose2D
from scanflow.scan import LaserScan, Odometry, ScanError


def test_nan_ranges_keep_their_exact_bits() -> None:
    bits = np.array([0x7FC00000, 0x7F800001, 0xFFC12345, 0x3F800000], dtype=np.uint32)
    scan = LaserScan(bits.view(np.float32), 0.0, 0.1)
    decoded = wire.ScanMessage.decode(wire.ScanMessage(scan).encode()).scan
    assert decoded.ranges_m.view(np.uint32).tolist() == bits.tolist()
    assert decoded.valid_mask.tolist() == [False, False, False, True]
    assert decoded.dropped_count == 3


@pytest.mark.parametrize(
    ("changes", "pattern"),
    [
        ({"stamp_s": ...}, r"scan\.stamp_s: missing"),
        ({"seq": "7"}, r"scan\.seq: expected an integer, got str"),
        ({"seq": True}, r"scan\.seq: expected an integer, got bool"),
        ({"seq": -1}, "seq must be >= 0"),
        ({"ranges_m": [1.0, 2.0]}, r"scan\.ranges_m: expected a map"),
        (
            {"ranges_m": {"d": ">f4", "s": [1], "b": b"abcd"}},
            r"ranges_m\.d: dtype '>f4' is not allowed",
        ),
        ({"ranges_m": {"d": "<f8", "s": [1], "b": bytes(8)}}, r"ranges_m\.d: expected dtype '<f4'"),
        ({"ranges_m": {"d": "<f4", "s": [3], "b": bytes(8)}}, r"ranges_m\.b: 8 bytes do not fit"),
        ({"ranges_m": {"d": "<f4", "s": [-1], "b": b""}}, r"ranges_m\.s: sizes must be integers"),
        ({"ranges_m": {"d": "<f4", "s": [2**64 - 1], "b": b""}}, r"ranges_m\.s: sizes must be"),
        ({"ranges_m": {"d": "<f4", "s": [True], "b": b""}}, r"ranges_m\.s: sizes must be"),
        ({"ranges_m": {"d": "<f4", "s": [1] * 5, "b": bytes(4)}}, r"ranges_m\.s: expected a list"),
        ({"stamp_s": math.nan}, "stamp_s must be finite"),
        ({"range_max_m": -1.0}, r"range_max_m \(-1.0\) must exceed"),
    ],
)
def test_bad_scan_fields_name_the_field(
    changes: dict[str, Any],
    pattern: str,
    payload: Callable[..., bytes],
    scan_message: wire.ScanMessage,
) -> None:
    with pytest.raises(wire.SchemaError, match=pattern):
        wire.ScanMessage.decode(payload(scan_message, **changes))


def test_deskewed_points_keep_every_float64_bit_and_refuse_float32(
    payload: Callable[..., bytes]
) -> None:
    points = np.array([[0.1, 1.0 / 3.0], [math.pi, -2.0 / 7.0]])  # not representable in float32
    misses = points[::-1] * 300.0
    msg = wire.DeskewedScanMessage("r", 0, 0.0, points, "odometry", False, 4, 2, misses)
    decoded = wire.DeskewedScanMessage.decode(msg.encode())
    for sent, got in ((points, decoded.points), (misses, decoded.no_return_points)):
        assert got.dtype == np.float64
        assert got.tobytes() == sent.tobytes()
    for name in ("points", "no_return_points"):
        narrow = {name: wire.codec.encode_array(points, "<f4")}
        with pytest.raises(wire.SchemaError, match=rf"{name}\.d: expected dtype '<f8', got '<f4'"):
            wire.decode_any(payload(msg, **narrow))


def test_deskewed_no_return_points_default_to_none_and_fit_the_beam_count() -> None:
    msg = wire.DeskewedScanMessage("r", 0, 0.0, np.zeros((2, 2)), "none", True, 3, 1)
    assert msg.no_return_points.shape == (0, 2)
    full = wire.DeskewedScanMessage("r", 0, 0.0, np.zeros((2, 2)), "none", True, 3, 1, [[9, 0]])
    assert wire.DeskewedScanMessage.decode(full.encode()).no_return_points.tolist() == [[9, 0]]


def test_deskewed_odom_pose_is_optional_and_must_be_a_pose(payload: Callable[..., bytes]) -> None:
    msg = wire.DeskewedScanMessage("r", 0, 0.0, np.zeros((1, 2)), "none", True, 1, 0)
    assert wire.DeskewedScanMessage.decode(msg.encode()).odom_pose is None
    with_pose = wire.DeskewedScanMessage(
        "r", 0, 0.0, np.zeros((1, 2)), "none", True, 1, 0, odom_pose=Pose2D(1.0, 2.0, 0.5)
    )
    assert wire.DeskewedScanMessage.decode(with_pose.encode()).odom_pose == Pose2D(1.0, 2.0, 0.5)
    with pytest.raises(wire.MessageError, match="odom_pose must be a Pose2D, got tuple"):
        wire.DeskewedScanMessage(
            "r", 0, 0.0, np.zeros((1, 2)), "none", True, 1, 0, odom_pose=(1.0, 2.0, 0.5)
        )
    with pytest.raises(wire.SchemaError, match="odom_pose"):
        wire.decode_any(payload(msg, odom_pose=[1.0, "x", 0.0]))


def test_scan_errors_surface_as_chained_decode_errors(
    payload: Callable[..., bytes], scan_message: wire.ScanMessage
) -> None:
    data = payload(scan_message, beam_time_offsets_s={"d": "<f8", "s": [2], "b": bytes(16)})
    with pytest.raises(wire.SchemaError, match="beam_time_offsets_s has shape") as info:
        wire.decode_any(data)
    assert isinstance(info.value.__cause__, ScanError)


def test_odometry_beyond_max_position_is_malformed(payload: Callable[..., bytes]) -> None:
    """A glitching odometry driver's 1e308 m went into the deskewer's buffer: the differences
    of two such poses overflowed, and every scan it covered was lost to a failed publish."""
    odom = wire.OdometryMessage(Odometry(1.0, Pose2D(), robot_id="r"))
    with pytest.raises(wire.DecodeError, match=r"odom: pose must lie within \+-1e\+09 m"):
        wire.decode_any(payload(odom, pose=[1e308, 0.0, 0.0]))  # (Odometry's own bound)
    with pytest.raises(wire.DecodeError, match=r"odom\.pose \(2000000\.0, 0\.0\) m is beyond"):
        wire.decode_any(payload(odom, pose=[2e6, 0.0, 0.0]))
    wire.OdometryMessage(Odometry(1.0, Pose2D(0.0, -wire.MAX_POSITION_M, 0.0), robot_id="r"))
