"""Shared by the wire tests: a scan message, a payload re-packer and the FAST hypothesis profile."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import msgpack
import numpy as np
import pytest
from hypothesis import HealthCheck, settings
from scanflow import wire
from scanflow.scan import LaserScan

# A settings decorator is needed at decoration time, where no fixture reaches: the test files
# take it as `FAST = settings.get_profile("wire_fast")` (conftest.py is loaded before them).
settings.register_profile(
    "wire_fast", max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow]
)


def _payload(msg: wire.Message, **changes: Any) -> bytes:
    """`msg` re-packed with top-level fields replaced (a value of ... deletes the field)."""
    obj = msgpack.unpackb(msg.encode())
    for key, value in changes.items():
        if value is ...:
            del obj[key]
        else:
            obj[key] = value
    return msgpack.packb(obj)


@pytest.fixture(scope="session")
def payload() -> Callable[..., bytes]:
    """`payload(msg, **changes)`: `msg` re-packed with top-level fields replaced (a value of
    ... deletes the field), to feed a decoder a payload that is wrong in one field."""
    return _payload


@pytest.fixture(scope="session")
def scan_message() -> wire.ScanMessage:
    """A three-beam scan message of robot "r1", its middle range NaN (a masked beam)."""
    return wire.ScanMessage(LaserScan(np.array([1.0, np.nan, 3.0]), 0.0, 0.1, robot_id="r1"))
