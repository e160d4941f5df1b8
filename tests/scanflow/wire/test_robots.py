"""Retiring a robot: the request and each service's answer, built or decoded; a malformed one is
refused naming the field."""

from __future__ import annotations

import re
from collections.abc import Callable
from typing import Any

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scanflow import keys, wire
from scanflow.wire import RetiredMessage, RetireMessage

FAST = settings.get_profile("wire_fast")  # registered in conftest.py

ids = st.from_regex(r"\A[A-Za-z0-9_.-]{1,12}\Z").filter(
    lambda v: v.strip(".") and v not in keys.RESERVED_ROBOT_IDS
)
names = st.text(min_size=1, max_size=12)
counts = st.integers(0, wire.MAX_COUNT)


@FAST
@given(robot=ids, service=names, instance=names, known=st.booleans(),
       dropped=st.dictionaries(names, counts, max_size=6))
def test_an_answer_comes_back_from_the_wire_as_it_was_sent(
    robot: str, service: str, instance: str, known: bool, dropped: dict[str, int]
) -> None:
    answer = RetiredMessage(robot, service, instance, known, dropped)
    back = wire.decode_any(answer.encode())
    assert isinstance(back, RetiredMessage)
    assert (back.robot_id, back.service, back.instance, back.known, back.dropped) == (
        robot, service, instance, known, dropped)
    assert RetireMessage.decode(RetireMessage(robot).encode()) == RetireMessage(robot)


@FAST
@given(robot=st.sampled_from(["", "a/b", "*", "..", "health", "stats", "x" * 65]))
def test_a_robot_id_no_key_can_carry_is_refused_built_or_decoded(
    robot: str, payload: Callable[..., bytes]
) -> None:
    with pytest.raises(wire.MessageError, match=r"robot id|robot_id"):
        RetireMessage(robot)
    with pytest.raises(wire.SchemaError, match=r"^retire: .*robot"):
        RetireMessage.decode(payload(RetireMessage("r"), robot_id=robot))
    with pytest.raises(wire.SchemaError, match=r"^retired: .*robot"):
        RetiredMessage.decode(payload(RetiredMessage("r", "deskew", "0", False), robot_id=robot))


@FAST
@given(key=names, value=st.integers(max_value=-1) | st.integers(min_value=wire.MAX_COUNT + 1))
def test_a_count_out_of_range_is_refused_naming_it(key: str, value: int) -> None:
    pattern = rf"^dropped\[{re.escape(repr(key))}\] must be in"
    with pytest.raises(wire.MessageError, match=pattern):
        RetiredMessage("r", "deskew", "0", True, {"ok": 1, key: value})


ANSWER = RetiredMessage("r", "matcher", "1", True, {"map_revision": 3})


@pytest.mark.parametrize(
    ("changes", "pattern"),
    [
        ({"known": 1}, r"retired\.known: expected a bool, got int"),
        ({"known": ...}, r"retired\.known: missing"),
        ({"dropped": {"a": True}}, r"retired\.dropped\['a'\]: expected an integer, got bool"),
        ({"dropped": {"a": 1.0}}, r"retired\.dropped\['a'\]: expected an integer, got float"),
        ({"dropped": {"a": -1}}, r"retired: dropped\['a'\] must be in"),
        ({"dropped": [1]}, r"retired\.dropped: expected a map, got list"),
        ({"service": ""}, r"retired: service must be a non-empty string"),
        ({"instance": 0}, r"retired\.instance: expected a string, got int"),
        ({"robot_id": ...}, r"retired\.robot_id: missing"),
        ({"type": "scan"}, r"message\.type: expected 'retired', got 'scan'"),
    ],
)
def test_a_malformed_answer_is_a_schema_error_naming_the_field(
    changes: dict[str, Any], pattern: str, payload: Callable[..., bytes]
) -> None:
    with pytest.raises(wire.DecodeError, match=pattern):
        RetiredMessage.decode(payload(ANSWER, **changes))


def test_an_answer_is_not_a_request_nor_the_other_way_round() -> None:
    with pytest.raises(wire.SchemaError, match="expected 'retire', got 'retired'"):
        RetireMessage.decode(ANSWER.encode())
    with pytest.raises(wire.SchemaError, match="expected 'retired', got 'retire'"):
        RetiredMessage.decode(RetireMessage("r").encode())


@pytest.mark.parametrize("known", [1, None, "yes"], ids=repr)
def test_known_must_be_a_bool_when_built(known: Any) -> None:
    with pytest.raises(wire.MessageError, match="known must be a bool"):
        RetiredMessage("r", "deskew", "0", known)
