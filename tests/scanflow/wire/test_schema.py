"""Field schemas: each codec's exact trip through msgpack, and the field a refusal names."""

from __future__ import annotations

import math
from types import SimpleNamespace
from typing import Any

import msgpack
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp
from scanflow.geometry import Pose2D
from scanflow.wire import SchemaError
from scanflow.wire.codec import Fields
from scanflow.wire.schema import (
    BLOB,
    FLAG,
    INT,
    NUMBER,
    PATH,
    POSE,
    TEXT,
    VECTOR3,
    FieldCodec,
    Schema,
    array,
    decode_fields,
    encode_fields,
    mapping,
    optional,
)

FAST = settings.get_profile("wire_fast")  # registered in conftest.py

ALL: Schema = {
    "text": TEXT,
    "int": INT,
    "number": NUMBER,
    "flag": FLAG,
    "blob": BLOB,
    "pose": POSE,
    "vector": VECTOR3,
    "f4": array("<f4"),
    "maybe": optional(INT),
    "counts": mapping((int,), "an integer"),
}

finite = st.floats(-1e6, 1e6, allow_nan=False)
values = st.fixed_dictionaries({
    "text": st.text(max_size=20),
    "int": st.integers(-(2**63), 2**64 - 1),
    "number": st.floats(allow_nan=False) | st.integers(-(2**53), 2**53),
    "flag": st.booleans(),
    "blob": st.binary(max_size=40),
    "pose": st.builds(Pose2D, finite, finite, st.floats(-10, 10)),
    "vector": st.lists(st.floats(allow_nan=False), min_size=3, max_size=3),
    "f4": hnp.arrays(np.float32, hnp.array_shapes(min_dims=1, max_dims=3, min_side=0, max_side=4)),
    "maybe": st.none() | st.integers(-5, 5),
    "counts": st.dictionaries(st.text(max_size=8), st.integers(0, 100), max_size=5),
})


def _wire(schema: Schema, obj: Any) -> Fields:
    """`obj`'s schema fields encoded, sent through msgpack as a payload is, and read back."""
    packed = msgpack.packb(encode_fields(schema, obj), use_bin_type=True)
    return Fields(msgpack.unpackb(packed, raw=False), "m")


def _decode_one(codec: FieldCodec, value: Any) -> Any:
    """Field `f` of value `value` (as it came off msgpack) read by `codec`."""
    return decode_fields({"f": codec}, Fields({"f": value}, "m"))["f"]


@FAST
@given(values)
def test_every_codec_comes_back_exactly_through_msgpack(fields: dict[str, Any]) -> None:
    back = decode_fields(ALL, _wire(ALL, SimpleNamespace(**fields)))
    assert list(back) == list(ALL)
    f4 = back.pop("f4")
    assert (f4.dtype, f4.shape, f4.tobytes()) == (
        np.dtype("<f4"), fields["f4"].shape, fields["f4"].tobytes()
    )
    assert not f4.flags.writeable  # a read-only view of the payload
    assert back["pose"] == fields["pose"]
    assert back["vector"] == tuple(fields["vector"])
    assert back["number"] == fields["number"] and type(back["number"]) is float
    for name in ("text", "int", "flag", "blob", "maybe", "counts"):
        assert back[name] == fields[name] and type(back[name]) is type(fields[name]), name


def test_encode_fields_reads_only_the_schemas_fields_in_its_order() -> None:
    obj = SimpleNamespace(b=2, a="x", extra="not sent")
    assert list(encode_fields({"b": INT, "a": TEXT}, obj).items()) == [("b", 2), ("a", "x")]
    with pytest.raises(AttributeError, match="missing"):
        encode_fields({"missing": INT}, obj)


def test_numpy_scalars_are_encoded_as_plain_msgpack_values() -> None:
    encoded = encode_fields(
        {"i": INT, "n": NUMBER, "f": FLAG, "v": VECTOR3},
        SimpleNamespace(i=np.int64(3), n=np.float32(0.5), f=np.bool_(True), v=np.zeros(3)),
    )
    assert [type(encoded[k]) for k in "inf"] == [int, float, bool]
    assert isinstance(encoded["v"], list)
    msgpack.packb(encoded)  # nothing numpy left that msgpack would refuse


def test_an_array_travels_as_an_envelope_of_its_wire_dtype() -> None:
    envelope = array("<f4").encode([[1, 2, 3]])
    assert envelope == {"d": "<f4", "s": [1, 3], "b": np.array([1, 2, 3], "<f4").tobytes()}
    assert _decode_one(array("<f4"), envelope).tolist() == [[1.0, 2.0, 3.0]]


def test_optional_is_nil_for_none_but_its_key_must_be_present() -> None:
    maybe = optional(POSE)
    assert maybe.encode(None) is None and _decode_one(maybe, None) is None
    assert _decode_one(maybe, maybe.encode(Pose2D(1.0, 2.0, 0.5))) == Pose2D(1.0, 2.0, 0.5)
    with pytest.raises(SchemaError, match=r"^m\.f: missing$"):
        decode_fields({"f": maybe}, Fields({}, "m"))


def test_a_path_is_two_float64_arrays() -> None:
    path = SimpleNamespace(stamps_s=[0, 1], poses=np.zeros((2, 3), np.float32))
    encoded = encode_fields(PATH, path)
    assert [encoded[k]["d"] for k in ("stamps_s", "poses")] == ["<f8", "<f8"]
    back = decode_fields(PATH, _wire(PATH, path))
    assert back["stamps_s"].dtype == back["poses"].dtype == np.float64


@pytest.mark.parametrize(
    ("codec", "value", "pattern"),
    [
        (TEXT, b"x", r"m\.f: expected a string, got bytes"),
        (INT, True, r"m\.f: expected an integer, got bool"),
        (INT, 1.0, r"m\.f: expected an integer, got float"),
        (NUMBER, False, r"m\.f: expected a number, got bool"),
        (NUMBER, "1", r"m\.f: expected a number, got str"),
        (FLAG, 1, r"m\.f: expected a bool, got int"),
        (BLOB, "x", r"m\.f: expected bytes, got str"),
        (POSE, [0.0, 0.0], r"m\.f: expected a list of 3 numbers"),
        (POSE, [math.nan, 0.0, 0.0], r"m\.f: "),
        (VECTOR3, [0.0, True, 0.0], r"m\.f: expected numbers"),
        (array("<f8"), {"d": "<f4", "s": [0], "b": b""}, r"m\.f\.d: expected dtype '<f8'"),
        (optional(INT), "x", r"m\.f: expected an integer, got str"),
        (mapping((int,), "an integer"), {"k": 1.5}, r"m\.f\['k'\]: expected an integer"),
        (mapping((int,), "an integer"), [1], r"m\.f: expected a map, got list"),
    ],
)
def test_a_wrong_value_is_refused_naming_the_field(
    codec: FieldCodec, value: Any, pattern: str
) -> None:
    with pytest.raises(SchemaError, match=pattern):
        _decode_one(codec, value)


@pytest.mark.parametrize("codec", [TEXT, INT, NUMBER, FLAG, BLOB, POSE, VECTOR3, array("<i8")])
def test_a_missing_field_is_refused_naming_it(codec: FieldCodec) -> None:
    with pytest.raises(SchemaError, match=r"^m\.f: missing$"):
        decode_fields({"f": codec}, Fields({"other": 1}, "m"))
