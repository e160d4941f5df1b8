"""Retiring a robot: the request a service drops all of a robot's state on, and its answer.

A fleet whose robot ids change keeps each service's `max_robots` places filled with robots that
are gone; retiring one frees its place. The request goes to each service that keeps robot state
on `<prefix>/<robot>/retire/<service>`; every instance that takes it answers with what it
dropped (the gateway's `DELETE /api/v1/robots/{robot}` asks them, in the order the data flows).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import ClassVar

from scanflow.wire.base import Message, check_count, check_robot_id, check_text
from scanflow.wire.errors import MessageError
from scanflow.wire.schema import FLAG, TEXT, Schema, mapping


@dataclass(frozen=True)
class RetireMessage(Message):
    """Drop every piece of state kept for `robot_id`: its place among `max_robots` is free, and
    a message of it that comes later starts it afresh, as a new robot."""

    TYPE = "retire"
    WIRE: ClassVar[Schema] = {"robot_id": TEXT}
    robot_id: str

    def __post_init__(self) -> None:
        check_robot_id(self.robot_id)


@dataclass(frozen=True, eq=False)
class RetiredMessage(Message):
    """One service instance's answer to a RetireMessage: it holds nothing of `robot_id` now.
    `known`: it held some state of the robot (false: nothing to drop); `dropped` counts what
    went, by name (e.g. `map_revision`, `keyframes`, `scans_pending`, `snapshot_files`)."""

    TYPE = "retired"
    WIRE: ClassVar[Schema] = {
        "robot_id": TEXT,
        "service": TEXT,
        "instance": TEXT,
        "known": FLAG,
        "dropped": mapping((int,), "an integer"),
    }
    robot_id: str
    service: str
    instance: str
    known: bool
    dropped: dict[str, int] = field(default_factory=dict)

    def __post_init__(self) -> None:
        check_robot_id(self.robot_id)
        check_text("service", self.service)
        check_text("instance", self.instance)
        if not isinstance(self.known, bool):
            raise MessageError(f"known must be a bool, got {type(self.known).__name__}")
        dropped = {}
        for name, count in self.dropped.items():
            if not isinstance(name, str):
                raise MessageError(f"dropped key {name!r} must be a string")
            dropped[name] = check_count(f"dropped[{name!r}]", count)
        object.__setattr__(self, "dropped", dropped)
