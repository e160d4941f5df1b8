"""Retiring a robot: every service that keeps state for it drops all of it, so that its place
among the service's `max_robots` is free (a fleet whose robot ids change over months).

The request (`RetireMessage`) comes on `<prefix>/<robot>/retire/<service>` (keys.retire). The
shell hands it to the service's worker through the inbox, behind every message that came
before it, so the worker drops the robot between two messages, the one thread that owns its
state (`ServiceShell.serve_retire`); the answer (`RetiredMessage`) leaves through the outbox,
behind everything the worker published before the drop. The gateway asks the services one
after the other in the order the data flows (RETIRING): what one service sent of the robot
before it dropped it reaches the next before that one's own retire, and cannot start the robot
again there. A message of the robot that comes later starts it afresh, as a new robot.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import zenoh
from scanflow import keys
from scanflow.wire import RetireMessage

# The services that keep robot state, in the order the data flows through them.
RETIRING = ("deskew", "matcher", "mapserver")


@dataclass
class Dropped:
    """What a service dropped of a robot: `known`, it held something of it; `counts` by name."""

    known: bool
    counts: dict[str, int] = field(default_factory=dict)


def retire_request(query: zenoh.Query, service: str, prefix: str) -> str:
    """The robot a retire query names: its RetireMessage's, which must be the one its key
    names (ValueError, or a DecodeError, naming what is wrong)."""
    payload = query.payload
    if payload is None:
        raise ValueError("a retire query needs a RetireMessage payload")
    robot_id = RetireMessage.decode(payload.to_bytes()).robot_id
    key = keys.retire(robot_id, service, prefix)
    if str(query.key_expr) != key:
        raise ValueError(f"retiring {robot_id!r} from {service} must be asked on {key}")
    return robot_id


class QueryReply:
    """A query's reply handed to the outbox as if it were a publisher: it leaves after every
    put queued before it, and the query is final once it has."""

    def __init__(self, query: zenoh.Query, key: str) -> None:
        self.query = query
        self.key = key

    def put(self, payload: bytes, **_options: Any) -> None:
        """Reply with `payload` on `key` and finish the query (the outbox's put options, a
        timestamp, are a publisher's)."""
        try:
            self.query.reply(self.key, payload)
        finally:
            self.query.drop()

    def refuse(self, reason: str) -> None:
        """Finish the query with an error reply instead."""
        try:
            self.query.reply_err(reason)
        finally:
            self.query.drop()
