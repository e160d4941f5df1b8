"""Every Zenoh key expression scanflow uses: the one place to read or change them.

Layout (``<prefix>`` defaults to ``scanflow``; ``<robot>`` is a robot id):

| key                                   | kind       | payload (scanflow.wire)        |
|---------------------------------------|------------|--------------------------------|
| <prefix>/<robot>/scan/raw             | pub/sub    | ScanMessage                    |
| <prefix>/<robot>/odom                 | pub/sub    | OdometryMessage                |
| <prefix>/<robot>/scan/deskewed        | pub/sub    | DeskewedScanMessage            |
| <prefix>/<robot>/pose                 | pub/sub    | PoseEstimateMessage            |
| <prefix>/<robot>/match                | queryable  | MatchRequest -> MatchResponse  |
| <prefix>/<robot>/initial_pose         | queryable  | InitialPoseMessage (echoed)    |
| <prefix>/<robot>/map/meta             | queryable  | MapMetaMessage                 |
| <prefix>/<robot>/map/image            | queryable  | MapImageMessage (png/pgm/yaml) |
| <prefix>/<robot>/map/region           | queryable  | MapRegionMessage               |
| <prefix>/<robot>/map/changed          | pub/sub    | MapChangedMessage              |
| <prefix>/<robot>/map/insert           | pub/sub    | MapInsertMessage (**), or      |
|                                       |            | MapRedrawMessage (loop closure)|
| <prefix>/<robot>/map/resume           | queryable  | ResumeMessage (map server)     |
| <prefix>/<robot>/map/resend           | queryable  | MapInsertMessage... (matcher)  |
| <prefix>/<robot>/trajectory           | queryable  | TrajectoryMessage              |
| <prefix>/<robot>/retire/<service>     | queryable  | RetireMessage -> RetiredMessage|
|                                       |            | (one per instance) (***)       |
| <prefix>/match                        | queryable  | MatchRequest (scan-to-scan)    |
| <prefix>/health/<service>/<instance>  | liveliness | (token, no payload)            |
| <prefix>/stats/<service>/<instance>   | queryable  | ServiceStatsMessage            |

Zenoh keeps publication order only within one subscriber, and a full inbox stops a
session's whole link: every service subscribes to exactly the keys it consumes, and no service
relies on the order of two keys (see docs/services.md).

(**) the scans the matcher's front end inserted into its map, each with the pose it went in at;
the map server inserts the same points at the same pose, so its map equals the front end's.
Each names the insert before it; a map server that missed some asks the matcher for them again
on `map/resend?after=A;through=B` (services.common.resend).

(***) every service that keeps robot state (deskew, matcher, mapserver) drops all of the
robot's and answers with what it dropped; the gateway asks them one service after the other,
in the order the data flows (services.common.retire).

Ids are single chunks (see `check_id`); a prefix may span several chunks ("site1/scanflow").
Robot ids "health" and "stats" are reserved: their keys would collide with the service keys.
"""

from __future__ import annotations

import re

DEFAULT_PREFIX = "scanflow"
_ID_RE = re.compile(r"^[A-Za-z0-9_\-.]{1,64}$")
# A robot with one of these ids would share keys with the per-service keys below the prefix.
RESERVED_ROBOT_IDS = frozenset({"health", "stats"})


class KeyExprError(ValueError):
    """A robot id or service name that cannot be part of a key expression."""


def check_id(value: str, what: str = "robot id") -> str:
    """Ids become key chunks and file names: letters, digits, '_', '-', '.', at most 64
    characters, not dots alone ('.', '..' would be paths)."""
    if not isinstance(value, str) or not _ID_RE.match(value) or not value.strip("."):
        raise KeyExprError(
            f"{what} {value!r} is invalid: use 1-64 letters, digits, '_', '-' or '.' (not dots "
            "alone)"
        )
    return value


def check_robot_id(value: str) -> str:
    """A robot id: a valid id that is not one of the RESERVED_ROBOT_IDS."""
    check_id(value, "robot id")
    if value in RESERVED_ROBOT_IDS:
        raise KeyExprError(f"robot id {value!r} is reserved (keys below it belong to services)")
    return value


def check_prefix(prefix: str) -> str:
    """A key prefix: one or more id chunks joined by '/', e.g. 'scanflow' or 'site1/scanflow'."""
    if not isinstance(prefix, str):
        raise KeyExprError(f"prefix must be a string, got {prefix!r}")
    for chunk in prefix.split("/"):
        check_id(chunk, f"prefix {prefix!r} chunk")
    return prefix


def raw_scan(robot: str = "*", prefix: str = DEFAULT_PREFIX) -> str:
    """`<prefix>/<robot>/scan/raw`: raw scans (ScanMessage); robot "*" matches every robot."""
    return _key(robot, "scan/raw", prefix)


def odom(robot: str = "*", prefix: str = DEFAULT_PREFIX) -> str:
    """`<prefix>/<robot>/odom`: odometry samples (OdometryMessage)."""
    return _key(robot, "odom", prefix)


def deskewed_scan(robot: str = "*", prefix: str = DEFAULT_PREFIX) -> str:
    """`<prefix>/<robot>/scan/deskewed`: deskewed scans (DeskewedScanMessage)."""
    return _key(robot, "scan/deskewed", prefix)


def pose(robot: str = "*", prefix: str = DEFAULT_PREFIX) -> str:
    """`<prefix>/<robot>/pose`: pose estimates (PoseEstimateMessage)."""
    return _key(robot, "pose", prefix)


def robot_match(robot: str = "*", prefix: str = DEFAULT_PREFIX) -> str:
    """`<prefix>/<robot>/match`: match queries against that robot's map (MatchRequest)."""
    return _key(robot, "match", prefix)


def initial_pose(robot: str = "*", prefix: str = DEFAULT_PREFIX) -> str:
    """`<prefix>/<robot>/initial_pose`: the queryable taking a robot's InitialPoseMessage."""
    return _key(robot, "initial_pose", prefix)


def scan_match(prefix: str = DEFAULT_PREFIX) -> str:
    """`<prefix>/match`: scan-to-scan match queries (MatchRequest), not tied to a robot."""
    return f"{check_prefix(prefix)}/match"


def map_key(robot: str = "*", what: str = "meta", prefix: str = DEFAULT_PREFIX) -> str:
    """`<prefix>/<robot>/map/<what>`: a map key (meta, image, region, changed, insert, ...)."""
    return _key(robot, f"map/{check_id(what, 'map topic')}", prefix)


def trajectory(robot: str = "*", prefix: str = DEFAULT_PREFIX) -> str:
    """`<prefix>/<robot>/trajectory`: the trajectory queryable (TrajectoryMessage)."""
    return _key(robot, "trajectory", prefix)


def retire(robot: str = "*", service: str = "*", prefix: str = DEFAULT_PREFIX) -> str:
    """`<prefix>/<robot>/retire/<service>`: the queryable on which `service` drops the robot
    (RetireMessage -> RetiredMessage); service "*" reaches every service at once."""
    return _key(robot, f"retire/{_chunk(service, 'service')}", prefix)


def health(service: str = "*", instance: str = "*", prefix: str = DEFAULT_PREFIX) -> str:
    """`<prefix>/health/<service>/<instance>`: a service's liveliness token."""
    return _service_key("health", service, instance, prefix)


def stats(service: str = "*", instance: str = "*", prefix: str = DEFAULT_PREFIX) -> str:
    """`<prefix>/stats/<service>/<instance>`: a service's stats queryable."""
    return _service_key("stats", service, instance, prefix)


def robot_of(key: str, prefix: str = DEFAULT_PREFIX) -> str:
    """The robot id in a concrete per-robot key (the chunk right after the prefix)."""
    head = check_prefix(prefix) + "/"
    parts = str(key).removeprefix(head).split("/")
    if not str(key).startswith(head) or len(parts) < 2:
        raise KeyExprError(f"key {key!r} is not a per-robot key under {prefix!r}")
    return check_robot_id(parts[0])


def addresses_services(key: str, prefix: str = DEFAULT_PREFIX) -> bool:
    """True when `key` lies below the services' keys (`<prefix>/stats/...`, `/health/...`):
    a queryable on `<prefix>/*/...` receives such queries too (`stats/*/*` matches
    `*/map/resend`), and they are not for it."""
    head = check_prefix(prefix) + "/"
    return str(key).startswith(head) and str(key)[len(head):].split("/")[0] in RESERVED_ROBOT_IDS


def check_sender(key: str, robot_id: str, prefix: str = DEFAULT_PREFIX) -> str:
    """`robot_id`, a message's own, when it is the robot its per-robot `key` names: one robot's
    message on another's key would change the other robot's state."""
    keyed = robot_of(key, prefix)
    if keyed != robot_id:
        raise KeyExprError(f"a message of robot {robot_id!r} on robot {keyed!r}'s key {key!r}")
    return robot_id


def _chunk(value: str, what: str) -> str:
    return value if value == "*" else check_id(value, what)


def _key(robot: str, suffix: str, prefix: str) -> str:
    robot = robot if robot == "*" else check_robot_id(robot)
    return f"{check_prefix(prefix)}/{robot}/{suffix}"


def _service_key(kind: str, service: str, instance: str, prefix: str) -> str:
    return (
        f"{check_prefix(prefix)}/{kind}/{_chunk(service, 'service')}/{_chunk(instance, 'instance')}"
    )
