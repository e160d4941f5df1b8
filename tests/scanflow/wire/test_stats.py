"""Service stats: counters are integers >= 0, gauges numbers (+-inf yes, NaN no), refusals name
the counter or gauge, built or decoded."""

from __future__ import annotations

import math
import re
from collections.abc import Callable
from typing import Any

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scanflow import wire
from scanflow.wire import ServiceStatsMessage

FAST = settings.get_profile("wire_fast")  # registered in conftest.py

keys = st.text(min_size=1, max_size=12)


@FAST
@given(key=keys, value=st.integers(max_value=-1))
def test_a_negative_counter_is_refused_naming_it(key: str, value: int) -> None:
    with pytest.raises(wire.MessageError, match=rf"^counters\[{_escaped(key)}\] must be in"):
        ServiceStatsMessage("svc", "0", 0.0, counters={"ok": 1, key: value})


@pytest.mark.parametrize(
    "value", [math.nan, 1.5, 2.0, True, "3", None, np.float64(1.0)], ids=repr
)
def test_a_counter_that_is_not_an_integer_is_refused_naming_it(value: Any) -> None:
    with pytest.raises(wire.MessageError, match=r"^counters\['c'\] must be an integer"):
        ServiceStatsMessage("svc", "0", 0.0, counters={"c": value})


def test_a_counter_past_max_count_is_refused() -> None:
    ServiceStatsMessage("svc", "0", 0.0, counters={"c": wire.MAX_COUNT})
    with pytest.raises(wire.MessageError, match=r"counters\['c'\] must be in \[0, 2\*\*62\]"):
        ServiceStatsMessage("svc", "0", 0.0, counters={"c": wire.MAX_COUNT + 1})


@FAST
@given(key=keys)
def test_a_nan_gauge_is_refused_naming_it(key: str) -> None:
    with pytest.raises(wire.MessageError, match=rf"^gauges\[{_escaped(key)}\] must not be NaN"):
        ServiceStatsMessage("svc", "0", 0.0, gauges={"ok": 1.0, key: math.nan})


@pytest.mark.parametrize("value", [None, True, np.bool_(False), "1", [1.0]], ids=repr)
def test_a_gauge_that_is_not_a_number_is_refused_naming_it(value: Any) -> None:
    with pytest.raises(wire.MessageError, match=r"^gauges\['g'\] must be a number"):
        ServiceStatsMessage("svc", "0", 0.0, gauges={"g": value})


@pytest.mark.parametrize("which", ["counters", "gauges"])
def test_a_key_that_is_not_a_string_is_refused(which: str) -> None:
    with pytest.raises(wire.MessageError, match=rf"^{which} key 1 must be a string"):
        ServiceStatsMessage("svc", "0", 0.0, **{which: {1: 2}})


@pytest.mark.parametrize(
    ("fields", "pattern"),
    [
        ({"service": ""}, "service must be a non-empty string"),
        ({"instance": 0}, "instance must be a non-empty string"),
        ({"stamp_s": math.inf}, "stamp_s must be finite"),
        ({"stamp_s": math.nan}, "stamp_s must be finite"),
    ],
)
def test_service_instance_and_stamp_are_checked(fields: dict[str, Any], pattern: str) -> None:
    with pytest.raises(wire.MessageError, match=pattern):
        ServiceStatsMessage(**{"service": "svc", "instance": "0", "stamp_s": 0.0, **fields})


def test_infinite_gauges_are_allowed_and_come_back_from_the_wire() -> None:
    """An unbounded queue limit is +inf; the gauges keep it, and -inf, through a payload."""
    stats = ServiceStatsMessage("svc", "0", 1.0, {}, {"limit": math.inf, "low": -math.inf})
    assert ServiceStatsMessage.decode(stats.encode()).gauges == {
        "limit": math.inf, "low": -math.inf
    }


def test_counters_are_plain_ints_and_gauges_plain_floats() -> None:
    stats = ServiceStatsMessage(
        "svc", "0", 1, counters={"c": np.int64(3)}, gauges={"i": 4, "u": np.uint8(2)}
    )
    assert [type(v) for v in stats.counters.values()] == [int]
    assert [type(v) for v in stats.gauges.values()] == [float, float]
    assert type(stats.stamp_s) is float


@pytest.mark.parametrize(
    ("changes", "pattern"),
    [
        ({"counters": {"c": -1}}, r"counters\['c'\] must be in"),
        ({"gauges": {"g": math.nan}}, r"gauges\['g'\] must not be NaN"),
        ({"gauges": {"g": True}}, r"gauges\['g'\]: expected a number, got bool"),
        ({"counters": {"c": True}}, r"counters\['c'\]: expected an integer, got bool"),
    ],
)
def test_a_payload_with_a_bad_counter_or_gauge_is_a_schema_error_naming_it(
    changes: dict[str, Any], pattern: str, payload: Callable[..., bytes]
) -> None:
    good = ServiceStatsMessage("svc", "0", 0.0, {"c": 1}, {"g": 1.0})
    with pytest.raises(wire.SchemaError, match=pattern):
        wire.decode_any(payload(good, **changes))


def _escaped(key: str) -> str:
    """The regex of `key` as the error message shows it (its repr)."""
    return re.escape(repr(key))
