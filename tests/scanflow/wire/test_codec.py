"""The codec: framing, array envelopes, size limits, malformed payloads and fuzzed bytes."""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import msgpack
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scanflow import wire
from scanflow.geometry import Pose2D
from scanflow.scan import LaserScan, Odometry

FAST = settings.get_profile("wire_fast")  # registered in conftest.py


# ---------------------------------------------------------------- framing


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
    assert msgpack.unpackb(data)["v"] == wire.SCHEMA_VERSION == 10


# ---------------------------------------------------------------- clear errors


def test_wrong_version_is_a_version_error(
    payload: Callable[..., bytes], scan_message: wire.ScanMessage
) -> None:
    # 1: before no_return_points, 2: before the sensor mount, 3: before map redraws,
    # 4: before the resume message, 5: before the inserts' keyframe flag, 6: before the map
    # state message, 7: before the estimates' odometry pose, 8: before retiring a robot,
    # 9: before the tracker's run token
    for version in (1, 2, 3, 4, 5, 6, 7, 8, 9, 11):
        with pytest.raises(wire.VersionError, match=rf"\.v: schema version {version}"):
            wire.decode_any(payload(scan_message, v=version))


def test_zero_sized_arrays_with_huge_dimensions_are_refused(payload: Callable[..., bytes]) -> None:
    envelope = {"d": "<f8", "s": [0, 2**62, 2**62], "b": b""}
    with pytest.raises(wire.SchemaError, match=r"poses\.s: sizes must be integers"):
        wire.decode_any(payload(wire.TrajectoryMessage("r", [], np.zeros((0, 3))), poses=envelope))


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


def test_error_messages_stay_short_for_huge_hostile_strings(
    payload: Callable[..., bytes], scan_message: wire.ScanMessage
) -> None:
    huge = "x" * 60_000
    for changes in ({"type": huge}, {"robot_id": ""}, {"frame_id": 5}):
        with pytest.raises(wire.DecodeError) as info:
            wire.decode_any(payload(scan_message, **changes))
        assert len(str(info.value)) < 400
    image = wire.MapImageMessage("r", 1, "png", b"")
    with pytest.raises(wire.SchemaError, match="format must be one of") as info:
        wire.decode_any(payload(image, format=huge))
    assert len(str(info.value)) < 400


# ---------------------------------------------------------------- size limits


def test_oversized_payload_is_rejected_before_unpacking() -> None:
    data = bytes(wire.MAX_PAYLOAD_BYTES + 1)
    with pytest.raises(wire.PayloadTooLarge, match="over MAX_PAYLOAD_BYTES"):
        wire.decode_any(data)
    assert issubclass(wire.PayloadTooLarge, ValueError)


def test_non_bytes_input_is_a_decode_error() -> None:
    with pytest.raises(wire.DecodeError, match="payload must be bytes, got str"):
        wire.decode_any("scan")  # type: ignore[arg-type]



def test_a_payload_decodes_the_same_from_any_buffer_it_comes_in() -> None:
    """decode takes bytes, bytearray or any memoryview: one of 4-byte items included."""
    payloads = (wire.MapImageMessage("r", 1, "png", b"x" * k).encode() for k in range(4))
    data = next(d for d in payloads if len(d) % 4 == 0)
    expected = wire.decode_any(data)
    for buffer in (bytearray(data), memoryview(data), memoryview(data).cast("I")):
        assert wire.decode_any(buffer).data == expected.data
    big = memoryview(bytes(wire.MAX_PAYLOAD_BYTES + 4)).cast("I")
    with pytest.raises(wire.PayloadTooLarge, match="over MAX_PAYLOAD_BYTES"):
        wire.decode_any(big)


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


# ---------------------------------------------------------------- fuzzing
# Random bytes and mutated valid encodings (bit flips, truncation at every offset, field
# deletion, type swaps): the only exception allowed out of a decoder is DecodeError.


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
        wire.RetireMessage("r"),
        wire.RetiredMessage("r", "mapserver", "0", True, {"map_revision": 4, "keyframes": 2}),
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


FREE_FORM_MAPS = {"options", "counters", "gauges", "dropped"}  # their keys are data, not schema


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
