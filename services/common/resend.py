"""The resend query, made by a map server that missed inserts and answered by the robot's
matcher: `keys.map_key(robot, "resend")` with `?after=A;through=B` asks for the inserts with seqs
above A (-1: from the run's first) up to and including B, in order (see
services.matcher.recent)."""

from __future__ import annotations

import zenoh

FIRST = -1  # `after` for "from the run's first insert"


def resend_range(parameters: zenoh.Parameters) -> tuple[int, int]:
    """(after, through) from a resend query's parameters; ValueError naming a bad one."""
    values = []
    for name in ("after", "through"):
        text = parameters.get(name)
        try:
            value = int(text) if text is not None else None
        except ValueError:
            value = None
        if value is None or value < FIRST:
            raise ValueError(f"a resend query needs {name}=<seq> (an integer >= -1), got {text!r}")
        values.append(value)
    after, through = values
    if through <= after:
        raise ValueError(f"a resend query needs through > after, got {after}..{through}")
    return after, through


def resend_selector(key: str, after: int, through: int) -> str:
    """The query for the inserts after `after` through `through` on a robot's resend key."""
    return f"{key}?after={after};through={through}"
