"""Every Zenoh key expression scanflow uses: the one place to read or change them.

Layout (``<prefix>`` defaults to ``scanflow``; ``<robot>`` is a robot id):

| key                                   | kind       | payload (scanflow.wire)        |
|---------------------------------------|------------|--------------------------------|
| <prefix>/<robot>/scan/raw             | pub/sub    | ScanMessage                    |
| <prefix>/<robot>/odom                 | pub/sub    | OdometryMessage                |
| <prefix>/<robot>/scan/deskewed        | pub/sub    | DeskewedScanMessage            |
| <prefix>/<robot>/pose                 | pub/sub    | PoseEstimateMessage            |
| <prefix>/<robot>/match                | queryable  | MatchRequest -> MatchResponse  |
| <prefix>/<robot>/map/meta             | queryable  | MapMetaMessage                 |
| <prefix>/<robot>/map/image            | queryable  | MapImageMessage (png/pgm/yaml) |
| <prefix>/<robot>/map/region           | queryable  | MapRegionMessage               |
| <prefix>/<robot>/map/changed          | pub/sub    | MapChangedMessage              |
| <prefix>/<robot>/trajectory           | queryable  | TrajectoryMessage              |
| <prefix>/match                        | queryable  | MatchRequest (scan-to-scan)    |
| <prefix>/health/<service>/<instance>  | liveliness | (token, no payload)            |
| <prefix>/stats/<service>/<instance>   | queryable  | ServiceStatsMessage            |
"""

from __future__ import annotations

import re

DEFAULT_PREFIX = "scanflow"
_ID_RE = re.compile(r"^[A-Za-z0-9_\-.]{1,64}$")


class KeyExprError(ValueError):
    """A robot id or service name that cannot be part of a key expression."""


def check_id(value: str, what: str = "robot id") -> str:
    """Ids become key chunks: letters, digits, '_', '-', '.', at most 64 characters."""
    if not isinstance(value, str) or not _ID_RE.match(value):
        raise KeyExprError(
            f"{what} {value!r} is invalid: use 1-64 letters, digits, '_', '-' or '.'"
        )
    return value


def raw_scan(robot: str = "*", prefix: str = DEFAULT_PREFIX) -> str:
    return _key(robot, "scan/raw", prefix)


def odom(robot: str = "*", prefix: str = DEFAULT_PREFIX) -> str:
    return _key(robot, "odom", prefix)


def deskewed_scan(robot: str = "*", prefix: str = DEFAULT_PREFIX) -> str:
    return _key(robot, "scan/deskewed", prefix)


def pose(robot: str = "*", prefix: str = DEFAULT_PREFIX) -> str:
    return _key(robot, "pose", prefix)


def robot_match(robot: str = "*", prefix: str = DEFAULT_PREFIX) -> str:
    return _key(robot, "match", prefix)


def scan_match(prefix: str = DEFAULT_PREFIX) -> str:
    return f"{prefix}/match"


def map_key(robot: str = "*", what: str = "meta", prefix: str = DEFAULT_PREFIX) -> str:
    return _key(robot, f"map/{what}", prefix)


def trajectory(robot: str = "*", prefix: str = DEFAULT_PREFIX) -> str:
    return _key(robot, "trajectory", prefix)


def health(service: str = "*", instance: str = "*", prefix: str = DEFAULT_PREFIX) -> str:
    return f"{prefix}/health/{_chunk(service, 'service')}/{_chunk(instance, 'instance')}"


def stats(service: str = "*", instance: str = "*", prefix: str = DEFAULT_PREFIX) -> str:
    return f"{prefix}/stats/{_chunk(service, 'service')}/{_chunk(instance, 'instance')}"


def robot_of(key: str, prefix: str = DEFAULT_PREFIX) -> str:
    """The robot id in a concrete per-robot key."""
    parts = str(key).split("/")
    if len(parts) < 3 or parts[0] != prefix:
        raise KeyExprError(f"key {key!r} is not a per-robot key under {prefix!r}")
    return check_id(parts[1])


def _chunk(value: str, what: str) -> str:
    return value if value == "*" else check_id(value, what)


def _key(robot: str, suffix: str, prefix: str) -> str:
    return f"{prefix}/{_chunk(robot, 'robot id')}/{suffix}"
