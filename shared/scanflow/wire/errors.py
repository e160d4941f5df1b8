"""The exceptions of the wire format: one family for every way a payload can be unusable."""

from __future__ import annotations


class DecodeError(ValueError):
    """Bytes that are not a valid scanflow message; the message names the field at fault."""


class VersionError(DecodeError):
    """A message written with a schema version this reader does not speak."""


class SchemaError(DecodeError):
    """A field that is missing, of the wrong type or shape, or has a forbidden value."""


class PayloadTooLarge(DecodeError):  # noqa: N818 (name set by the issue)
    """A payload (or a part of it) over the size limits; rejected before it is unpacked."""


class MessageError(ValueError):
    """A message built with inconsistent fields (raised when constructing, not decoding)."""
