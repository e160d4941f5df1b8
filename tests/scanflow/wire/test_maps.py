"""Map messages: grid geometry, map insert fields and keyframes split back into scans."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import pytest
from scanflow import wire
from scanflow.geometry import Pose2D
from scanflow.wire.maps import is_map_image_format


def test_map_messages_expose_grid_geometry() -> None:
    meta = wire.MapMetaMessage("r", 0.5, -2.0, 1.0, 10, 20, 3, 0.0)
    region = wire.MapRegionMessage(meta, 2, 4, np.zeros((3, 5), np.int8))
    win = region.window_spec
    assert (win.origin_x_m, win.origin_y_m, win.rows, win.cols) == (0.0, 2.0, 3, 5)
    assert wire.MapMetaMessage.from_spec("r", meta.spec, 3, 0.0).spec == meta.spec


def test_map_insert_points_must_be_finite_float64_rows_and_the_pose_a_pose(
    payload: Callable[..., bytes]
) -> None:
    points = np.array([[1.0, 2.0], [3.0, 4.0]])
    msg = wire.MapInsertMessage("r", 3, 2.0, Pose2D(1, 2, 3), points, np.zeros((0, 2)))
    assert wire.MapInsertMessage.decode(msg.encode()).points.tobytes() == points.tobytes()
    with pytest.raises(wire.MessageError, match="pose must be a Pose2D"):
        wire.MapInsertMessage("r", 3, 2.0, (1, 2, 3), points, np.zeros((0, 2)))
    with pytest.raises(wire.MessageError, match="no_return_points"):
        wire.MapInsertMessage("r", 3, 2.0, Pose2D(), points, np.zeros((2, 3)))
    with pytest.raises(wire.SchemaError, match="points contains non-finite"):
        wire.decode_any(
            payload(msg, points=wire.codec.encode_array(np.full((1, 2), np.nan), "<f8"))
        )


def test_map_insert_previous_seq_comes_before_its_seq(payload: Callable[..., bytes]) -> None:
    msg = wire.MapInsertMessage("r", 3, 2.0, Pose2D(), np.zeros((0, 2)), np.zeros((0, 2)))
    assert wire.MapInsertMessage.decode(msg.encode()).previous_seq is None
    for bad in (3, 7):
        with pytest.raises(wire.SchemaError, match="previous_seq must be below seq 3"):
            wire.decode_any(payload(msg, previous_seq=bad))
    with pytest.raises(wire.SchemaError, match="previous_seq"):
        wire.decode_any(payload(msg, previous_seq=-1))


def test_keyframes_split_back_into_their_scans() -> None:
    msg = wire.KeyframesMessage(
        "r", np.array([1, 4, 9]), np.array([0.1, 0.4, 0.9]), np.zeros((3, 3)), np.zeros((3, 3)),
        np.array([2, 0, 1]), np.arange(6.0).reshape(3, 2), np.array([0, 1, 0]),
        np.array([[7.0, 8.0]]),
    )
    (h0, m0), (h1, m1), (h2, m2) = wire.KeyframesMessage.decode(msg.encode()).scans()
    assert h0.tolist() == [[0, 1], [2, 3]] and h1.shape == (0, 2) and h2.tolist() == [[4, 5]]
    assert m0.shape == (0, 2) and m1.tolist() == [[7, 8]] and m2.shape == (0, 2)
    assert wire.KeyframesMessage(
        "r", np.zeros(0, np.int64), np.zeros(0), np.zeros((0, 3)), np.zeros((0, 3)),
        np.zeros(0, np.int64), np.zeros((0, 2)), np.zeros(0, np.int64), np.zeros((0, 2)),
    ).scans() == []


def test_keyframe_counts_that_wrap_around_int64_are_refused(payload: Callable[..., bytes]) -> None:
    """Four counts of 2**62 add up to 2**64, 0 in int64: they must not pass for the 0 rows."""
    none, n = np.zeros((0, 2)), 4
    msg = wire.KeyframesMessage(
        "r", np.arange(n), np.zeros(n), np.zeros((n, 3)), np.zeros((n, 3)),
        np.zeros(n, np.int64), none, np.zeros(n, np.int64), none,
    )  # fmt: skip
    wrapping = wire.codec.encode_array(np.full(n, 2**62), "<i8")
    with pytest.raises(wire.SchemaError, match="hit_counts must be >= 0 and add up"):
        wire.decode_any(payload(msg, hit_counts=wrapping))
    with pytest.raises(wire.MessageError, match="miss_counts must be >= 0 and add up"):
        wire.KeyframesMessage(
            "r", np.arange(n), np.zeros(n), np.zeros((n, 3)), np.zeros((n, 3)),
            np.zeros(n, np.int64), none, np.full(n, 2**62), none,
        )  # fmt: skip


def test_a_map_image_format_is_one_the_message_carries() -> None:
    assert all(is_map_image_format(fmt) for fmt in wire.MAP_IMAGE_FORMATS)
    assert not is_map_image_format("jpeg") and not is_map_image_format("")
