"""The message base: exact round trips of every type, decode dispatch, shared field checks."""

from __future__ import annotations

import dataclasses
import math
import struct
from collections.abc import Callable
from typing import Any

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp
from scanflow import keys, wire
from scanflow.geometry import Pose2D
from scanflow.scan import MAX_MOUNT_M, LaserScan, Odometry

FAST = settings.get_profile("wire_fast")  # registered in conftest.py


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
near = st.floats(-MAX_MOUNT_M, MAX_MOUNT_M, allow_nan=False)
mounts = st.builds(Pose2D, near, near, st.floats(-10, 10))  # a LaserScan's are bounded
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
        mount=draw(mounts),
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
    run=counts,
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
        run=draw(counts),
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
        run=draw(counts),
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
        draw(f64_arrays((n, 3))), kept, draw(st.none() | poses), draw(counts),
    )


@st.composite
def map_states(draw: st.DrawFn) -> wire.MapStateMessage:
    robot_id, n, seq = draw(ids), draw(small_n), draw(counts)
    kept = draw(st.none() | keyframes())
    if kept is not None:
        kept = dataclasses.replace(kept, robot_id=robot_id)
    return wire.MapStateMessage(
        robot_id, seq, draw(st.integers(0, seq)), draw(st.binary()), draw(f64_arrays(n)),
        draw(f64_arrays((n, 3))), kept, draw(counts),
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
    "retire": st.builds(wire.RetireMessage, ids),
    "retired": st.builds(
        wire.RetiredMessage, ids, ids, ids, st.booleans(),
        st.dictionaries(texts, counts, max_size=8),
    ),
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


# ---------------------------------------------------------------- dispatch and field checks


def test_a_second_message_class_with_a_taken_type_name_is_refused() -> None:
    """Two classes under one type name would make decoding ambiguous: the second is refused
    when it is defined, naming the type, and the registered class still decodes."""
    with pytest.raises(TypeError, match="wire type 'scan' is registered twice"):
        type("Impostor", (wire.Message,), {"TYPE": "scan"})
    scan = wire.ScanMessage(LaserScan(np.ones(3), 0.0, 0.1))
    assert type(wire.decode_any(scan.encode())) is wire.ScanMessage


def test_unknown_and_mismatched_types_are_schema_errors(
    payload: Callable[..., bytes], scan_message: wire.ScanMessage
) -> None:
    with pytest.raises(wire.SchemaError, match="unknown type 'laser'"):
        wire.decode_any(payload(scan_message, type="laser"))
    with pytest.raises(wire.SchemaError, match="expected 'odom', got 'scan'"):
        wire.OdometryMessage.decode(scan_message.encode())


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
    msg: wire.Message, changes: dict[str, Any], pattern: str, payload: Callable[..., bytes]
) -> None:
    with pytest.raises(wire.SchemaError, match=pattern):
        wire.decode_any(payload(msg, **changes))


@pytest.fixture
def message(request: pytest.FixtureRequest, scan_message: wire.ScanMessage) -> wire.Message:
    """The message named by an `indirect` parameter: the shared scan, or a map image."""
    messages = {"scan": scan_message, "map_image": wire.MapImageMessage("r", 1, "png", b"")}
    return messages[request.param]


@pytest.mark.parametrize("robot_id", ["*", "**", "$*", "a/b", "..", ".", "stats", "x" * 65])
@pytest.mark.parametrize("message", ["scan", "map_image"], indirect=True)
def test_a_robot_id_that_is_no_key_chunk_is_malformed(
    message, robot_id: str, payload: Callable[..., bytes]
) -> None:
    """Such an id would be a wildcard, a path (snapshot files) or a service's key."""
    with pytest.raises(wire.DecodeError, match="robot id"):
        wire.decode_any(payload(message, robot_id=robot_id))


@pytest.mark.parametrize("seq", [2**62 + 1, 2**63, 2**64 - 1])
def test_a_seq_past_max_count_is_malformed(
    seq: int, payload: Callable[..., bytes], scan_message: wire.ScanMessage
) -> None:
    """It would overflow int64 in snapshots and in the next seq numbered after it."""
    with pytest.raises(wire.DecodeError, match=r"seq must be in \[0, 2\*\*62\]"):
        wire.decode_any(payload(scan_message, seq=seq))
    wire.decode_any(payload(scan_message, seq=wire.MAX_COUNT))



@pytest.mark.parametrize("seqs", [[1, -(2**63)], [5, 7, -(2**63) + 3]])
def test_keyframe_seqs_whose_difference_wraps_around_int64_are_refused(
    seqs: list[int], payload: Callable[..., bytes]
) -> None:
    """A negative seq after a positive one: the int64 difference wraps to a positive one."""
    msg = wire.MapRedrawMessage(
        "r", 0, Pose2D(), np.arange(len(seqs)), np.zeros((len(seqs), 3)), np.zeros(0),
        np.zeros((0, 3)),
    )  # fmt: skip
    bad = wire.codec.encode_array(np.array(seqs, np.int64), "<i8")
    with pytest.raises(wire.SchemaError, match="keyframe_seqs must be >= 0 and strictly"):
        wire.decode_any(payload(msg, keyframe_seqs=bad))


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


def test_a_text_field_a_reader_would_refuse_is_refused_when_built() -> None:
    from scanflow.wire.codec import MAX_STR_BYTES

    # The limit is in UTF-8 bytes: "é" takes two, so half as many characters reach it.
    fits = "é" * (MAX_STR_BYTES // 2)
    assert wire.ServiceStatsMessage.decode(wire.ServiceStatsMessage(fits, "i", 1.0).encode())
    for over in ("x" * (MAX_STR_BYTES + 1), "é" * (MAX_STR_BYTES // 2 + 1)):
        with pytest.raises(wire.MessageError, match="service is over MAX_STR_BYTES"):
            wire.ServiceStatsMessage(over, "i", 1.0)
