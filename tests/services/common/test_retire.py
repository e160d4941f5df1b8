"""The retire request as a service reads it off a query, and the reply the outbox sends."""

from __future__ import annotations

from types import SimpleNamespace

import pytest
from scanflow import keys, wire
from scanflow.geometry import Pose2D
from scanflow.wire import RetireMessage

from services.common.retire import RETIRING, QueryReply, retire_request


def query(key: str, payload: bytes | None) -> SimpleNamespace:
    return SimpleNamespace(
        key_expr=key, payload=None if payload is None else SimpleNamespace(to_bytes=lambda: payload)
    )


def test_a_retire_query_names_its_robot_on_its_robots_key() -> None:
    key = keys.retire("r1", "deskew", "site/sf")
    assert retire_request(query(key, RetireMessage("r1").encode()), "deskew", "site/sf") == "r1"


@pytest.mark.parametrize(
    ("key", "payload", "error", "pattern"),
    [
        (keys.retire("r1", "deskew"), None, ValueError, "needs a RetireMessage payload"),
        (keys.retire("r1", "deskew"), b"\x00junk", wire.DecodeError, "payload"),
        (keys.retire("r1", "deskew"), RetireMessage("r2").encode(), ValueError,
         "retiring 'r2' from deskew must be asked on scanflow/r2/retire/deskew"),
        (keys.retire("*", "deskew"), RetireMessage("r1").encode(), ValueError, "must be asked on"),
        (keys.retire("r1", "deskew"), wire.InitialPoseMessage("r1", Pose2D()).encode(),
         wire.SchemaError, "expected 'retire', got 'initial_pose'"),
    ],
)
def test_a_bad_retire_query_is_refused_naming_why(key, payload, error, pattern) -> None:
    with pytest.raises(error, match=pattern):
        retire_request(query(key, payload), "deskew", keys.DEFAULT_PREFIX)


class Query:
    def __init__(self) -> None:
        self.calls: list[tuple] = []

    def reply(self, key: str, payload: bytes) -> None:
        self.calls.append(("reply", key, payload))

    def reply_err(self, text: str) -> None:
        self.calls.append(("error", text))

    def drop(self) -> None:
        self.calls.append(("drop",))


def test_the_outbox_sends_the_reply_and_finishes_the_query() -> None:
    q = Query()
    QueryReply(q, "k").put(b"answer", timestamp=object())  # a publisher's options: ignored
    assert q.calls == [("reply", "k", b"answer"), ("drop",)]
    q = Query()
    QueryReply(q, "k").refuse("busy")
    assert q.calls == [("error", "busy"), ("drop",)]


def test_the_services_are_retired_in_the_order_the_data_flows() -> None:
    assert RETIRING == ("deskew", "matcher", "mapserver")
