"""The gateway's one Zenoh session: pose/scan/map subscriptions, liveliness, queries, publishing.

Zenoh callbacks only decode and record (TrackStore, EventHub); blocking queries are meant to
run in a worker thread (`aquery`). A query that nobody answers fails fast with 503, one that
times out with 504, an error reply with a status derived from the remote exception.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol, TypedDict, TypeVar

import anyio.to_thread
import zenoh
from scanflow import keys
from scanflow.config import GatewaySettings, ZenohSettings
from scanflow.wire import (
    DecodeError,
    MapChangedMessage,
    OdometryMessage,
    PoseEstimateMessage,
    RetiredMessage,
    RetireMessage,
    ScanMessage,
    ServiceStatsMessage,
)

from services.common.counters import worth_logging
from services.common.retire import RETIRING
from services.common.robots import RobotLimit
from services.common.zsession import open_session, sorted_replies
from services.gateway.events import EventHub
from services.gateway.metrics import Metrics
from services.gateway.models import PoseOut
from services.gateway.tracks import StaleSeqError, TrackStore

M = TypeVar("M", PoseEstimateMessage, MapChangedMessage, ScanMessage, OdometryMessage)

log = logging.getLogger("scanflow.gateway")
EXPECTED_SERVICES = ("router", "deskew", "matcher", "mapserver")
STATS_TIMEOUT_S = 1.0
# Where the services' stats keep a robot's last seq of each input stream (deskew and matcher
# see the scans, the map server their poses, deskew the odometry).
_SEQ_GAUGES = {"scan": ("scan", "pose"), "odom": ("odom",)}
_ERROR_STATUS = {  # remote exception name -> HTTP status
    "LookupError": 404,
    "KeyError": 404,
    "ValueError": 422,
    "MatchInputError": 422,
    "KeyExprError": 422,
    "DecodeError": 422,
    "SchemaError": 422,
    "RobotLimitError": 503,
}


class BackendError(Exception):
    """A bus operation that failed; `status_code` is the HTTP answer, `reason` says why."""

    def __init__(self, status_code: int, reason: str) -> None:
        super().__init__(reason)
        self.status_code = status_code
        self.reason = reason


@dataclass(frozen=True)
class Reply:
    key: str
    payload: bytes


class SessionInfo(TypedDict):
    """The Zenoh session's state, as /health shows it (`ZenohOut`)."""

    open: bool
    mode: str
    zid: str
    routers: list[str]
    peers: list[str]


class _Declared(Protocol):
    """A subscriber or publisher the backend undeclares when it closes."""

    def undeclare(self) -> None: ...


def error_status(text: str) -> int:
    """HTTP status for an error reply: 'Timeout' 504, 'busy' 503, known exceptions 404/422."""
    if text == "Timeout":
        return 504
    if "busy" in text:
        return 503
    return _ERROR_STATUS.get(text.split(":", 1)[0].strip(), 502)


class ZenohBackend:
    """Everything the HTTP side needs from the bus, safe to call from any thread."""

    def __init__(
        self, session: zenoh.Session, settings: GatewaySettings, zenoh_settings: ZenohSettings
    ) -> None:
        self.session = session
        self.settings = settings
        self.mode = zenoh_settings.mode
        self.prefix = keys.check_prefix(zenoh_settings.prefix)
        self.metrics = Metrics()
        self.tracks = TrackStore(
            settings.trajectory_cache_len, RobotLimit(settings.max_robots, self._refused_robot)
        )
        self.events = EventHub(settings.stream_queue_len)
        self._lock = threading.Lock()
        self._ingest_lock = threading.Lock()  # posted messages: numbered and put in order
        self._alive: set[tuple[str, str]] = set()
        self._publishers: dict[str, zenoh.Publisher] = {}
        self._declared: list[_Declared] = []
        self._closed = False

    @classmethod
    def open(cls, settings: GatewaySettings, zenoh_settings: ZenohSettings) -> ZenohBackend:
        """A backend on a new Zenoh session, with its subscriptions declared."""
        backend = cls(open_session(zenoh_settings), settings, zenoh_settings)
        backend.start()
        return backend

    def start(self) -> None:
        """Declare the subscriptions the HTTP side reads from."""
        p = self.prefix
        sub = self.session.declare_subscriber
        self._declared += [
            sub(keys.pose("*", p), self._on_pose),
            # Other sources' input only: the echo of a post of this gateway's, coming late,
            # would otherwise lower the seq it numbers from (publish_numbered records posts).
            sub(keys.raw_scan("*", p), self._on_scan, allowed_origin=zenoh.Locality.REMOTE),
            sub(keys.odom("*", p), self._on_odometry, allowed_origin=zenoh.Locality.REMOTE),
            sub(keys.map_key("*", "changed", p), self._on_map_changed),
            self.session.liveliness().declare_subscriber(
                keys.health("*", "*", p), self._on_liveliness, history=True
            ),
        ]

    def close(self) -> None:
        """Undeclare subscriptions and publishers and close the session; later calls do nothing."""
        if self._closed:
            return
        self._closed = True
        for entity in reversed(self._declared + list(self._publishers.values())):
            try:
                entity.undeclare()
            except zenoh.ZError:
                log.debug("undeclare failed during close", exc_info=True)
        self.session.close()

    # -- subscriptions (Zenoh threads) ----------------------------------------------------
    def _refused_robot(self, robot_id: str, first: bool) -> None:
        self.metrics.count("scanflow_gateway_robots_refused_total")
        if first:
            log.warning("robot %s refused: the gateway tracks %d robots already "
                        "(SCANFLOW_GATEWAY_MAX_ROBOTS)", robot_id, self.settings.max_robots)

    def _decoded(self, sample: zenoh.Sample, decode: Callable[[bytes], M], kind: str) -> M | None:
        """The sample's message, None when malformed or on another robot's key (counted)."""
        try:
            message = decode(sample.payload.to_bytes())
            keys.check_sender(str(sample.key_expr), message.robot_id, self.prefix)
        except (DecodeError, keys.KeyExprError) as exc:
            n = self.metrics.count("scanflow_gateway_malformed_total", kind=kind)
            if worth_logging(n):  # scans and odometry come fast: a bad source would flood it
                log.warning("malformed %s #%d on %s: %s", kind, n, sample.key_expr, exc)
            return None
        return message

    def _on_pose(self, sample: zenoh.Sample) -> None:
        estimate = self._decoded(sample, PoseEstimateMessage.decode, "pose")
        if estimate is None:
            return
        if not self.tracks.add_pose(estimate):
            return
        self.metrics.count("scanflow_gateway_poses_received_total")
        self.events.publish(estimate.robot_id, "pose", PoseOut.from_estimate(estimate).model_dump())

    def _on_scan(self, sample: zenoh.Sample) -> None:
        message = self._decoded(sample, ScanMessage.decode, "scan")
        if message is not None:
            self.tracks.saw_scan(message.robot_id, message.seq)

    def _on_odometry(self, sample: zenoh.Sample) -> None:
        message = self._decoded(sample, OdometryMessage.decode, "odom")
        if message is not None:
            self.tracks.saw_odometry(message.robot_id, message.seq)

    def _on_map_changed(self, sample: zenoh.Sample) -> None:
        notice = self._decoded(sample, MapChangedMessage.decode, "map_changed")
        if notice is None:
            return
        self.tracks.saw_map(notice.robot_id, notice.revision)
        box = [notice.min_x_m, notice.min_y_m, notice.max_x_m, notice.max_y_m]
        self.events.publish(
            notice.robot_id, "map", {"revision": notice.revision, "box_m": box}
        )

    def _on_liveliness(self, sample: zenoh.Sample) -> None:
        parts = str(sample.key_expr).split("/")
        entry = (parts[-2], parts[-1])
        with self._lock:
            if sample.kind == zenoh.SampleKind.PUT:
                self._alive.add(entry)
            else:
                self._alive.discard(entry)

    # -- reads ----------------------------------------------------------------------------
    def alive_services(self) -> list[tuple[str, str]]:
        """(service, instance) of every liveliness token present now, sorted."""
        with self._lock:
            return sorted(self._alive)

    def session_info(self) -> SessionInfo:
        """The Zenoh session's state for /health: open, mode, own zid, routers and peers."""
        closed = self._closed or self.session.is_closed()
        info = self.session.info
        return {
            "open": not closed,
            "mode": self.mode,
            "zid": "" if closed else str(info.zid()),
            "routers": [] if closed else [str(z) for z in info.routers_zid()],
            "peers": [] if closed else [str(z) for z in info.peers_zid()],
        }

    def query(
        self, selector: str, payload: bytes | None = None, timeout_s: float | None = None,
        every_reply: bool = False,
    ) -> list[Reply]:
        """OK replies to `selector` (blocking); raises BackendError when none came back.
        `every_reply`: none merged away (Zenoh's default keeps one reply per key)."""
        timeout_s = self.settings.query_timeout_s if timeout_s is None else timeout_s
        if self._closed:
            raise BackendError(503, "the gateway's Zenoh session is closed")
        consolidation = zenoh.ConsolidationMode.NONE if every_reply else None
        answers, errors = sorted_replies(self.session.get(
            selector, payload=payload, timeout=timeout_s, consolidation=consolidation
        ))
        if answers:
            return [Reply(key, data) for key, data in answers]
        if errors:
            status = max(error_status(e) for e in errors)
            reason = "; ".join(sorted(set(errors)))
            if status == 504:
                reason = f"no answer on {selector} within {timeout_s} s"
            raise BackendError(status, reason)
        raise BackendError(503, f"no service answers {selector} (is it running?)")

    def service_stats(self, timeout_s: float = STATS_TIMEOUT_S) -> list[ServiceStatsMessage]:
        """Every service's stats that answer within `timeout_s` (none: an empty list);
        malformed answers are counted."""
        try:
            replies = self.query(keys.stats("*", "*", self.prefix), None, timeout_s, True)
        except BackendError:
            return []
        stats = []
        for reply in replies:
            try:
                stats.append(ServiceStatsMessage.decode(reply.payload))
            except DecodeError:
                self.metrics.count("scanflow_gateway_malformed_total", kind="stats")
        return stats

    def _services_last_seq(self, robot_id: str, stream: str) -> int:
        """The last seq any service saw on the robot's input `stream` (-1: none): a gateway that
        (re)started knows nothing of the posts before it, and numbering them from 0 again
        would restart the robot's map in every service."""
        names = [f"seq.{robot_id}/{kind}.last" for kind in _SEQ_GAUGES[stream]]
        stats = self.service_stats(self.settings.query_timeout_s)  # all services, or the wait
        lasts = [s.gauges[n] for s in stats for n in names if n in s.gauges]
        return int(max(lasts, default=-1))

    def retire(self, robot_id: str) -> tuple[list[RetiredMessage], dict[str, int] | None]:
        """Retire the robot from every service that keeps robot state, one service after the
        other in the order the data flows (services.common.retire.RETIRING), then from the
        gateway itself: the answers of every instance asked, and what the gateway's own track
        held (None: it had none). Blocking; each service within `query_timeout_s`.

        BackendError 503 when no instance of one of those services is alive (nothing is asked:
        a map server that is not running would bring the robot back from its snapshot when
        it starts), or when one answers it is busy (stopping); 504 naming each instance that
        is alive (its liveliness token) and did not answer in time; an error reply otherwise
        with its status (error_status). The services asked before the one that failed have
        dropped the robot: the message names them, and asking again finishes the retire."""
        if self._closed:
            raise BackendError(503, "the gateway's Zenoh session is closed")
        alive = self.alive_services()
        running = {service for service, _ in alive}
        absent = [name for name in RETIRING if name not in running]
        if absent:
            raise BackendError(
                503, f"no {' or '.join(absent)} is running: robot {robot_id!r} was retired from "
                f"no service (every one of {', '.join(RETIRING)} must answer; a map server "
                "started later would bring the robot back from its snapshot)"
            )
        answers: list[RetiredMessage] = []
        for service in RETIRING:
            instances = {i for s, i in alive if s == service}
            answers += self._retire_from(robot_id, service, instances, answers)
        with self._ingest_lock:  # not between the numbering and the put of a post
            gateway = self.tracks.forget(robot_id)
            with self._lock:
                stale = [self._publishers.pop(k, None) for k in (
                    keys.raw_scan(robot_id, self.prefix), keys.odom(robot_id, self.prefix))]
        for publisher in stale:
            if publisher is not None:
                try:
                    publisher.undeclare()
                except zenoh.ZError:  # the session closing
                    log.debug("undeclaring a retired robot's publisher failed", exc_info=True)
        log.info("robot %s retired from %s", robot_id,
                 ", ".join(f"{a.service}/{a.instance}" for a in answers))
        return answers, gateway

    def _retire_from(
        self, robot_id: str, service: str, instances: set[str], before: list[RetiredMessage]
    ) -> list[RetiredMessage]:
        """Every answer of `service`'s instances to the retire (all replies kept: one per
        instance, every matcher shard's); BackendError when one of `instances` (alive) did not
        answer in time or an instance answered with an error."""
        timeout_s = self.settings.query_timeout_s
        answers, errors = [], []
        for reply in self.session.get(
            keys.retire(robot_id, service, self.prefix), payload=RetireMessage(robot_id).encode(),
            target=zenoh.QueryTarget.ALL, consolidation=zenoh.ConsolidationMode.NONE,
            timeout=timeout_s,
        ):
            result = reply.result  # a Sample, or the ReplyError of a failed reply
            if isinstance(result, zenoh.ReplyError):
                if (text := result.payload.to_string()) != "Timeout":
                    errors.append(text)
            else:
                answers.append(RetiredMessage.decode(result.payload.to_bytes()))
        done = ", ".join(f"{a.service}/{a.instance}" for a in before + answers) or "none"
        again = f" (retired from: {done}; ask again to finish the retire)"
        if errors:
            status = max(error_status(e) for e in errors)
            raise BackendError(status, f"{service}: {'; '.join(sorted(set(errors)))}{again}")
        silent = sorted(instances - {a.instance for a in answers if a.service == service})
        if silent:
            names = ", ".join(f"{service}/{i}" for i in silent)
            raise BackendError(
                504, f"{names} is alive but did not answer the retire of robot {robot_id!r} "
                f"within {timeout_s} s{again}"
            )
        return answers

    async def aretire(self, robot_id: str) -> tuple[list[RetiredMessage], dict[str, int] | None]:
        """`retire` in a worker thread, so the event loop never waits on the bus."""
        return await anyio.to_thread.run_sync(lambda: self.retire(robot_id))

    async def aquery(
        self, selector: str, payload: bytes | None = None, timeout_s: float | None = None
    ) -> list[Reply]:
        """`query` in a worker thread, so the event loop never waits on the bus."""
        return await anyio.to_thread.run_sync(lambda: self.query(selector, payload, timeout_s))

    # -- writes ---------------------------------------------------------------------------
    def _next_seq(self, robot_id: str, stream: str, given: int | None) -> int:
        """The seq to publish on the robot's input `stream`: the client's, or one past the last
        one on the bus (from any source; for scans, before one is seen, past the robot's last
        pose). 409 for a client's seq that would restart the robot's map (TrackStore.next_seq),
        503 for a robot over SCANFLOW_GATEWAY_MAX_ROBOTS."""
        try:
            seq = self.tracks.next_seq(robot_id, stream, given)
        except StaleSeqError as exc:
            raise BackendError(409, str(exc)) from exc
        if seq is None:
            raise BackendError(
                503, f"robot {robot_id!r} refused: the gateway tracks "
                f"{self.settings.max_robots} robots already (SCANFLOW_GATEWAY_MAX_ROBOTS)"
            )
        return seq

    def publish(self, key: str, payload: bytes) -> None:
        """Reliable put through a cached publisher that blocks rather than drops; 503 when
        Zenoh refuses it (the session closing, say), the publisher then being declared again."""
        try:
            with self._lock:
                pub = self._publishers.get(key)
                if pub is None:
                    pub = self._publishers[key] = self.session.declare_publisher(
                        key,
                        congestion_control=zenoh.CongestionControl.BLOCK,
                        reliability=zenoh.Reliability.RELIABLE,
                    )
            pub.put(payload, timestamp=self.session.new_timestamp())  # copies known by it
        except zenoh.ZError as exc:
            with self._lock:  # the next post declares a fresh publisher
                stale = self._publishers.pop(key, None)
            if stale is not None:
                try:
                    stale.undeclare()
                except zenoh.ZError:  # undeclared already (or the session closing)
                    log.debug("undeclaring a failed publisher failed", exc_info=True)
            self.metrics.count("scanflow_gateway_publish_failed_total")
            raise BackendError(503, f"could not publish on {key}: {exc}") from exc

    def publish_numbered(
        self, robot_id: str, stream: str, given: int | None, key: str,
        encode: Callable[[int], bytes],
    ) -> int:
        """Number a posted message (`given`, or the next seq: `_next_seq`) and put
        `encode(seq)` on `key`, one post at a time: posts numbered n and n + 1 must reach the
        bus in that order, or every service takes n for a replay and starts the robot's map
        afresh. The seq counts as used only once the put went out: after a refused put (503)
        the same seq is given to the next post, so the services see no gap. Returns the seq."""
        with self._ingest_lock:
            if not self.tracks.knows_seq(robot_id, stream):
                self.tracks.learn_seq(robot_id, stream, self._services_last_seq(robot_id, stream))
            seq = self._next_seq(robot_id, stream, given)
            self.publish(key, encode(seq))
            if stream == "scan":
                self.tracks.saw_scan(robot_id, seq)
            else:
                self.tracks.saw_odometry(robot_id, seq)
            return seq

    async def apublish_numbered(
        self, robot_id: str, stream: str, given: int | None, key: str,
        encode: Callable[[int], bytes],
    ) -> int:
        """`publish_numbered` in a worker thread (a put may block on a congested link)."""
        return await anyio.to_thread.run_sync(
            lambda: self.publish_numbered(robot_id, stream, given, key, encode)
        )
