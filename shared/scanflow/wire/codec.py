"""msgpack framing, the numpy array envelope and typed field access for untrusted payloads.

A payload is one msgpack map with `type` (str) and `v` (schema version) next to the message's
own fields. Arrays travel as `{"d": dtype, "s": shape, "b": raw little-endian bytes}`, never as
lists of numbers. Unpacking runs under fixed limits so hostile bytes cannot make it hang or
allocate more than the payload's own size.
"""

from __future__ import annotations

import math
import reprlib
from collections.abc import Collection
from typing import Any

import msgpack
import numpy as np
from numpy.typing import ArrayLike, NDArray

from scanflow.geometry import Pose2D
from scanflow.wire.errors import (
    DecodeError,
    MessageError,
    PayloadTooLarge,
    SchemaError,
    VersionError,
)

SCHEMA_VERSION = 10  # 2: no-return points; 3: the sensor `mount`; 4: map redraws; 5: resume;
# 6: an insert says whether it is a keyframe; 7: a matcher's map state; 8: the odometry pose
# of an estimate, and of a resume's last pose; 9: retiring a robot; 10: the tracker's `run`
# on inserts, redraws, map states, resumes and estimates
MAX_PAYLOAD_BYTES = 16 * 1024 * 1024  # any message
# A bulk message (a map, a path, keyframes: it grows with the run) may be this big; it stays
# under Zenoh's own 1 GiB (`transport/link/rx/max_message_size`), so ours is the error seen.
MAX_BULK_BYTES = 512 * 1024 * 1024
_PEEK_BYTES = 256  # holds the map header, the "type" key and any type tag
MAX_STR_BYTES = 64 * 1024
MAX_MAP_LEN = 4096
MAX_ARRAY_LEN = 16
MAX_NDIM = 4
ALLOWED_DTYPES = frozenset({"|i1", "|u1", "<i2", "<u2", "<i4", "<u4", "<i8", "<u8", "<f4", "<f8"})
_DTYPES = {name: np.dtype(name) for name in ALLOWED_DTYPES}
Scalar = bool | int | float | str

_UNPACK_ERRORS = (ValueError, TypeError, OverflowError, msgpack.UnpackException)
_repr = reprlib.Repr()
_repr.maxstring = _repr.maxother = 40
MAX_ERROR_CHARS = 300


def short(value: Any) -> str:
    """A bounded repr: error messages must not echo megabytes of a hostile payload."""
    return _repr.repr(value)


def clip(text: str) -> str:
    """`text` cut to MAX_ERROR_CHARS (with "..."), so an error message stays bounded."""
    return text if len(text) <= MAX_ERROR_CHARS else text[:MAX_ERROR_CHARS] + "..."


def _limit(bulk: bool) -> str:
    return f"MAX_BULK_BYTES={MAX_BULK_BYTES}" if bulk else f"MAX_PAYLOAD_BYTES={MAX_PAYLOAD_BYTES}"


def pack_message(type_name: str, fields: dict[str, Any], bulk: bool = False) -> bytes:
    """The msgpack bytes of one message, its `type` the first key (`unpack_message` reads it
    first); refuses to write what a reader would reject as too big (`bulk`: MAX_BULK_BYTES)."""
    data = msgpack.packb({"type": type_name, "v": SCHEMA_VERSION, **fields}, use_bin_type=True)
    if len(data) > (MAX_BULK_BYTES if bulk else MAX_PAYLOAD_BYTES):
        raise MessageError(f"{type_name} encodes to {len(data)} bytes, over {_limit(bulk)}")
    return data


def unpack_message(data: Any, bulk_types: Collection[str] = ()) -> tuple[str, Fields]:
    """Check size, msgpack syntax, version and type tag; return the type and its fields.

    A payload over MAX_PAYLOAD_BYTES is read only if its first key is a `type` in
    `bulk_types`, and only up to MAX_BULK_BYTES: the tag is read off its first bytes, so other
    big payloads are refused before anything is unpacked."""
    if not isinstance(data, bytes | bytearray | memoryview):
        raise DecodeError(f"payload must be bytes, got {type(data).__name__}")
    view = memoryview(data)
    size = view.nbytes
    if size > MAX_BULK_BYTES:
        raise PayloadTooLarge(f"payload is {size} bytes, over {_limit(True)}")
    if view.itemsize != 1:  # msgpack reads only buffers of bytes
        data = view.tobytes()
    if size > MAX_PAYLOAD_BYTES:
        tag = _leading_type(data)
        if tag not in bulk_types:
            bulky = ", ".join(sorted(bulk_types)) or "none"
            raise PayloadTooLarge(
                f"payload is {size} bytes, over {_limit(False)} (its type {short(tag)} is not "
                f"one that may be bigger: {bulky})"
            )
    if size == 0:
        raise DecodeError("payload is empty")
    try:
        obj = msgpack.unpackb(
            data,
            raw=False,
            strict_map_key=True,
            max_bin_len=MAX_BULK_BYTES,
            max_str_len=MAX_STR_BYTES,
            max_array_len=MAX_ARRAY_LEN,
            max_map_len=MAX_MAP_LEN,
            max_ext_len=0,
        )
    except _UNPACK_ERRORS as exc:
        raise DecodeError(clip(f"payload is not valid msgpack within the limits: {exc}")) from exc
    fields = Fields(obj, "message")
    version = fields.integer("v")
    if version != SCHEMA_VERSION:
        raise VersionError(
            f"message.v: schema version {version} unsupported (this reader: {SCHEMA_VERSION})"
        )
    type_name = fields.text("type")
    if size > MAX_PAYLOAD_BYTES and type_name not in bulk_types:  # a second "type" key
        raise PayloadTooLarge(
            f"payload is {size} bytes, over {_limit(False)} for {short(type_name)}"
        )
    fields.where = type_name
    return type_name, fields


def _leading_type(data: bytes | bytearray | memoryview) -> str | None:
    """The payload's `type` tag if it is the first key of its map (None otherwise), read from
    its first bytes alone."""
    unpacker = msgpack.Unpacker(raw=False, max_buffer_size=_PEEK_BYTES, max_str_len=_PEEK_BYTES)
    unpacker.feed(bytes(memoryview(data)[:_PEEK_BYTES]))
    try:
        unpacker.read_map_header()
        if unpacker.unpack() != "type":
            return None
        tag = unpacker.unpack()
    except (msgpack.OutOfData, *_UNPACK_ERRORS):
        return None
    return tag if isinstance(tag, str) else None


def encode_array(values: ArrayLike, dtype: str) -> dict[str, Any]:
    """The array envelope: dtype string, shape list and raw little-endian bytes."""
    a = np.ascontiguousarray(values, dtype=_DTYPES[dtype])
    return {"d": dtype, "s": list(a.shape), "b": a.tobytes()}


def decode_array(envelope: Any, where: str, dtype: str) -> NDArray[Any]:
    """A read-only array viewing the envelope's bytes, after checking dtype, shape and length."""
    env = Fields(envelope, where)
    found = env.text("d")
    if found not in ALLOWED_DTYPES:
        raise SchemaError(f"{where}.d: dtype {short(found)} is not allowed")
    if found != dtype:
        raise SchemaError(f"{where}.d: expected dtype {dtype!r}, got {found!r}")
    shape = env.get("s")
    if not isinstance(shape, list) or len(shape) > MAX_NDIM:
        raise SchemaError(
            f"{where}.s: expected a list of at most {MAX_NDIM} sizes, got {short(shape)}"
        )
    if not all(type(n) is int and 0 <= n <= MAX_BULK_BYTES for n in shape):
        raise SchemaError(
            f"{where}.s: sizes must be integers in 0..{MAX_BULK_BYTES}, got {short(shape)}"
        )
    raw = env.blob("b")
    itemsize = _DTYPES[dtype].itemsize
    if math.prod(shape) * itemsize != len(raw):
        raise SchemaError(
            f"{where}.b: {len(raw)} bytes do not fit shape {shape} of {dtype} "
            f"({itemsize} bytes each)"
        )
    return np.frombuffer(raw, dtype=_DTYPES[dtype]).reshape(shape)


def encode_pose(pose: Pose2D) -> list[float]:
    """A pose as the wire's [x, y, theta] list (`Fields.pose` reads it back)."""
    return [pose.x, pose.y, pose.theta]


class Fields:
    """Typed, named access to one decoded msgpack map; any mismatch is a SchemaError naming it."""

    def __init__(self, data: Any, where: str) -> None:
        if not isinstance(data, dict):
            raise SchemaError(f"{where}: expected a map, got {type(data).__name__}")
        self.data = data
        self.where = where

    def get(self, name: str) -> Any:
        """The raw value of field `name`; SchemaError when it is missing."""
        if name not in self.data:
            raise SchemaError(f"{self.where}.{name}: missing")
        return self.data[name]

    def _typed(self, name: str, types: tuple[type, ...], what: str) -> Any:
        value = self.get(name)
        if type(value) not in types:
            raise SchemaError(
                f"{self.where}.{name}: expected {what}, got {type(value).__name__} {short(value)}"
            )
        return value

    def is_nil(self, name: str) -> bool:
        """True when field `name` is nil (None); SchemaError when it is missing."""
        return self.get(name) is None

    def text(self, name: str) -> str:
        """A str."""
        return self._typed(name, (str,), "a string")

    def integer(self, name: str) -> int:
        """An int (a bool is refused)."""
        return self._typed(name, (int,), "an integer")

    def number(self, name: str) -> float:
        """An int or float (never a bool), as float; finiteness is the message's to check."""
        return float(self._typed(name, (int, float), "a number"))

    def flag(self, name: str) -> bool:
        """A bool (0 and 1 are refused)."""
        return self._typed(name, (bool,), "a bool")

    def blob(self, name: str) -> bytes:
        """A bytes value (msgpack bin)."""
        return self._typed(name, (bytes,), "bytes")

    def array(self, name: str, dtype: str) -> NDArray[Any]:
        """The array envelope in field `name`, decoded read-only (`decode_array`) as `dtype`."""
        return decode_array(self.get(name), f"{self.where}.{name}", dtype)

    def nested(self, name: str) -> Fields:
        """The map in field `name` as Fields, its errors named `where.name`."""
        return Fields(self.get(name), f"{self.where}.{name}")

    def numbers(self, name: str, count: int) -> tuple[float, ...]:
        """A fixed-length list of numbers, e.g. a pose or a velocity."""
        value = self.get(name)
        if not isinstance(value, list) or len(value) != count:
            raise SchemaError(f"{self.where}.{name}: expected a list of {count} numbers")
        if not all(type(v) in (int, float) for v in value):
            raise SchemaError(f"{self.where}.{name}: expected numbers, got {short(value)}")
        return tuple(float(v) for v in value)

    def pose(self, name: str) -> Pose2D:
        """A Pose2D from [x, y, theta]; SchemaError unless 3 finite numbers."""
        x, y, theta = self.numbers(name, 3)
        try:
            return Pose2D(x, y, theta)
        except ValueError as exc:
            raise SchemaError(f"{self.where}.{name}: {exc}") from exc

    def mapping(self, name: str, types: tuple[type, ...], what: str) -> dict[str, Any]:
        """A str-keyed map whose values have one of `types` exactly (bool is not an int here)."""
        value = self.get(name)
        if not isinstance(value, dict):
            raise SchemaError(f"{self.where}.{name}: expected a map, got {type(value).__name__}")
        for key, item in value.items():
            if type(key) is not str:
                raise SchemaError(f"{self.where}.{name}: key {short(key)} is not a string")
            if type(item) not in types:
                raise SchemaError(
                    f"{self.where}.{name}[{short(key)}]: expected {what}, got {type(item).__name__}"
                )
        return value
