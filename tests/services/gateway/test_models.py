"""models.py: the API's request and response models (limits, NaN, unknown fields, round trips)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from pydantic import ValidationError
from scanflow.geometry import Pose2D
from scanflow.maps.grid import GridSpec
from scanflow.wire import MapMetaMessage, MatchResponse

from services.gateway.models import (
    COORD_LIMIT_M,
    MapMetaOut,
    MatchIn,
    MatchOut,
    OdometryIn,
    PoseIn,
    PoseOut,
    ScanIn,
    matrix_out,
)

from .conftest import INGEST_SCAN, estimate


def refusal(model: type, data: dict) -> str:
    """The ValidationError text of `data` against `model` (the test fails if it is accepted)."""
    with pytest.raises(ValidationError) as info:
        model.model_validate(data)
    return str(info.value)


@pytest.mark.parametrize(
    ("model", "data", "field"),
    [
        (PoseIn, {"x_m": 1.0, "z_m": 0.0}, "z_m"),
        (ScanIn, {**INGEST_SCAN, "colour": "red"}, "colour"),
        (OdometryIn, {"stamp_s": 1.0, "pose": {}, "velocity": {"vz_mps": 1.0}}, "vz_mps"),
        (MatchIn, {"source": INGEST_SCAN, "robot_id": "r1", "extra": 1}, "extra"),
    ],
)
def test_unknown_fields_are_refused_by_name(model, data, field):
    text = refusal(model, data)
    assert field in text and "xtra" in text  # pydantic's "Extra inputs are not permitted"


@pytest.mark.parametrize("value", [math.nan, math.inf, -math.inf])
def test_nan_and_infinity_are_refused_naming_the_field(value):
    assert "theta_rad" in refusal(PoseIn, {"theta_rad": value})
    assert "angle_min_rad" in refusal(ScanIn, {**INGEST_SCAN, "angle_min_rad": value})
    options = {"source": INGEST_SCAN, "robot_id": "r1", "options": {"max_step_m": value}}
    assert "max_step_m" in refusal(MatchIn, options)


@pytest.mark.parametrize(
    ("model", "data", "field"),
    [
        (PoseIn, {"x_m": COORD_LIMIT_M * 1.01}, "x_m"),
        (PoseIn, {"theta_rad": 101.0}, "theta_rad"),
        (ScanIn, {**INGEST_SCAN, "ranges_m": []}, "ranges_m"),
        (ScanIn, {**INGEST_SCAN, "angle_increment_rad": 1.5}, "angle_increment_rad"),
        (ScanIn, {**INGEST_SCAN, "scan_duration_s": 11.0}, "scan_duration_s"),
        (ScanIn, {**INGEST_SCAN, "seq": -1}, "seq"),
        (ScanIn, {**INGEST_SCAN, "mount": {"y_m": -250.0}}, "mount.y_m"),
        (ScanIn, {**INGEST_SCAN, "intensities": [1.0]}, "intensities has 1 values"),
        (ScanIn, {**INGEST_SCAN, "range_min_m": 5.0, "range_max_m": 5.0}, "must exceed"),
        (OdometryIn, {"stamp_s": -1.0, "pose": {}}, "stamp_s"),
        (OdometryIn, {"stamp_s": 1.0, "pose": {}, "velocity": {"vx_mps": 101}}, "vx_mps"),
        (MatchIn, {"source": INGEST_SCAN}, "exactly one of target"),
        (MatchIn, {"source": INGEST_SCAN, "target": INGEST_SCAN, "robot_id": "r1"},
         "exactly one of target"),
        (MatchIn, {"source": INGEST_SCAN, "robot_id": "a/b"}, "robot_id"),
        (MatchIn, {"source": INGEST_SCAN, "robot_id": "stats"}, "reserved"),
        (MatchIn, {"source": INGEST_SCAN, "robot_id": "r1", "options": {"a": [1]}}, "options"),
    ],
)
def test_values_out_of_their_range_are_refused_naming_them(model, data, field):
    assert field in refusal(model, data)


def test_a_scans_null_ranges_become_masked_beams_and_its_mount_travels():
    body = ScanIn.model_validate({**INGEST_SCAN, "ranges_m": [1.0, None, 2.0],
                                  "mount": {"x_m": 0.2, "theta_rad": 0.1}})
    scan = body.to_scan("r9", 12)
    assert (scan.robot_id, scan.seq, scan.valid_count) == ("r9", 12, 2)
    assert math.isnan(scan.ranges_m[1]) and scan.ranges_m[2] == 2.0
    assert scan.mount == Pose2D(0.2, 0.0, 0.1)
    assert ScanIn.model_validate(INGEST_SCAN).to_scan("r9", 0).mount == Pose2D()


def test_odometry_keeps_its_velocity_or_none():
    moving = OdometryIn.model_validate(
        {"stamp_s": 2.0, "pose": {"x_m": 1.0}, "velocity": {"vx_mps": 0.5, "omega_radps": 0.1}}
    ).to_odometry("r1", 3)
    assert (moving.robot_id, moving.seq, moving.stamp_s) == ("r1", 3, 2.0)
    assert moving.pose == Pose2D(1.0, 0.0, 0.0) and moving.velocity == (0.5, 0.0, 0.1)
    still = OdometryIn.model_validate({"stamp_s": 2.0, "pose": {}}).to_odometry("r1", 4)
    assert still.velocity is None


finite = st.floats(-COORD_LIMIT_M, COORD_LIMIT_M, allow_nan=False)
angles = st.floats(-100.0, 100.0, allow_nan=False)


@settings(max_examples=60, deadline=None)
@given(x=finite, y=finite, theta=angles)
def test_a_pose_survives_a_json_round_trip(x, y, theta):
    pose = PoseIn(x_m=x, y_m=y, theta_rad=theta)
    assert PoseIn.model_validate_json(pose.model_dump_json()) == pose
    assert pose.to_pose() == Pose2D(x, y, theta)


@settings(max_examples=40, deadline=None)
@given(ranges=st.lists(st.none() | st.floats(0.0, 100.0, width=32), min_size=1, max_size=40))
def test_a_scan_survives_a_json_round_trip(ranges):
    scan = ScanIn(ranges_m=ranges, angle_min_rad=-1.0, angle_increment_rad=0.01)
    again = ScanIn.model_validate_json(scan.model_dump_json())
    assert again == scan
    masked = np.isnan(again.to_scan("r", 0).ranges_m)
    assert masked.tolist() == [r is None for r in ranges]


def test_matrix_out_turns_non_finite_entries_into_null():
    values = np.diag([1.0, math.inf, -math.inf])
    values[0, 1] = math.nan
    assert matrix_out(values) == [[1.0, None, 0.0], [0.0, None, 0.0], [0.0, 0.0, None]]


def test_a_pose_out_of_an_estimate_keeps_its_correction_unless_interpolated():
    failed = estimate("r1", 7, 3.0, 1.0, 2.0, 0.5, status="lost")
    out = PoseOut.from_estimate(failed)
    assert (out.seq, out.stamp_s, out.x_m, out.status, out.interpolated) == (7, 3.0, 1.0, "lost",
                                                                            False)
    assert [out.covariance[i][i] for i in range(3)] == [None] * 3  # infinite: no information
    assert out.covariance[0][1] == 0.0 and out.map_correction is None
    redrawn = estimate("r1", 8, 4.0, 1.0, 2.0)
    redrawn = type(redrawn)(**{**vars(redrawn), "correction": Pose2D(0.5, 0.0, 0.1)})
    correction = PoseOut.from_estimate(redrawn).map_correction.model_dump()
    assert correction == pytest.approx({"x_m": 0.5, "y_m": 0.0, "theta_rad": 0.1})
    between = PoseOut.from_estimate(redrawn, Pose2D(9.0, 0.0, 0.0), 3.5)
    assert (between.x_m, between.stamp_s, between.interpolated) == (9.0, 3.5, True)
    assert between.map_correction is None


def test_a_pose_from_the_trajectory_says_it_has_no_covariance():
    out = PoseOut.from_trajectory("r1", Pose2D(1.0, 2.0, 0.3), 5.0)
    assert (out.seq, out.stamp_s, out.status, out.interpolated) == (None, 5.0, "trajectory", True)
    assert out.covariance == [[None] * 3] * 3 and "no covariance" in out.message


def test_map_meta_gives_the_size_in_metres():
    meta = MapMetaMessage.from_spec("r1", GridSpec(-1.0, -2.0, 0.5, 4, 6), revision=3, stamp_s=5.0)
    out = MapMetaOut.from_message(meta)
    assert (out.rows, out.cols, out.width_m, out.height_m) == (4, 6, 3.0, 2.0)
    assert (out.origin_x_m, out.origin_y_m, out.revision) == (-1.0, -2.0, 3)


def test_a_match_answer_for_json_with_its_wait():
    answer = MatchResponse(Pose2D(0.5, 0.25, 0.1), np.diag([1e-3, 1e-3, math.inf]), 0.8, 7,
                           True, "ok", "icp", time_s=0.002, inliers=6)
    out = MatchOut.from_response(answer, 0.01)
    assert out.pose.model_dump() == pytest.approx({"x_m": 0.5, "y_m": 0.25, "theta_rad": 0.1})
    assert out.covariance[2][2] is None and out.covariance[0][0] == 1e-3
    assert (out.iterations, out.inliers, out.time_s, out.round_trip_s) == (7, 6, 0.002, 0.01)


def test_answers_beyond_the_input_limits_still_validate():
    """An answer is never refused by an input's bounds (it would be a 500 to the client)."""
    far = Pose2D(3.0 * COORD_LIMIT_M, -2.0 * COORD_LIMIT_M, 0.0)
    answer = MatchResponse(far, np.eye(3), 0.5, 3, True, "ok", "svd", time_s=0.001, inliers=3)
    assert MatchOut.from_response(answer, 0.01).pose.x_m == far.x
    redrawn = estimate("r1", 8, 4.0, 1.0, 2.0)
    redrawn = type(redrawn)(**{**vars(redrawn), "correction": far})
    assert PoseOut.from_estimate(redrawn).map_correction.y_m == far.y


def test_nan_in_json_is_refused(client, auth):
    """A bare NaN literal in an otherwise valid request (JSON has no NaN; Python's parser takes
    it): the range is refused by name, not read as a missing return."""
    scan = '{"ranges_m": [1.0, NaN], "angle_min_rad": 0, "angle_increment_rad": 0.1}'
    text = f'{{"source": {scan}, "target": {scan}}}'
    headers = {**auth, "Content-Type": "application/json"}
    r = client.post("/api/v1/match", content=text, headers=headers)
    assert r.status_code == 422
    assert "ranges_m" in r.text
