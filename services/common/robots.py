"""How many robots a service keeps state for: a bound, so that messages naming ever new robot
ids (a misconfigured fleet, a faulty client) cannot grow a service's memory without end."""

from __future__ import annotations

from collections.abc import Callable
from typing import Protocol


class RobotLimitError(RuntimeError):
    """A request for a robot the service cannot keep state for (over its max_robots); the
    gateway answers it with 503."""


class Known(Protocol):
    """The robots a service holds (a dict of their state, keyed by id)."""

    def __contains__(self, robot_id: object) -> bool: ...

    def __len__(self) -> int: ...


class RobotLimit:
    """Admits a robot already known, or a new one while fewer than `max_robots` are known;
    refuses the rest, counting each message and reporting each refused id once."""

    def __init__(self, max_robots: int, refused: Callable[[str, bool], None]) -> None:
        if max_robots < 1:
            raise ValueError(f"max_robots must be >= 1, got {max_robots}")
        self.max_robots = max_robots
        self._refused = refused  # (robot id, first time for it)
        self._reported: set[str] = set()

    def admits(self, robot_id: str, known: Known) -> bool:
        """Whether the service may keep state for `robot_id`; a refusal is reported to `refused`."""
        if robot_id in known or len(known) < self.max_robots:
            return True
        first = robot_id not in self._reported and len(self._reported) < self.max_robots
        if first:
            self._reported.add(robot_id)
        self._refused(robot_id, first)
        return False

    def forget(self, robot_id: str) -> None:
        """The robot was retired: a refusal of it later is reported (logged) again."""
        self._reported.discard(robot_id)
