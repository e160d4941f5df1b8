"""The wire format: every message scanflow puts on the bus, and its msgpack codec.

Each message is a frozen dataclass with `encode() -> bytes` and `Cls.decode(bytes)`;
`decode_any(bytes)` dispatches on the payload's `type` field. Payloads are msgpack maps with a
schema version `v` (SCHEMA_VERSION); numpy arrays travel as raw little-endian bytes with dtype
and shape. Anything wrong with a payload raises a `DecodeError` (subclasses `VersionError`,
`SchemaError`, `PayloadTooLarge`) naming the field; building a message with bad fields raises
`MessageError`. Decoded arrays are read-only views of the payload.

A payload is at most MAX_PAYLOAD_BYTES (16 MiB: a scan, an estimate, an insert), except the
`BULK` types, which grow with the run (a map, its region, a path, a redraw, a resume, a
map state):
up to MAX_BULK_BYTES (512 MiB). Zenoh splits a big payload into fragments on its own.

Changing any message's fields bumps SCHEMA_VERSION (2: `DeskewedScanMessage.no_return_points`;
3: the sensor `mount` on scans, deskewed scans and map inserts; 4: `MapRedrawMessage`,
`KeyframesMessage` and `PoseEstimateMessage.correction`, loop closure in the services;
5: `ResumeMessage`, a restarted matcher's one consistent answer from the map server;
6: `MapInsertMessage.keyframe`, false for an insert the back end culled as a keyframe;
7: `MapStateMessage`, a matcher's whole map for a map server that missed more inserts than
the matcher keeps; 8: `PoseEstimateMessage.odom_pose` and `ResumeMessage.odom_pose`, so a
restarted matcher predicts the robot's next pose from the odometry since the last one;
9: `RetireMessage` and `RetiredMessage`, a robot retired from every service; 10: `run`, the
tracker's run token, on inserts, redraws, map states, resumes and estimates, so that a map
server tells a new run from a gap in the old one):
readers refuse other versions with a VersionError, so services of two versions fail loudly
instead of dropping or missing a field.
"""

from scanflow.wire.base import (
    ENDED_RUNS_KEPT,
    MAX_COUNT,
    MAX_POSITION_M,
    Message,
    decode_any,
    message_types,
    new_run,
)
from scanflow.wire.codec import (
    ALLOWED_DTYPES,
    MAX_BULK_BYTES,
    MAX_PAYLOAD_BYTES,
    SCHEMA_VERSION,
)
from scanflow.wire.errors import (
    DecodeError,
    MessageError,
    PayloadTooLarge,
    SchemaError,
    VersionError,
)
from scanflow.wire.estimates import (
    InitialPoseMessage,
    MapRef,
    MatchRequest,
    MatchResponse,
    PoseEstimateMessage,
    TrajectoryMessage,
)
from scanflow.wire.maps import (
    MAP_IMAGE_FORMATS,
    KeyframesMessage,
    MapChangedMessage,
    MapImageMessage,
    MapInsertMessage,
    MapMetaMessage,
    MapRedrawMessage,
    MapRegionMessage,
    MapStateMessage,
    ResumeMessage,
)
from scanflow.wire.robots import RetiredMessage, RetireMessage
from scanflow.wire.scans import DeskewedScanMessage, OdometryMessage, ScanMessage
from scanflow.wire.stats import ServiceStatsMessage

__all__ = [
    "ALLOWED_DTYPES",
    "ENDED_RUNS_KEPT",
    "MAP_IMAGE_FORMATS",
    "MAX_BULK_BYTES",
    "MAX_COUNT",
    "MAX_PAYLOAD_BYTES",
    "MAX_POSITION_M",
    "SCHEMA_VERSION",
    "DecodeError",
    "DeskewedScanMessage",
    "InitialPoseMessage",
    "KeyframesMessage",
    "MapChangedMessage",
    "MapImageMessage",
    "MapInsertMessage",
    "MapMetaMessage",
    "MapRedrawMessage",
    "MapRef",
    "MapRegionMessage",
    "MapStateMessage",
    "MatchRequest",
    "MatchResponse",
    "Message",
    "MessageError",
    "OdometryMessage",
    "PayloadTooLarge",
    "PoseEstimateMessage",
    "ResumeMessage",
    "RetireMessage",
    "RetiredMessage",
    "ScanMessage",
    "SchemaError",
    "ServiceStatsMessage",
    "TrajectoryMessage",
    "VersionError",
    "decode_any",
    "message_types",
    "new_run",
]
