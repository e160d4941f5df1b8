"""The message base class (encode, decode, the type registry) and field checks for constructors.

Every message validates its fields when built, so decoding a payload is: unpack, read typed
fields, construct. A constructor's ValueError on decoded data surfaces as a chained SchemaError.
"""

from __future__ import annotations

import math
import operator
import secrets
from typing import Any, ClassVar, Self

import numpy as np
from numpy.typing import ArrayLike, NDArray

from scanflow import keys
from scanflow.geometry import Pose2D
from scanflow.wire.codec import (
    MAX_STR_BYTES,
    Fields,
    clip,
    pack_message,
    short,
    unpack_message,
)
from scanflow.wire.errors import DecodeError, MessageError, SchemaError
from scanflow.wire.schema import Schema, decode_fields, encode_fields

_REGISTRY: dict[str, type[Message]] = {}
_BULK: set[str] = set()  # the types that may be up to MAX_BULK_BYTES


class Message:
    """A frozen dataclass that knows its wire `TYPE` tag and its field schema `WIRE`.

    The default codec writes and reads exactly the fields listed in `WIRE`; messages that wrap
    another type (a LaserScan, an Odometry) override `to_fields` / `from_fields`.
    """

    TYPE: ClassVar[str]
    WIRE: ClassVar[Schema]
    # A map, a path or keyframes grows with the run: up to MAX_BULK_BYTES, not MAX_PAYLOAD_BYTES.
    BULK: ClassVar[bool] = False

    def __init_subclass__(cls, **kwargs: Any) -> None:
        super().__init_subclass__(**kwargs)
        if cls.TYPE in _REGISTRY:
            raise TypeError(f"wire type {cls.TYPE!r} is registered twice")
        _REGISTRY[cls.TYPE] = cls
        if cls.BULK:
            _BULK.add(cls.TYPE)

    def to_fields(self) -> dict[str, Any]:
        """The message's own fields as msgpack-ready values (arrays as envelopes)."""
        return encode_fields(self.WIRE, self)

    @classmethod
    def from_fields(cls, fields: Fields) -> Self:
        """Build the message from typed fields read off a payload."""
        return cls(**decode_fields(cls.WIRE, fields))

    def encode(self) -> bytes:
        """The msgpack payload; MessageError over MAX_PAYLOAD_BYTES (MAX_BULK_BYTES if BULK)."""
        return pack_message(self.TYPE, self.to_fields(), self.BULK)

    @classmethod
    def decode(cls, data: bytes | bytearray | memoryview) -> Self:
        """Decode a payload that must hold this message type; raises DecodeError otherwise."""
        type_name, fields = unpack_message(data, _BULK)
        if type_name != cls.TYPE:
            raise SchemaError(f"message.type: expected {cls.TYPE!r}, got {short(type_name)}")
        return cls.build(fields)

    @classmethod
    def build(cls, fields: Fields) -> Self:
        """The message from decoded fields; a constructor's ValueError becomes a SchemaError."""
        try:
            return cls.from_fields(fields)
        except DecodeError:
            raise
        except ValueError as exc:
            raise SchemaError(clip(f"{fields.where}: {exc}")) from exc


def decode_any(data: bytes | bytearray | memoryview) -> Message:
    """Decode any scanflow message, dispatching on its `type` field."""
    type_name, fields = unpack_message(data, _BULK)
    cls = _REGISTRY.get(type_name)
    if cls is None:
        known = ", ".join(sorted(_REGISTRY))
        raise SchemaError(f"message.type: unknown type {short(type_name)} (known: {known})")
    return cls.build(fields)


def message_types() -> dict[str, type[Message]]:
    """Every registered message class by its wire type tag."""
    return dict(_REGISTRY)


def check_finite(name: str, value: float) -> float:
    """`value` as a float; MessageError naming `name` when it is not finite."""
    value = float(value)
    if not math.isfinite(value):
        raise MessageError(f"{name} must be finite, got {value!r}")
    return value


MAX_POSITION_M = 1e6  # an operator's pose, odometry: no map is larger (the gateway bounds the same)
MAX_COUNT = 2**62  # seqs and counts: int64 with room to add one (snapshots, numpy arrays)


ENDED_RUNS_KEPT = 16  # a reader of estimates or inserts drops late ones of its last replaced runs


def new_run() -> int:
    """A fresh run token: random, non-zero, a count on the wire. A tracker draws one when it
    starts a robot afresh; its inserts, redraws, map states and estimates carry it, so that a
    map server tells a new run from a gap in the old one (seqs alone cannot: a server that
    missed a run's first scans sees its seqs go on past the old run's)."""
    return secrets.randbelow(MAX_COUNT) + 1


def check_count(name: str, value: int) -> int:
    """An integer in [0, MAX_COUNT] (numpy integers welcome, bools and floats refused)."""
    if isinstance(value, bool):
        raise MessageError(f"{name} must be an integer, got {value!r}")
    try:
        value = operator.index(value)
    except TypeError:
        raise MessageError(f"{name} must be an integer, got {value!r}") from None
    if not 0 <= value <= MAX_COUNT:
        raise MessageError(f"{name} must be in [0, 2**62], got {value}")
    return value


def check_pose(name: str, value: Any) -> Pose2D:
    """`value` itself when it is a Pose2D, else MessageError naming `name`."""
    if not isinstance(value, Pose2D):
        raise MessageError(f"{name} must be a Pose2D, got {type(value).__name__}")
    return value


def check_position(name: str, pose: Pose2D) -> Pose2D:
    """`pose` when it lies within +-MAX_POSITION_M, else MessageError naming `name`: a pose
    further out is its source's fault, and differences of such poses overflow to inf."""
    if max(abs(pose.x), abs(pose.y)) > MAX_POSITION_M:
        raise MessageError(f"{name} ({pose.x}, {pose.y}) m is beyond +-{MAX_POSITION_M:g} m")
    return pose


def check_text(name: str, value: str, allow_empty: bool = False) -> str:
    """`value` when it is a string, non-empty unless `allow_empty`, and one a reader takes (at
    most MAX_STR_BYTES in UTF-8); else MessageError."""
    if not isinstance(value, str) or (not value and not allow_empty):
        raise MessageError(
            f"{name} must be a {'' if allow_empty else 'non-empty '}string, got {short(value)}"
        )
    # 4 bytes per character at most: only a long string is encoded to be measured.
    if len(value) * 4 > MAX_STR_BYTES and len(value.encode()) > MAX_STR_BYTES:
        raise MessageError(f"{name} is over MAX_STR_BYTES={MAX_STR_BYTES} bytes in UTF-8")
    return value


def check_robot_id(value: str) -> str:
    """A robot id as keys take it (`scanflow.keys.check_robot_id`): a decoded message cannot
    name a robot whose keys would be wildcards ('*'), paths ('a/b', '..') or service keys."""
    check_text("robot_id", value)
    try:
        return keys.check_robot_id(value)
    except keys.KeyExprError as error:
        raise MessageError(str(error)) from None


def check_bytes(name: str, value: Any) -> bytes:
    """A blob (bytes, bytearray or memoryview), as bytes."""
    if not isinstance(value, bytes | bytearray | memoryview):
        raise MessageError(f"{name} must be bytes, got {type(value).__name__}")
    return bytes(value)


def check_path(message: Any) -> None:
    """Check and set a message's `stamps_s` (N,) and `poses` (N, 3): a robot's path."""
    stamps = check_array("stamps_s", message.stamps_s, np.float64, (None,))
    poses = check_array("poses", message.poses, np.float64, (len(stamps), 3))
    object.__setattr__(message, "stamps_s", stamps)
    object.__setattr__(message, "poses", poses)


def check_array(
    name: str,
    values: ArrayLike,
    dtype: type[np.generic],
    shape: tuple[int | None, ...],
    finite: bool = True,
    allow_inf: bool = False,
) -> NDArray[Any]:
    """`values` as `dtype` with the given shape (None: any size), optionally free of NaN/inf."""
    a = np.asarray(values, dtype=dtype)
    if a.ndim != len(shape) or any(
        n is not None and n != m for n, m in zip(shape, a.shape, strict=True)
    ):
        want = "(" + ", ".join("N" if n is None else str(n) for n in shape) + ")"
        raise MessageError(f"{name} must have shape {want}, got {a.shape}")
    if finite and a.dtype.kind == "f":
        bad = np.isnan(a) if allow_inf else ~np.isfinite(a)
        if bad.any():
            what = "NaN" if allow_inf else "non-finite values"
            raise MessageError(
                f"{name} contains {what} (first at flat index {int(np.argmax(bad))})"
            )
    return a


def check_seqs(name: str, values: ArrayLike) -> NDArray[np.int64]:
    """Scan seqs of a list of keyframes: int64, >= 0 and strictly increasing."""
    seqs = check_array(name, values, np.int64, (None,))
    # Neighbours compared, not differenced: np.diff wraps around int64 (1 then -2**63).
    if seqs.size and (seqs[0] < 0 or np.any(seqs[1:] <= seqs[:-1])):
        raise MessageError(f"{name} must be >= 0 and strictly increasing")
    return seqs
