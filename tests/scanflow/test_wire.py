"""Wire format: round trips for every message, exact bits, and hostile payloads.

The fuzz tests feed random bytes and mutated valid encodings (bit flips, truncation at every
offset, field deletion, type swaps); the only exception allowed out of a decoder is DecodeError.
"""

from __future__ import annotations

import dataclasses
import math
import struct
from typing import Any

import msgpack
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp
from scanflow import keys, wire
from scanflow.geometry import Pose2D
from scanflow.scan import LaserScan, Odometry, ScanError

FAST = settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])

# ---------------------------------------------------------------- strategies

finite = st.floats(-1e6, 1e6, allow_nan=False, allow_infinity=False)
non_negative = st.floats(0.0, 1e3, allow_nan=False, allow_infinity=False)
# Robot ids as keys take them (scanflow.keys.check_robot_id).
ids = st.from_regex(r"\A[A-Za-z0-9_.-]{1,12}\Z").filter(
    lambda v: v.strip(".") and v not in keys.RESERVED_ROBOT_IDS
)
texts = st.text(max_size=20)
counts = st.integers(0, wire.MAX_COUNT)
poses = st.builds(Pose2D, finite, finite, st.floats(-10, 10))
small_n = st.integers(0, 40)


def f32_any_bits(n: int) -> st.SearchStrategy[np.ndarray]:
    """float32 arrays from arbitrary bit patterns: every NaN payload, inf, -0, subnormals."""
    return hnp.arrays(np.uint32, n).map(lambda a: a.view(np.float32))


def f64_arrays(shape: Any, allow_inf: bool = False) -> st.SearchStrategy[np.ndarray]:
    elems = st.floats(allow_nan=False, allow_infinity=allow_inf, width=64)
    return hnp.arrays(np.float64, shape, elements=elems)


def f64_points(n: int) -> st.SearchStrategy[np.ndarray]:
    elems = st.floats(-1e4, 1e4, allow_nan=False, width=64)
    return hnp.arrays(np.float64, (n, 2), elements=elems)


@st.composite
def scans(draw: st.DrawFn) -> LaserScan:
    n = draw(small_n)
    range_min = draw(st.floats(0, 10))
    range_max = draw(st.one_of(st.just(math.inf), st.floats(range_min + 0.1, 1e4)))
    offsets = draw(st.none() | hnp.arrays(np.float64, n, elements=st.floats(0, 1)).map(np.cumsum))
    return LaserScan(
        ranges_m=draw(f32_any_bits(n)),
        angle_min_rad=draw(finite),
        angle_increment_rad=draw(st.floats(-1, 1)),
        range_min_m=range_min,
        range_max_m=range_max,
        stamp_s=draw(finite),
        scan_duration_s=draw(non_negative),
        beam_time_offsets_s=offsets,
        robot_id=draw(ids),
        frame_id=draw(texts),
        intensities=draw(st.none() | f32_any_bits(n)),
        seq=draw(counts),
        mount=draw(poses),
    )


covariances = f64_arrays((3, 3), allow_inf=True)
scan_messages = st.builds(wire.ScanMessage, scans())
odometry_messages = st.builds(
    wire.OdometryMessage,
    st.builds(
        Odometry,
        stamp_s=finite,
        pose=poses,
        velocity=st.none() | st.tuples(finite, finite, finite),
        robot_id=ids,
        seq=counts,
    ),
)


@st.composite
def deskewed_messages(draw: st.DrawFn) -> wire.DeskewedScanMessage:
    n = draw(small_n)
    misses = draw(small_n)
    beams = draw(st.integers(n + misses, n + misses + 50))
    return wire.DeskewedScanMessage(
        robot_id=draw(ids),
        seq=draw(counts),
        stamp_s=draw(finite),
        points=draw(f64_points(n)),
        source_used=draw(texts),
        times_assumed=draw(st.booleans()),
        beam_count=beams,
        dropped_count=draw(st.integers(misses, beams)),
        no_return_points=draw(f64_points(misses)),
        odom_pose=draw(st.none() | poses),
        mount=draw(poses),
    )


pose_messages = st.builds(
    wire.PoseEstimateMessage,
    robot_id=ids,
    seq=counts,
    stamp_s=finite,
    pose=poses,
    covariance=covariances,
    status=ids,
    method=texts,
    iterations=counts,
    score=finite,
    message=texts,
    correction=st.none() | poses,
    odom_pose=st.none() | poses,
)
scalars = st.booleans() | st.integers(-(2**63), 2**64 - 1) | st.floats(allow_nan=False) | texts
points_f64 = small_n.flatmap(lambda n: f64_arrays((n, 2)))
match_requests = st.builds(
    wire.MatchRequest,
    method=ids,
    source=scans() | points_f64,
    target=scans() | points_f64 | st.builds(wire.MapRef, ids),
    initial_guess=st.none() | poses,
    options=st.dictionaries(texts, scalars, max_size=6),
)
match_responses = st.builds(
    wire.MatchResponse,
    pose=poses,
    covariance=covariances,
    score=finite,
    iterations=counts,
    converged=st.booleans(),
    status=ids,
    method=texts,
    message=texts,
    time_s=non_negative,
    inliers=counts,
    weak_direction=st.none() | st.tuples(finite, finite, finite),
    error=texts,
) | st.builds(wire.MatchResponse.from_error, ids, texts)


@st.composite
def trajectories(draw: st.DrawFn) -> wire.TrajectoryMessage:
    n = draw(small_n)
    return wire.TrajectoryMessage(
        robot_id=draw(ids),
        stamps_s=draw(f64_arrays(n)),
        poses=draw(f64_arrays((n, 3))),
        covariances=draw(st.none() | f64_arrays((n, 3, 3), allow_inf=True)),
    )


map_metas = st.builds(
    wire.MapMetaMessage,
    robot_id=ids,
    resolution_m=st.floats(1e-3, 10),
    origin_x_m=finite,
    origin_y_m=finite,
    rows=st.integers(0, 10**6),
    cols=st.integers(0, 10**6),
    revision=counts,
    stamp_s=finite,
)


@st.composite
def map_regions(draw: st.DrawFn) -> wire.MapRegionMessage:
    meta = draw(map_metas.filter(lambda m: m.rows * m.cols > 0))
    h = draw(st.integers(0, min(meta.rows, 20)))
    w = draw(st.integers(0, min(meta.cols, 20)))
    occupancy = draw(hnp.arrays(np.int8, (h, w), elements=st.integers(-1, 100)))
    row0 = draw(st.integers(0, meta.rows - h))
    col0 = draw(st.integers(0, meta.cols - w))
    return wire.MapRegionMessage(meta, row0, col0, occupancy)


map_images = st.builds(
    wire.MapImageMessage, ids, counts, st.sampled_from(wire.MAP_IMAGE_FORMATS), st.binary()
)


@st.composite
def map_changes(draw: st.DrawFn) -> wire.MapChangedMessage:
    x0, x1 = sorted(draw(st.tuples(finite, finite)))
    y0, y1 = sorted(draw(st.tuples(finite, finite)))
    return wire.MapChangedMessage(draw(ids), draw(counts), draw(finite), x0, y0, x1, y1)


service_stats = st.builds(
    wire.ServiceStatsMessage,
    service=ids,
    instance=ids,
    stamp_s=finite,
    counters=st.dictionaries(texts, counts, max_size=8),
    gauges=st.dictionaries(texts, st.floats(allow_nan=False), max_size=8),
)

@st.composite
def map_inserts(draw: st.DrawFn) -> wire.MapInsertMessage:
    seq = draw(counts)
    return wire.MapInsertMessage(
        robot_id=draw(ids),
        seq=seq,
        stamp_s=draw(finite),
        pose=draw(poses),
        points=draw(f64_points(draw(small_n))),
        no_return_points=draw(f64_points(draw(small_n))),
        mount=draw(poses),
        previous_seq=draw(st.none() | st.integers(0, seq - 1)) if seq > 0 else None,
        keyframe=draw(st.booleans()),
    )


@st.composite
def map_redraws(draw: st.DrawFn) -> wire.MapRedrawMessage:
    seqs = np.array(sorted(draw(st.sets(counts, max_size=20))), dtype=np.int64)
    n = draw(small_n)
    return wire.MapRedrawMessage(
        robot_id=draw(ids),
        seq=draw(counts),
        correction=draw(poses),
        keyframe_seqs=seqs,
        keyframe_poses=draw(f64_arrays((len(seqs), 3))),
        stamps_s=draw(f64_arrays(n)),
        poses=draw(f64_arrays((n, 3))),
    )


@st.composite
def keyframes(draw: st.DrawFn) -> wire.KeyframesMessage:
    seqs = np.array(sorted(draw(st.sets(counts, max_size=6))), dtype=np.int64)
    n = len(seqs)
    hit_counts = np.array(draw(st.lists(st.integers(0, 5), min_size=n, max_size=n)), np.int64)
    miss_counts = np.array(draw(st.lists(st.integers(0, 3), min_size=n, max_size=n)), np.int64)
    return wire.KeyframesMessage(
        draw(ids), seqs, draw(f64_arrays(n)), draw(f64_arrays((n, 3))), draw(f64_arrays((n, 3))),
        hit_counts, draw(f64_points(int(hit_counts.sum()))), miss_counts,
        draw(f64_points(int(miss_counts.sum()))),
    )


@st.composite
def resumes(draw: st.DrawFn) -> wire.ResumeMessage:
    robot_id, n = draw(ids), draw(small_n)
    kept = draw(st.none() | keyframes())
    if kept is not None:
        kept = dataclasses.replace(kept, robot_id=robot_id)
    return wire.ResumeMessage(
        robot_id, draw(counts), draw(st.binary()), draw(f64_arrays(n)),
        draw(f64_arrays((n, 3))), kept, draw(st.none() | poses),
    )


@st.composite
def map_states(draw: st.DrawFn) -> wire.MapStateMessage:
    robot_id, n, seq = draw(ids), draw(small_n), draw(counts)
    kept = draw(st.none() | keyframes())
    if kept is not None:
        kept = dataclasses.replace(kept, robot_id=robot_id)
    return wire.MapStateMessage(
        robot_id, seq, draw(st.integers(0, seq)), draw(st.binary()), draw(f64_arrays(n)),
        draw(f64_arrays((n, 3))), kept,
    )


def _keyframes_of(robot_id: str) -> wire.KeyframesMessage:
    """One keyframe of `robot_id` with no points."""
    none = np.zeros((0, 2))
    return wire.KeyframesMessage(robot_id, np.array([1]), np.zeros(1), np.zeros((1, 3)),
                                 np.zeros((1, 3)), np.array([0]), none, np.array([0]), none)


STRATEGIES: dict[str, st.SearchStrategy[wire.Message]] = {
    "scan": scan_messages,
    "scan_deskewed": deskewed_messages(),
    "odom": odometry_messages,
    "pose": pose_messages,
    "match_request": match_requests,
    "match_response": match_responses,
    "trajectory": trajectories(),
    "map_meta": map_metas,
    "map_region": map_regions(),
    "map_image": map_images,
    "map_changed": map_changes(),
    "map_insert": map_inserts(),
    "map_redraw": map_redraws(),
    "keyframes": keyframes(),
    "resume": resumes(),
    "map_state": map_states(),
    "service_stats": service_stats,
    "initial_pose": st.builds(wire.InitialPoseMessage, ids, poses),
}


def assert_same(a: Any, b: Any, path: str = "msg") -> None:
    """Deep equality with arrays compared bit for bit (dtype, shape and bytes)."""
    assert type(a) is type(b), f"{path}: {type(a).__name__} != {type(b).__name__}"
    if isinstance(a, np.ndarray):
        assert (a.dtype, a.shape) == (b.dtype, b.shape), path
        assert a.tobytes() == b.tobytes(), path
    elif dataclasses.is_dataclass(a):
        for f in dataclasses.fields(a):
            assert_same(getattr(a, f.name), getattr(b, f.name), f"{path}.{f.name}")
    elif isinstance(a, dict):
        assert list(a) == list(b), path
        for key in a:
            assert_same(a[key], b[key], f"{path}[{key!r}]")
    elif isinstance(a, list | tuple):
        assert len(a) == len(b), path
        for i, (x, y) in enumerate(zip(a, b, strict=True)):
            assert_same(x, y, f"{path}[{i}]")
    elif isinstance(a, float):
        assert struct.pack("<d", a) == struct.pack("<d", b), f"{path}: {a!r} != {b!r}"
    else:
        assert a == b, f"{path}: {a!r} != {b!r}"


# ---------------------------------------------------------------- round trips


def test_every_registered_type_has_a_strategy() -> None:
    assert set(STRATEGIES) == set(wire.message_types())


@pytest.mark.parametrize("type_name", sorted(STRATEGIES))
def test_round_trip_is_exact(type_name: str) -> None:
    @FAST
    @given(STRATEGIES[type_name])
    def check(msg: wire.Message) -> None:
        data = msg.encode()
        for decoded in (type(msg).decode(data), wire.decode_any(data)):
            assert_same(msg, decoded)
            assert decoded.encode() == data

    check()


def test_nan_ranges_keep_their_exact_bits() -> None:
    bits = np.array([0x7FC00000, 0x7F800001, 0xFFC12345, 0x3F800000], dtype=np.uint32)
    scan = LaserScan(bits.view(np.float32), 0.0, 0.1)
    decoded = wire.ScanMessage.decode(wire.ScanMessage(scan).encode()).scan
    assert decoded.ranges_m.view(np.uint32).tolist() == bits.tolist()
    assert decoded.valid_mask.tolist() == [False, False, False, True]
    assert decoded.dropped_count == 3


def test_arrays_travel_as_little_endian_bytes_not_lists() -> None:
    ranges = np.arange(5, dtype=">f4")  # big-endian input must come out the same
    data = wire.ScanMessage(LaserScan(ranges, 0.0, 0.1)).encode()
    envelope = msgpack.unpackb(data)["ranges_m"]
    assert envelope == {"d": "<f4", "s": [5], "b": np.arange(5, dtype="<f4").tobytes()}
    assert wire.decode_any(data).scan.ranges_m.dtype == np.float32


def test_decoded_arrays_are_read_only() -> None:
    msg = wire.TrajectoryMessage("r", np.zeros(2), np.zeros((2, 3)))
    decoded = wire.TrajectoryMessage.decode(msg.encode())
    with pytest.raises(ValueError, match="read-only"):
        decoded.poses[0, 0] = 1.0


def test_every_payload_carries_type_and_version() -> None:
    data = wire.MapImageMessage("r", 1, "png", b"x").encode()
    assert msgpack.unpackb(data)["type"] == "map_image"
    assert msgpack.unpackb(data)["v"] == wire.SCHEMA_VERSION == 8


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


def test_map_messages_expose_grid_geometry() -> None:
    meta = wire.MapMetaMessage("r", 0.5, -2.0, 1.0, 10, 20, 3, 0.0)
    region = wire.MapRegionMessage(meta, 2, 4, np.zeros((3, 5), np.int8))
    win = region.window_spec
    assert (win.origin_x_m, win.origin_y_m, win.rows, win.cols) == (0.0, 2.0, 3, 5)
    assert wire.MapMetaMessage.from_spec("r", meta.spec, 3, 0.0).spec == meta.spec


# ---------------------------------------------------------------- clear errors


def _payload(msg: wire.Message, **changes: Any) -> bytes:
    """`msg` re-packed with top-level fields replaced (a value of ... deletes the field)."""
    obj = msgpack.unpackb(msg.encode())
    for key, value in changes.items():
        if value is ...:
            del obj[key]
        else:
            obj[key] = value
    return msgpack.packb(obj)


SCAN = wire.ScanMessage(LaserScan(np.array([1.0, np.nan, 3.0]), 0.0, 0.1, robot_id="r1"))


def test_wrong_version_is_a_version_error() -> None:
    # 1: before no_return_points, 2: before the sensor mount, 3: before map redraws,
    # 4: before the resume message, 5: before the inserts' keyframe flag, 6: before the map
    # state message, 7: before the estimates' odometry pose
    for version in (1, 2, 3, 4, 5, 6, 7, 9):
        with pytest.raises(wire.VersionError, match=rf"\.v: schema version {version}"):
            wire.decode_any(_payload(SCAN, v=version))


def test_unknown_and_mismatched_types_are_schema_errors() -> None:
    with pytest.raises(wire.SchemaError, match="unknown type 'laser'"):
        wire.decode_any(_payload(SCAN, type="laser"))
    with pytest.raises(wire.SchemaError, match="expected 'odom', got 'scan'"):
        wire.OdometryMessage.decode(SCAN.encode())


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
def test_bad_scan_fields_name_the_field(changes: dict[str, Any], pattern: str) -> None:
    with pytest.raises(wire.SchemaError, match=pattern):
        wire.ScanMessage.decode(_payload(SCAN, **changes))


def test_deskewed_points_keep_every_float64_bit_and_refuse_float32() -> None:
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
            wire.decode_any(_payload(msg, **narrow))


def test_deskewed_no_return_points_default_to_none_and_fit_the_beam_count() -> None:
    msg = wire.DeskewedScanMessage("r", 0, 0.0, np.zeros((2, 2)), "none", True, 3, 1)
    assert msg.no_return_points.shape == (0, 2)
    full = wire.DeskewedScanMessage("r", 0, 0.0, np.zeros((2, 2)), "none", True, 3, 1, [[9, 0]])
    assert wire.DeskewedScanMessage.decode(full.encode()).no_return_points.tolist() == [[9, 0]]


def test_deskewed_odom_pose_is_optional_and_must_be_a_pose() -> None:
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
        wire.decode_any(_payload(msg, odom_pose=[1.0, "x", 0.0]))


def test_map_insert_points_must_be_finite_float64_rows_and_the_pose_a_pose() -> None:
    points = np.array([[1.0, 2.0], [3.0, 4.0]])
    msg = wire.MapInsertMessage("r", 3, 2.0, Pose2D(1, 2, 3), points, np.zeros((0, 2)))
    assert wire.MapInsertMessage.decode(msg.encode()).points.tobytes() == points.tobytes()
    with pytest.raises(wire.MessageError, match="pose must be a Pose2D"):
        wire.MapInsertMessage("r", 3, 2.0, (1, 2, 3), points, np.zeros((0, 2)))
    with pytest.raises(wire.MessageError, match="no_return_points"):
        wire.MapInsertMessage("r", 3, 2.0, Pose2D(), points, np.zeros((2, 3)))
    with pytest.raises(wire.SchemaError, match="points contains non-finite"):
        wire.decode_any(
            _payload(msg, points=wire.codec.encode_array(np.full((1, 2), np.nan), "<f8"))
        )


def test_map_insert_previous_seq_comes_before_its_seq() -> None:
    msg = wire.MapInsertMessage("r", 3, 2.0, Pose2D(), np.zeros((0, 2)), np.zeros((0, 2)))
    assert wire.MapInsertMessage.decode(msg.encode()).previous_seq is None
    for bad in (3, 7):
        with pytest.raises(wire.SchemaError, match="previous_seq must be below seq 3"):
            wire.decode_any(_payload(msg, previous_seq=bad))
    with pytest.raises(wire.SchemaError, match="previous_seq"):
        wire.decode_any(_payload(msg, previous_seq=-1))


def test_zero_sized_arrays_with_huge_dimensions_are_refused() -> None:
    envelope = {"d": "<f8", "s": [0, 2**62, 2**62], "b": b""}
    with pytest.raises(wire.SchemaError, match=r"poses\.s: sizes must be integers"):
        wire.decode_any(_payload(wire.TrajectoryMessage("r", [], np.zeros((0, 3))), poses=envelope))


def test_scan_errors_surface_as_chained_decode_errors() -> None:
    data = _payload(SCAN, beam_time_offsets_s={"d": "<f8", "s": [2], "b": bytes(16)})
    with pytest.raises(wire.SchemaError, match="beam_time_offsets_s has shape") as info:
        wire.decode_any(data)
    assert isinstance(info.value.__cause__, ScanError)


@pytest.mark.parametrize(
    ("msg", "changes", "pattern"),
    [
        (
            wire.DeskewedScanMessage("r", 0, 0.0, np.zeros((1, 2)), "none", True, 1, 0),
            {"points": wire.codec.encode_array(np.full((1, 2), np.nan), "<f8")},
            "points contains non-finite",
        ),
        (
            wire.DeskewedScanMessage("r", 0, 0.0, np.zeros((1, 2)), "none", True, 2, 1),
            {"no_return_points": wire.codec.encode_array(np.full((1, 2), np.inf), "<f8")},
            "no_return_points contains non-finite",
        ),
        (
            wire.DeskewedScanMessage("r", 0, 0.0, np.zeros((1, 2)), "none", True, 1, 0),
            {"no_return_points": wire.codec.encode_array(np.zeros((1, 2)), "<f8")},
            r"exceed beam_count \(1\)",
        ),
        (
            wire.PoseEstimateMessage("r", 0, 0.0, Pose2D(), np.eye(3), "ok", "icp", 1, 0.0),
            {"pose": [0.0, math.inf, 0.0]},
            r"pose\.pose: Pose2D\.y must be finite",
        ),
        (
            wire.PoseEstimateMessage("r", 0, 0.0, Pose2D(), np.eye(3), "ok", "icp", 1, 0.0),
            {"covariance": wire.codec.encode_array(np.full((3, 3), np.nan), "<f8")},
            "covariance contains NaN",
        ),
        (
            wire.MatchRequest("icp", np.zeros((1, 2)), wire.MapRef("r")),
            {"source": {"kind": "map", "robot_id": "r"}},
            r"source\.kind: expected 'scan' or 'points'",
        ),
        (
            wire.MatchRequest("icp", np.zeros((1, 2)), wire.MapRef("r")),
            {"options": {"k": [1]}},
            r"options\['k'\]: expected bool/int/float/str",
        ),
        (
            wire.MapImageMessage("r", 1, "png", b""),
            {"format": "gif"},
            "format must be one of",
        ),
        (
            wire.MapRegionMessage(
                wire.MapMetaMessage("r", 0.1, 0, 0, 2, 2, 0, 0.0), 0, 0, np.zeros((2, 2), np.int8)
            ),
            {"occupancy": wire.codec.encode_array(np.full((2, 2), 101, np.int8), "|i1")},
            "occupancy values must be -1 or 0..100",
        ),
        (
            wire.MapChangedMessage("r", 1, 0.0, 0, 0, 1, 1),
            {"min_x_m": 2.0},
            "dirty box min",
        ),
        (
            wire.ServiceStatsMessage("svc", "a", 0.0),
            {"counters": {"n": 1.5}},
            r"counters\['n'\]: expected an integer",
        ),
    ],
)
def test_bad_message_fields_name_the_field(
    msg: wire.Message, changes: dict[str, Any], pattern: str
) -> None:
    with pytest.raises(wire.SchemaError, match=pattern):
        wire.decode_any(_payload(msg, **changes))


@pytest.mark.parametrize(
    ("data", "error"),
    [
        (b"", wire.DecodeError),
        (b"\xc1", wire.DecodeError),  # never-used msgpack byte
        (b"\x92\x01\x02", wire.SchemaError),  # an array, not a map
        (b"\xdd\xff\xff\xff\xff", wire.DecodeError),  # 4-billion-element array header
        (b"\xdf\xff\xff\xff\xff", wire.DecodeError),  # 4-billion-entry map header
        (b"\xc6\xff\xff\xff\xff", wire.DecodeError),  # 4 GiB bin header
        (b"\x91" * 100_000, wire.DecodeError),  # nesting deeper than the unpacker stack
        (b"\xd7\xff" + bytes(8), wire.DecodeError),  # extension type (timestamp)
        (b"\x81\x01\x02", wire.DecodeError),  # integer map key
        # trailing data
        (msgpack.packb({"v": wire.SCHEMA_VERSION, "type": "scan"}) + b"\x00", wire.DecodeError),
        (msgpack.packb({"type": "scan"}), wire.SchemaError),  # no version
        (msgpack.packb({"v": "1", "type": "scan"}), wire.SchemaError),
    ],
)
def test_malformed_payloads_raise_decode_errors(data: bytes, error: type[Exception]) -> None:
    with pytest.raises(error):
        wire.decode_any(data)


def test_error_messages_stay_short_for_huge_hostile_strings() -> None:
    huge = "x" * 60_000
    for changes in ({"type": huge}, {"robot_id": ""}, {"frame_id": 5}):
        with pytest.raises(wire.DecodeError) as info:
            wire.decode_any(_payload(SCAN, **changes))
        assert len(str(info.value)) < 400
    image = wire.MapImageMessage("r", 1, "png", b"")
    with pytest.raises(wire.SchemaError, match="format must be one of") as info:
        wire.decode_any(_payload(image, format=huge))
    assert len(str(info.value)) < 400


@pytest.mark.parametrize("robot_id", ["*", "**", "$*", "a/b", "..", ".", "stats", "x" * 65])
@pytest.mark.parametrize("message", [SCAN, wire.MapImageMessage("r", 1, "png", b"")],
                         ids=lambda m: m.TYPE)
def test_a_robot_id_that_is_no_key_chunk_is_malformed(message, robot_id: str) -> None:
    """Such an id would be a wildcard, a path (snapshot files) or a service's key."""
    with pytest.raises(wire.DecodeError, match="robot id"):
        wire.decode_any(_payload(message, robot_id=robot_id))


@pytest.mark.parametrize("seq", [2**62 + 1, 2**63, 2**64 - 1])
def test_a_seq_past_max_count_is_malformed(seq: int) -> None:
    """It would overflow int64 in snapshots and in the next seq numbered after it."""
    with pytest.raises(wire.DecodeError, match=r"seq must be in \[0, 2\*\*62\]"):
        wire.decode_any(_payload(SCAN, seq=seq))
    wire.decode_any(_payload(SCAN, seq=wire.MAX_COUNT))


def test_an_operators_pose_beyond_max_position_is_malformed() -> None:
    """HTTP bounds it the same; 1e300 m reached the tracker and broke its first scan."""
    far = wire.InitialPoseMessage("r", Pose2D(0.0, 0.0, 0.0))
    with pytest.raises(wire.DecodeError, match="beyond"):
        wire.decode_any(_payload(far, pose=[1e300, 0.0, 0.0]))
    with pytest.raises(wire.MessageError, match="beyond"):
        wire.InitialPoseMessage("r", Pose2D(0.0, -2e6, 0.0))
    wire.InitialPoseMessage("r", Pose2D(wire.MAX_POSITION_M, 0.0, 0.0))


def test_oversized_payload_is_rejected_before_unpacking() -> None:
    data = bytes(wire.MAX_PAYLOAD_BYTES + 1)
    with pytest.raises(wire.PayloadTooLarge, match="over MAX_PAYLOAD_BYTES"):
        wire.decode_any(data)
    assert issubclass(wire.PayloadTooLarge, ValueError)


def test_non_bytes_input_is_a_decode_error() -> None:
    with pytest.raises(wire.DecodeError, match="payload must be bytes, got str"):
        wire.decode_any("scan")  # type: ignore[arg-type]


def _big_deskewed(n: int) -> wire.DeskewedScanMessage:
    return wire.DeskewedScanMessage("r", 0, 0.0, np.zeros((n, 2)), "", False, n, 0)


def test_encoding_over_the_limit_is_refused() -> None:
    msg = _big_deskewed(wire.MAX_PAYLOAD_BYTES // 16 + 1)
    with pytest.raises(wire.MessageError, match="over MAX_PAYLOAD_BYTES"):
        msg.encode()


def test_bulk_messages_may_be_bigger_than_the_payload_limit() -> None:
    """A path (or a map, keyframes) grows with the run: past 16 MiB it still goes on the wire
    (a 700k-pose trajectory here), and comes back bit for bit."""
    n = wire.MAX_PAYLOAD_BYTES // 24 + 1
    rng = np.random.default_rng(0)
    msg = wire.TrajectoryMessage("r", np.arange(n, dtype=np.float64), rng.normal(size=(n, 3)))
    data = msg.encode()
    assert len(data) > wire.MAX_PAYLOAD_BYTES
    for back in (wire.decode_any(data), wire.TrajectoryMessage.decode(data)):
        assert isinstance(back, wire.TrajectoryMessage)
        assert back.poses.tobytes() == msg.poses.tobytes()
        assert back.stamps_s.tobytes() == msg.stamps_s.tobytes()


def test_bulk_messages_over_their_own_limit_are_refused(monkeypatch) -> None:
    monkeypatch.setattr(wire.codec, "MAX_BULK_BYTES", wire.MAX_PAYLOAD_BYTES + 1024)
    n = wire.MAX_PAYLOAD_BYTES // 24 + 1024
    msg = wire.TrajectoryMessage("r", np.zeros(n), np.zeros((n, 3)))
    with pytest.raises(wire.MessageError, match="over MAX_BULK_BYTES"):
        msg.encode()
    with pytest.raises(wire.PayloadTooLarge, match="over MAX_BULK_BYTES"):
        wire.decode_any(bytes(wire.codec.MAX_BULK_BYTES + 1))


def test_a_big_payload_of_another_type_is_refused_before_unpacking(monkeypatch) -> None:
    """Only the bulk types may pass 16 MiB; the type is read off the payload's first bytes, so a
    big scan is refused without being unpacked."""
    data = wire.codec.pack_message("deskewed_scan", _big_deskewed(2**20 + 1).to_fields(), True)
    assert len(data) > wire.MAX_PAYLOAD_BYTES

    def unpacked(*args: Any, **kwargs: Any) -> None:
        raise AssertionError("a big payload of a type that may not be big was unpacked")

    monkeypatch.setattr(msgpack, "unpackb", unpacked)
    for decode in (wire.decode_any, wire.DeskewedScanMessage.decode):
        with pytest.raises(wire.PayloadTooLarge, match="its type 'deskewed_scan' is not one"):
            decode(data)


def test_a_second_type_key_does_not_smuggle_a_big_payload_past_the_limit() -> None:
    """The first key says trajectory (a bulk type), a later one says scan: msgpack keeps the
    later one, and the size is checked again against it."""
    packer = msgpack.Packer(use_bin_type=True)
    fields = {"type": "trajectory", "v": wire.SCHEMA_VERSION, "pad": bytes(wire.MAX_PAYLOAD_BYTES)}
    data = packer.pack_map_header(4) + b"".join(
        packer.pack(k) + packer.pack(v) for k, v in [*fields.items(), ("type", "scan")]
    )
    with pytest.raises(wire.PayloadTooLarge, match=r"over MAX_PAYLOAD_BYTES=\d+ for 'scan'"):
        wire.decode_any(data)


@pytest.mark.parametrize("head", [b"", b"\x81", b"\x81\xa4type", b"\x81\xa4type\x05", b"\x90"])
def test_a_big_payload_whose_type_cannot_be_read_first_is_refused(head: bytes) -> None:
    with pytest.raises(wire.PayloadTooLarge, match="its type None is not one"):
        wire.decode_any(head + bytes(wire.MAX_PAYLOAD_BYTES + 1))


@pytest.mark.parametrize(
    ("build", "pattern"),
    [
        (lambda: wire.DeskewedScanMessage("r", 0, 0.0, np.zeros((3,)), "", False, 3, 0), "points"),
        (
            lambda: wire.DeskewedScanMessage("r", 0, 0.0, np.zeros((0, 2)), "", False, 1, 2),
            "dropped",
        ),
        (
            lambda: wire.DeskewedScanMessage(
                "r", 0, 0.0, np.zeros((0, 2)), "", False, 3, 1, np.zeros((2,))
            ),
            "no_return_points must have shape",
        ),
        (
            lambda: wire.DeskewedScanMessage(
                "r", 0, 0.0, np.zeros((2, 2)), "", False, 3, 1, np.zeros((2, 2))
            ),
            r"exceed beam_count \(3\)",
        ),
        (
            lambda: wire.DeskewedScanMessage(
                "r", 0, 0.0, np.zeros((1, 2)), "", False, 4, 1, np.zeros((2, 2))
            ),
            r"more than dropped_count \(1\)",
        ),
        (
            lambda: wire.PoseEstimateMessage("", 0, 0.0, Pose2D(), np.eye(3), "ok", "", 0, 0),
            "robot_id",
        ),
        (lambda: wire.MatchResponse(Pose2D(), np.eye(2), 0, 0, True, "ok", ""), "covariance"),
        (lambda: wire.MatchRequest("icp", np.zeros((2, 2)), np.zeros(2)), "target"),
        (
            lambda: wire.MatchRequest(
                "icp", np.zeros((1, 2)), np.zeros((1, 2)), options={"a": None}
            ),
            "options",
        ),
        (lambda: wire.TrajectoryMessage("r", np.zeros(2), np.zeros((3, 3))), "poses"),
        (
            lambda: wire.PoseEstimateMessage(
                "r", 0, 0.0, Pose2D(), np.eye(3), "ok", "", 0, 0, "", (1, 2, 3)
            ),
            "correction",
        ),
        (
            lambda: wire.MapRedrawMessage(
                "r", 0, Pose2D(), np.array([3, 3]), np.zeros((2, 3)), np.zeros(0), np.zeros((0, 3))
            ),
            "keyframe_seqs must be >= 0 and strictly increasing",
        ),
        (
            lambda: wire.MapRedrawMessage(
                "r", 0, Pose2D(), np.array([1, 3]), np.zeros((1, 3)), np.zeros(0), np.zeros((0, 3))
            ),
            "keyframe_poses must have shape",
        ),
        (
            lambda: wire.KeyframesMessage(
                "r", np.array([1]), np.zeros(1), np.zeros((1, 3)), np.zeros((1, 3)),
                np.array([3]), np.zeros((2, 2)), np.array([0]), np.zeros((0, 2)),
            ),
            "hit_counts must be >= 0 and add up to the rows of hits",
        ),
        (
            lambda: wire.MapRedrawMessage(
                "r", 0, Pose2D(), np.zeros(0), np.zeros((0, 3)), np.zeros(2),
                np.full((2, 3), np.nan),
            ),
            "poses contains non-finite",
        ),
        (
            lambda: wire.MapStateMessage("r", 3, 4, b"", np.zeros(0), np.zeros((0, 3))),
            "insert_seq must be at most seq 3, got 4",
        ),
        (
            lambda: wire.MapStateMessage("r", 3, 1, "npz", np.zeros(0), np.zeros((0, 3))),
            "map_npz must be bytes, got str",
        ),
        (
            lambda: wire.MapStateMessage(
                "r", 3, 1, b"", np.zeros(0), np.zeros((0, 3)), _keyframes_of("q")
            ),
            "keyframes.robot_id must be 'r', got 'q'",
        ),
        (
            lambda: wire.ResumeMessage(
                "r", 0, b"", np.zeros(0), np.zeros((0, 3)), _keyframes_of("q")
            ),
            "keyframes.robot_id must be 'r', got 'q'",
        ),
        (lambda: wire.MapMetaMessage("r", 0.0, 0, 0, 1, 1, 0, 0.0), "resolution_m"),
        (lambda: wire.ServiceStatsMessage("s", "i", 0.0, gauges={"g": math.nan}), "gauges"),
        (lambda: wire.ServiceStatsMessage("s", "i", 0.0, gauges={"g": None}), "gauges"),
        (lambda: wire.ServiceStatsMessage("s", "i", 0.0, counters={"c": -1}), "counters"),
        (lambda: wire.ScanMessage("not a scan"), "scan"),  # type: ignore[arg-type]
    ],
)
def test_building_bad_messages_names_the_field(build: Any, pattern: str) -> None:
    with pytest.raises(wire.MessageError, match=pattern):
        build()


# ---------------------------------------------------------------- fuzzing


def _decode_or_decode_error(data: bytes) -> None:
    """The contract under test: a message, or a DecodeError; nothing else ever escapes."""
    try:
        msg = wire.decode_any(data)
    except wire.DecodeError:
        return
    assert isinstance(msg, wire.Message)


def _examples() -> list[wire.Message]:
    """One valid message of every type, built deterministically."""
    scan = LaserScan(
        np.linspace(0.5, 4.0, 24, dtype=np.float32),
        -1.0,
        0.08,
        range_max_m=3.5,
        beam_time_offsets_s=np.linspace(0, 0.05, 24),
        intensities=np.ones(24),
        seq=5,
    )
    meta = wire.MapMetaMessage("r", 0.05, -1.0, -2.0, 6, 8, 3, 1.0)
    return [
        wire.ScanMessage(scan),
        wire.DeskewedScanMessage(
            "r", 1, 2.0, scan.points()[1:], "odometry", False, 24, 1, scan.points()[:1] * 2
        ),
        wire.OdometryMessage(Odometry(1.0, Pose2D(1, 2, 3), (0.5, 0.0, 0.1))),
        wire.PoseEstimateMessage("r", 1, 2.0, Pose2D(1, 2, 3), np.eye(3), "ok", "icp", 4, 0.5),
        wire.PoseEstimateMessage(
            "r", 1, 2.0, Pose2D(1, 2, 3), np.eye(3), "ok", "icp", 4, 0.5, "", Pose2D(0.1, 0, 0)
        ),
        wire.MatchRequest("icp", scan, wire.MapRef("r"), Pose2D(1, 0, 0), {"a": 1, "b": 2.5}),
        wire.MatchRequest("plicp", scan.points(), scan, None, {"c": "x", "d": True}),
        wire.MatchResponse.from_error("no map", "icp"),
        wire.MatchResponse(
            Pose2D(), np.eye(3), 1.0, 3, True, "ok", "icp", weak_direction=(1, 0, 0)
        ),
        wire.TrajectoryMessage("r", np.arange(4.0), np.zeros((4, 3)), np.zeros((4, 3, 3))),
        meta,
        wire.MapRegionMessage(meta, 2, 3, np.full((4, 5), -1, np.int8)),
        wire.MapImageMessage("r", 1, "png", b"\x89PNG\r\n"),
        wire.MapChangedMessage("r", 1, 0.0, 0, 0, 1, 1),
        wire.MapInsertMessage("r", 3, 2.0, Pose2D(1, 2, 3), scan.points(), scan.points()[:2] * 3),
        wire.MapInsertMessage("r", 3, 2.0, Pose2D(1, 2, 3), scan.points(), scan.points()[:2] * 3),
        wire.MapRedrawMessage(
            "r", 9, Pose2D(0.1, -0.2, 0.03), np.array([2, 5]), np.ones((2, 3)), np.arange(3.0),
            np.zeros((3, 3)),
        ),
        kept := wire.KeyframesMessage(
            "r", np.array([1, 4]), np.array([0.1, 0.4]), np.zeros((2, 3)), np.zeros((2, 3)),
            np.array([2, 1]), np.ones((3, 2)), np.array([0, 1]), np.ones((1, 2)),
        ),
        wire.ResumeMessage("r", 4, b"PK\x03\x04", np.arange(2.0), np.ones((2, 3)), kept),
        wire.ResumeMessage("r", 0, b"", np.zeros(0), np.zeros((0, 3))),
        wire.MapStateMessage("r", 7, 5, b"PK\x03\x04", np.arange(2.0), np.ones((2, 3))),
        wire.MapStateMessage("r", 7, 5, b"PK\x03\x04", np.arange(2.0), np.ones((2, 3)), kept),
        wire.ServiceStatsMessage("deskew", "a", 1.0, {"in": 3}, {"lag_s": 0.5}),
        wire.InitialPoseMessage("r", Pose2D(1.5, -2.0, 0.3)),
    ]


EXAMPLES = _examples()


def test_examples_cover_every_type() -> None:
    assert {m.TYPE for m in EXAMPLES} == set(wire.message_types())


def test_truncation_at_every_offset_is_a_decode_error() -> None:
    for msg in EXAMPLES:
        data = msg.encode()
        for end in range(len(data)):
            with pytest.raises(wire.DecodeError):
                wire.decode_any(data[:end])


def test_random_bytes_only_raise_decode_error() -> None:
    rng = np.random.default_rng(20240602)
    for _ in range(3000):
        size = int(rng.integers(0, 120))
        data = rng.integers(0, 256, size, dtype=np.uint8).tobytes()
        # Half of the cases start like a map so the decoder gets past the first byte.
        if rng.random() < 0.5:
            data = bytes([0x80 | int(rng.integers(0, 16))]) + data
        _decode_or_decode_error(data)


@settings(max_examples=500, deadline=None)
@given(st.binary(max_size=200))
def test_arbitrary_bytes_only_raise_decode_error(data: bytes) -> None:
    _decode_or_decode_error(data)


def test_bit_flips_only_raise_decode_error() -> None:
    rng = np.random.default_rng(7)
    for msg in EXAMPLES:
        data = np.frombuffer(msg.encode(), dtype=np.uint8)
        for _ in range(300):
            flipped = data.copy()
            for pos in rng.integers(0, len(data), int(rng.integers(1, 4))):
                flipped[pos] ^= np.uint8(1 << int(rng.integers(0, 8)))
            _decode_or_decode_error(flipped.tobytes())


FREE_FORM_MAPS = {"options", "counters", "gauges"}  # their keys are data, not schema


def _paths(obj: Any, prefix: tuple[Any, ...] = ()) -> list[tuple[Any, ...]]:
    """Every schema key path in a nested msgpack structure of maps."""
    out = []
    if isinstance(obj, dict) and not (prefix and prefix[-1] in FREE_FORM_MAPS):
        for key, value in obj.items():
            out.append((*prefix, key))
            out.extend(_paths(value, (*prefix, key)))
    return out


def _parent(obj: Any, path: tuple[Any, ...]) -> Any:
    for key in path[:-1]:
        obj = obj[key]
    return obj


def test_deleting_any_field_is_a_schema_error() -> None:
    cases = 0
    for msg in EXAMPLES:
        tree = msgpack.unpackb(msg.encode())
        for path in _paths(tree):
            mutated = msgpack.unpackb(msg.encode())
            del _parent(mutated, path)[path[-1]]
            with pytest.raises(wire.SchemaError, match=r"missing|expected"):
                wire.decode_any(msgpack.packb(mutated))
            cases += 1
    assert cases > 150


SWAPS = [
    None,
    True,
    0,
    -1,
    2**64 - 1,
    -(2**63),
    1.5,
    math.nan,
    -math.inf,
    "",
    "x",
    b"",
    b"\x00" * 9,
    [],
    [1, 2, 3],
    [1.0] * 16,
    {},
    {"d": "<f4"},
    {"a": 1},
]


def test_swapping_any_field_type_only_raises_decode_error() -> None:
    cases = 0
    for msg in EXAMPLES:
        tree = msgpack.unpackb(msg.encode())
        for path in _paths(tree):
            for value in SWAPS:
                mutated = msgpack.unpackb(msg.encode())
                _parent(mutated, path)[path[-1]] = value
                _decode_or_decode_error(msgpack.packb(mutated))
                cases += 1
    assert cases > 3000


@FAST
@given(st.sampled_from(EXAMPLES), st.data())
def test_random_splices_only_raise_decode_error(msg: wire.Message, data: st.DataObject) -> None:
    """Replace a random slice of a valid encoding with random bytes."""
    payload = msg.encode()
    start = data.draw(st.integers(0, len(payload)))
    stop = data.draw(st.integers(start, len(payload)))
    _decode_or_decode_error(payload[:start] + data.draw(st.binary(max_size=12)) + payload[stop:])


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
