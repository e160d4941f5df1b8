"""Estimate messages: match results carried, plain option values, an operator's pose bound."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import pytest
from scanflow import wire
from scanflow.geometry import Pose2D


def test_message_helpers_carry_match_results() -> None:
    from scanflow.matching.api import MatchStatus, failed

    result = failed("icp", MatchStatus.TOO_FEW_POINTS, Pose2D(1, 2, 0.5), "only 3 points")
    response = wire.MatchResponse.decode(wire.MatchResponse.from_result(result).encode())
    assert (response.status, response.message, response.ok) == (
        "too_few_points",
        "only 3 points",
        False,
    )
    assert np.isinf(np.diag(response.covariance)).all()
    estimate = wire.PoseEstimateMessage.from_result(result, "r", 7, 12.5)
    assert (estimate.seq, estimate.status, estimate.pose) == (7, "too_few_points", result.pose)
    error = wire.MatchResponse.from_error("no map for robot 'x'", "ndt")
    assert (error.ok, error.status, error.error) == (False, "error", "no map for robot 'x'")


def test_numpy_scalars_become_plain_python_values() -> None:
    request = wire.MatchRequest(
        "icp", np.zeros((1, 2)), wire.MapRef("r"), options={"k": np.float32(0.5), "n": np.int64(3)}
    )
    stats = wire.ServiceStatsMessage(
        "s", "i", np.float64(1.0), {"c": np.uint8(2)}, {"g": np.int16(4)}
    )
    assert wire.MatchRequest.decode(request.encode()).options == {"k": 0.5, "n": 3}
    decoded = wire.ServiceStatsMessage.decode(stats.encode())
    assert (decoded.counters, decoded.gauges) == ({"c": 2}, {"g": 4.0})


def test_an_operators_pose_beyond_max_position_is_malformed(payload: Callable[..., bytes]) -> None:
    """HTTP bounds it the same; 1e300 m reached the tracker and broke its first scan."""
    far = wire.InitialPoseMessage("r", Pose2D(0.0, 0.0, 0.0))
    with pytest.raises(wire.DecodeError, match="beyond"):
        wire.decode_any(payload(far, pose=[1e300, 0.0, 0.0]))
    with pytest.raises(wire.MessageError, match="beyond"):
        wire.InitialPoseMessage("r", Pose2D(0.0, -2e6, 0.0))
    wire.InitialPoseMessage("r", Pose2D(wire.MAX_POSITION_M, 0.0, 0.0))


def test_an_error_response_quoting_a_long_input_still_decodes() -> None:
    from scanflow.wire.codec import MAX_ERROR_CHARS, MAX_STR_BYTES

    error = f"MatchInputError: unknown method {'x' * MAX_STR_BYTES!r}"
    response = wire.MatchResponse.decode(wire.MatchResponse.from_error(error, "icp").encode())
    assert response.error.startswith("MatchInputError: unknown method 'xxx")
    assert len(response.error) <= MAX_ERROR_CHARS + 3
    assert len(response.message) <= MAX_ERROR_CHARS + 3
