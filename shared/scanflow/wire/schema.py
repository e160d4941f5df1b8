"""Declarative field schemas: each message lists its fields once with a codec per field.

A schema is a dict `field name -> FieldCodec`; `encode_fields` reads those attributes off an
object into msgpack-ready values and `decode_fields` reads them back, typed, from a payload.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, NamedTuple

from scanflow.wire.codec import Fields, encode_array, encode_pose


class FieldCodec(NamedTuple):
    """How one field goes to msgpack (`encode`) and comes back checked (`decode(fields, name)`)."""

    encode: Callable[[Any], Any]
    decode: Callable[[Fields, str], Any]


Schema = dict[str, FieldCodec]


def _same(value: Any) -> Any:
    return value


def _vector3(fields: Fields, name: str) -> tuple[float, ...]:
    return fields.numbers(name, 3)


TEXT = FieldCodec(_same, Fields.text)
INT = FieldCodec(int, Fields.integer)
NUMBER = FieldCodec(float, Fields.number)
FLAG = FieldCodec(bool, Fields.flag)
BLOB = FieldCodec(bytes, Fields.blob)
POSE = FieldCodec(encode_pose, Fields.pose)
VECTOR3 = FieldCodec(list, _vector3)


def array(dtype: str) -> FieldCodec:
    """A numpy array sent in the envelope with wire dtype `dtype` (e.g. "<f4")."""
    return FieldCodec(
        lambda value: encode_array(value, dtype),
        lambda fields, name: fields.array(name, dtype),
    )


# A robot's path, `poses[i]` (x, y, theta) at `stamps_s[i]` (checked by base.check_path).
PATH: Schema = {"stamps_s": array("<f8"), "poses": array("<f8")}


def optional(codec: FieldCodec) -> FieldCodec:
    """`codec`, or nil for None (the key itself must still be present)."""
    return FieldCodec(
        lambda value: None if value is None else codec.encode(value),
        lambda fields, name: None if fields.is_nil(name) else codec.decode(fields, name),
    )


def mapping(types: tuple[type, ...], what: str) -> FieldCodec:
    """A str-keyed map whose values have exactly one of `types`."""
    return FieldCodec(dict, lambda fields, name: fields.mapping(name, types, what))


def encode_fields(schema: Schema, obj: Any) -> dict[str, Any]:
    """Each schema field read off `obj` (an attribute of that name) and encoded by its codec."""
    return {name: codec.encode(getattr(obj, name)) for name, codec in schema.items()}


def decode_fields(schema: Schema, fields: Fields) -> dict[str, Any]:
    """Each schema field read, typed and checked, off `fields`: the constructor's keywords."""
    return {name: codec.decode(fields, name) for name, codec in schema.items()}
