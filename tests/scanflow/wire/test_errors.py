"""The wire's exceptions: what a caller catches for an unusable payload, and for a bad build."""

from __future__ import annotations

import inspect

import pytest
from scanflow import wire
from scanflow.wire import errors

DECODE_ERRORS = [errors.VersionError, errors.SchemaError, errors.PayloadTooLarge]


@pytest.mark.parametrize("error", DECODE_ERRORS, ids=lambda e: e.__name__)
def test_every_way_a_payload_is_unusable_is_caught_as_a_decode_error(error: type) -> None:
    with pytest.raises(errors.DecodeError):
        raise error("payload.field: wrong")
    assert issubclass(error, ValueError)


def test_the_decode_errors_are_distinct_kinds() -> None:
    """A caller can tell a version mismatch from a bad field from an oversized payload."""
    for error in DECODE_ERRORS:
        assert [other for other in DECODE_ERRORS if issubclass(error, other)] == [error]


def test_building_and_decoding_errors_are_two_value_error_families() -> None:
    """`except DecodeError` around a decode does not hide a service's own bad message, and
    `except ValueError` catches both."""
    assert issubclass(errors.DecodeError, ValueError)
    assert issubclass(errors.MessageError, ValueError)
    assert not issubclass(errors.MessageError, errors.DecodeError)
    assert not issubclass(errors.DecodeError, errors.MessageError)


def test_the_wire_package_exports_every_error_itself() -> None:
    defined = {
        name: cls
        for name, cls in vars(errors).items()
        if inspect.isclass(cls) and issubclass(cls, Exception) and cls.__module__ == errors.__name__
    }
    assert set(defined) == {
        "DecodeError", "VersionError", "SchemaError", "PayloadTooLarge", "MessageError"
    }
    for name, cls in defined.items():
        assert getattr(wire, name) is cls and name in wire.__all__

