"""What every scanflow service shares: session, health token, stats, inbox, clean shutdown.

A service builds a `ServiceShell`, declares its publishers, subscribers and queryables through
it, calls `start()` and then `run(handle)`: Zenoh callbacks only decode, count and enqueue;
`handle(kind, message)` runs on the one worker thread; queries run on one query thread; puts
leave in order from one sender thread (`Outbox`). SIGTERM or Ctrl-C ends `run` once the worker
has handled what the inbox held (`drain`), then `close()` sends what is queued, flushes,
undeclares and closes the session.

A full inbox blocks the Zenoh callback and with it the session's whole link (backpressure).
A robot is retired (`serve_retire`) on the worker, between two inbox items, and the answer
leaves through the outbox behind what the worker published before (services.common.retire).

Hints a service takes back from a service it feeds (deskew: the matcher's poses) must not wait
behind that: `subscribe_feedback` takes them on a second session whose callback never blocks,
else two services that publish to each other could each wait for the other forever. The same
side session carries the queries a worker makes mid-stream (`get`) or a helper thread makes
(`query`: the matcher's resume query) and the queryables that answer them
(`serve(..., side=True)`): their replies must not wait behind a blocked link either.
"""

from __future__ import annotations

import functools
import logging
import math
import os
import queue
import signal
import threading
import time
from collections import deque
from collections.abc import Callable
from typing import Any, cast

import zenoh
from scanflow import keys
from scanflow.config import ServiceSettings, ZenohSettings
from scanflow.wire import RetiredMessage, ServiceStatsMessage

from services.common.counters import Counters, SeqTracker, worth_logging
from services.common.dedup import SeenSamples
from services.common.inbox import Inbox
from services.common.outbox import Outbox
from services.common.process import io_threads
from services.common.retire import Dropped, QueryReply, retire_request
from services.common.robots import Known, RobotLimit
from services.common.zsession import open_session, sorted_replies

QueryHandler = Callable[[zenoh.Query], None]
_WAKE = "_wake"  # an inbox item that only wakes the worker to take feedback
_RETIRE = "_retire"  # an inbox item (robot id, query): drop the robot, then answer
# A stop's drain ends once nothing has come for this long: what upstream flushed has arrived.
DRAIN_QUIET_S = 0.25


# The error reply Zenoh gives a `get` whose queryable is there but did not finish in time.
TIMED_OUT = "Timeout"


class ServiceShell:
    """Session, liveliness token, stats queryable, counters and a bounded inbox for one service."""

    def __init__(
        self, service: str, settings: ServiceSettings, zenoh_settings: ZenohSettings
    ) -> None:
        self.service = keys.check_id(service, "service")
        self.instance = keys.check_id(settings.instance, "instance")
        queue_size = settings.queue_size
        self.slow_message_s = settings.slow_message_s
        self.inbox_drain_s = settings.inbox_drain_s
        self.prefix = zenoh_settings.prefix
        self.log = logging.getLogger(f"scanflow.{service}")
        self.stop_event = threading.Event()
        self.counters = Counters()
        self.seqs = SeqTracker()
        self._robots = RobotLimit(settings.max_robots, self._refused_robot)
        self._stop_deadline: float | None = None  # when a stop's drain ends (monotonic)
        self._stop_lock = threading.Lock()
        self.inbox = Inbox(queue_size)
        self.outbox = Outbox(queue_size, self.stop_deadline, f"{service}-sender")
        self._io_cpus = settings.io_cpus
        self._zenoh_settings = zenoh_settings
        self.session = self._open_session()
        self._side: zenoh.Session | None = None
        self._side_lock = threading.Lock()  # the worker and a helper thread may both open it
        self._feedback: deque[tuple[str, Any]] = deque()
        self._feedback_lock = threading.Lock()
        self._wake_posted = False  # one _WAKE in the inbox at a time: it takes the whole lane
        self._closed = threading.Event()  # set by close(): the query thread ends
        self._feedback_size = queue_size
        self._keep: dict[str, Callable[[Any], bool]] = {}  # per kind: feedback never dropped
        self._seen = SeenSamples()  # samples the network delivered twice
        self._declared: list[Any] = []
        self._publishers: dict[str, zenoh.Publisher] = {}
        self._stats_sources: list[Callable[[], dict[str, float]]] = []
        self._retire: Callable[[str], Dropped] | None = None  # the service's drop (serve_retire)
        self._queries: queue.Queue[tuple[QueryHandler, zenoh.Query]] = queue.Queue(queue_size)
        self._query_thread = threading.Thread(target=self._serve_queries, daemon=True)
        self._started_s = time.monotonic()
        self._busy_s = 0.0  # worker time in `handle` (and `idle`): how loaded the service is
        self._put_s = 0.0  # worker time handing payloads to the outbox (blocked when full)
        self._get_s = 0.0  # worker time waiting on its own queries' replies (`get`)
        self._handle_max_s = 0.0  # the longest a single message took to handle

    def _open_session(self) -> zenoh.Session:
        """A session whose runtime threads (started with the process's first) run on the
        service's I/O CPUs, if it has any (see services.common.process)."""
        with io_threads(self._io_cpus):
            return open_session(self._zenoh_settings)

    # -- declarations -------------------------------------------------------------------
    def admits(self, robot_id: str, known: Known) -> bool:
        """Whether to keep state for `robot_id`, `known` being the robots held (a refused one
        is counted as `robots_refused` and named in the log once)."""
        return self._robots.admits(robot_id, known)

    def _refused_robot(self, robot_id: str, first: bool) -> None:
        self.counters.add("robots_refused")
        if first:
            self.log.warning(
                "robot %s refused: this %s keeps %d robots already "
                "(SCANFLOW_%s_MAX_ROBOTS); its messages are dropped", robot_id, self.service,
                self._robots.max_robots, self.service.upper(),
            )

    def publisher(self, key: str) -> zenoh.Publisher:
        """A reliable publisher that blocks rather than drops when the network is slow."""
        pub = self.session.declare_publisher(
            key,
            congestion_control=zenoh.CongestionControl.BLOCK,
            reliability=zenoh.Reliability.RELIABLE,
        )
        self._declared.append(pub)
        return pub

    def put(self, key: str, payload: bytes) -> None:
        """Publish on `key` through a cached reliable, blocking publisher, by way of the
        outbox: in order, and blocking the caller only when the outbox is full. The sample
        carries a timestamp of this session, by which a subscriber knows a copy (`dedup`)."""
        t0 = time.perf_counter()
        stamp = self.session.new_timestamp()
        if not self.outbox.put(self._cached_publisher(key), payload, timestamp=stamp):
            self.log.warning("stopping with a full outbox: a message on %s was not sent", key)
        self._put_s += time.perf_counter() - t0

    def wait_for_subscribers(self, key: str, timeout_s: float) -> bool:
        """Wait until something subscribes to `key` (True), or `timeout_s` passes (False)."""
        pub = self._cached_publisher(key)
        deadline = time.monotonic() + timeout_s
        while not _has_subscribers(pub):
            if self.stop_event.wait(0.05) or time.monotonic() > deadline:
                return False
        return True

    def _cached_publisher(self, key: str) -> zenoh.Publisher:
        pub = self._publishers.get(key)
        if pub is None:
            pub = self._publishers[key] = self.publisher(key)
        return pub

    def subscribe(
        self,
        key: str,
        kind: str,
        decode: Callable[[bytes], Any],
        sink: Callable[[str, Any], object] | None = None,
    ) -> None:
        """Decode every sample on `key`; malformed ones are counted and logged, never fatal.

        Decoded messages go to `sink(kind, message)` (default: the inbox, blocking when full).
        `sink` runs on a Zenoh thread and must be quick. Subscribe to exactly what the service
        consumes: a full inbox stops this session's whole link (see the module docstring).
        """
        callback = self._sample_callback(kind, decode, sink or self.inbox.put)
        self._declared.append(self.session.declare_subscriber(key, callback))

    def subscribe_feedback(
        self,
        key: str,
        kind: str,
        decode: Callable[[bytes], Any],
        keep: Callable[[Any], bool] | None = None,
    ) -> None:
        """Decode every sample on `key` on a second session whose callback never blocks; the
        worker takes them (through `handle`) before its next inbox item. At most `queue_size`
        wait: past that the oldest goes, counted as `feedback_overflow.<kind>` (hints only),
        unless `keep(message)` says it must not (it is then the oldest after it that goes)."""
        if keep is not None:
            self._keep[kind] = keep
        callback = self._sample_callback(kind, decode, self._feed)
        self._declared.append(self._side_session().declare_subscriber(key, callback))

    def _side_session(self) -> zenoh.Session:
        """The second session (opened on first use) whose callbacks never block."""
        with self._side_lock:
            if self._side is None:
                self._side = self._open_session()
            return self._side

    def get(self, selector: str, timeout_s: float) -> tuple[list[bytes], list[str]]:
        """`query`, by the worker: the time it waits counts as the worker's waiting on queries
        (a slow message's log says so)."""
        t0 = time.perf_counter()
        try:
            return self.query(selector, timeout_s)
        finally:
            self._get_s += time.perf_counter() - t0

    def query(self, selector: str, timeout_s: float) -> tuple[list[bytes], list[str]]:
        """Query `selector` on the side session (from any thread): every reply's payload (none
        merged away, as Zenoh's default does to replies on one key), and the error replies'
        texts (both empty when no queryable matched; a queryable that did not finish within
        `timeout_s` gives the error TIMED_OUT)."""
        answers, errors = sorted_replies(self._side_session().get(
            selector, timeout=timeout_s, consolidation=zenoh.ConsolidationMode.NONE
        ))
        return [payload for _, payload in answers], errors

    def _feed(self, kind: str, message: Any) -> None:
        with self._feedback_lock:
            full = len(self._feedback) >= self._feedback_size
            dropped = self._drop_oldest_hint() if full else None
            self._feedback.append((kind, message))
            wake, self._wake_posted = not self._wake_posted, True
        if dropped is not None:
            n = self.counters.add(f"feedback_overflow.{dropped}")
            if worth_logging(n):
                self.log.warning("feedback queue full: dropped the oldest %s (#%d)", dropped, n)
        if wake:
            self.inbox.offer(_WAKE, None)  # a full inbox wakes the worker anyway

    def _drop_oldest_hint(self) -> str | None:
        """Drop the oldest waiting feedback that may go, and name its kind; None when all must
        stay (the lane then grows past its size)."""
        for i, (kind, message) in enumerate(self._feedback):
            keep = self._keep.get(kind)
            if keep is None or not keep(message):
                del self._feedback[i]
                return kind
        return None

    def _take_feedback(self) -> list[tuple[str, Any]]:
        with self._feedback_lock:
            items = list(self._feedback)
            self._feedback.clear()
            self._wake_posted = False
        return items

    def _sample_callback(
        self,
        kind: str,
        decode: Callable[[bytes], Any],
        deliver: Callable[[str, Any], object],
    ) -> Callable[[zenoh.Sample], None]:
        """A subscriber callback: decode, count, deliver; malformed samples are counted."""

        def on_sample(sample: zenoh.Sample) -> None:
            if sample.kind != zenoh.SampleKind.PUT:
                return
            if not self._seen.first(f"{kind}:{sample.key_expr}", sample.timestamp):
                n = self.counters.add(f"duplicates.{kind}")  # a copy the network made
                if worth_logging(n):
                    self.log.warning("a %s sample on %s came twice (#%d): the copy is dropped",
                                     kind, sample.key_expr, n)
                return
            try:
                message = decode(sample.payload.to_bytes())
                robot_id = getattr(message, "robot_id", None)
                if robot_id is not None:  # every per-robot message: on its own robot's key
                    keys.check_sender(str(sample.key_expr), robot_id, self.prefix)
            except Exception as exc:  # any decode failure: count, log, keep going
                self._count_malformed(kind, str(sample.key_expr), exc)
                return
            self.counters.add(f"received.{kind}")
            if deliver(kind, message) is False:  # the inbox refuses once the drain closed it
                self.counters.add(f"refused_at_stop.{kind}")

        return on_sample

    def serve(self, key: str, handler: QueryHandler, side: bool = False) -> zenoh.Queryable:
        """Answer queries on `key` with `handler(query)` on the query thread (not Zenoh's).
        `side`: for quick queries other services make mid-stream (`get`): on the side session,
        answered at once on its Zenoh thread, never queued behind a slow query (a whole-map
        search takes seconds). Returns the queryable (`undeclare` ends it)."""

        if not keys.addresses_services(key, self.prefix):  # a per-robot queryable
            handler = robots_only(handler, self.prefix)

        def on_query(query: zenoh.Query) -> None:
            try:
                self._queries.put_nowait((handler, query))
            except queue.Full:
                self.counters.add("queries.busy")
                query.reply_err(f"{self.service}/{self.instance} is busy: query queue full")

        if side:
            answer = functools.partial(self._answer, handler)
            queryable = self._side_session().declare_queryable(key, answer)
        else:
            queryable = self.session.declare_queryable(key, on_query)
        self._declared.append(queryable)
        return queryable

    def undeclare(self, entity: Any) -> None:
        """Undeclare a queryable (subscriber, ...) declared through the shell before it closes
        (a retired robot's)."""
        self._declared.remove(entity)
        entity.undeclare()

    def serve_retire(self, drop: Callable[[str], Dropped]) -> None:
        """Answer `<prefix>/<robot>/retire/<service>` (keys.retire): `drop(robot_id)` runs on
        the worker, after every inbox item that came before the query, and must let go of all
        the service keeps of the robot; the shell then forgets the robot's seqs, the samples it
        saw of it (dedup) and its refusals, and answers with a RetiredMessage through the
        outbox. A query that does not decode, or whose key is not its robot's, gets an error
        reply naming why."""
        self._retire = drop
        key = keys.retire("*", self.service, self.prefix)
        self._declared.append(self.session.declare_queryable(key, self._on_retire))

    def _on_retire(self, query: zenoh.Query) -> None:
        """On a Zenoh thread: into the inbox, in order with the samples (blocking when full, as
        they do); the worker answers it (`_answer_retire`)."""
        if keys.addresses_services(str(query.key_expr), self.prefix):  # a stats scrape
            query.drop()
            return
        try:
            robot_id = retire_request(query, self.service, self.prefix)
        except Exception as exc:  # a bad request is answered, never raised on Zenoh's thread
            self._count_malformed("retire", str(query.key_expr), exc)
            QueryReply(query, "").refuse(f"{type(exc).__name__}: {exc}")
            return
        if not self.inbox.put(_RETIRE, (robot_id, query)):
            QueryReply(query, "").refuse(f"{self.service}/{self.instance} is busy: stopping")

    def _answer_retire(self, _kind: str, item: tuple[str, zenoh.Query]) -> None:
        """On the worker: drop the robot (the service's part, then the shell's), answer through
        the outbox. A drop that fails is an error reply naming the service, logged and counted
        (`retire.failed`); the service goes on."""
        robot_id, query = item
        reply = QueryReply(query, keys.retire(robot_id, self.service, self.prefix))
        try:
            if self._retire is None:
                raise RuntimeError("this service keeps no robot state to retire")
            dropped = self._retire(robot_id)
            had_streams = self.seqs.forget_robot(robot_id)
            head = f"{self.prefix}/{robot_id}/"
            self._seen.forget(lambda seen: seen.partition(":")[2].startswith(head))
            self._robots.forget(robot_id)
            answer = RetiredMessage(robot_id, self.service, self.instance,
                                    dropped.known or had_streams, dropped.counts)
        except Exception as exc:
            self.counters.add("retire.failed")
            self.log.exception("robot %s: retiring it failed", robot_id)
            reply.refuse(f"{type(exc).__name__}: {self.service}/{self.instance}: {exc}")
            return
        self.counters.add("retire.answered")
        if answer.known:
            self.counters.add("robots_retired")
            self.log.info("robot %s retired: dropped %s", robot_id, answer.dropped)
        if not self.outbox.put(reply, answer.encode()):
            reply.refuse(f"{self.service}/{self.instance} is busy: stopping")

    def add_stats(self, source: Callable[[], dict[str, float]]) -> None:
        """Merge the gauges `source()` returns into the stats this service reports."""
        self._stats_sources.append(source)

    # -- life cycle ---------------------------------------------------------------------
    def start(self, install_signals: bool = True) -> None:
        """Announce the service: stats queryable, health token; handle SIGTERM/SIGINT."""
        stats_key = keys.stats(self.service, self.instance, self.prefix)
        self._declared.append(self.session.declare_queryable(stats_key, self._reply_stats))
        self._query_thread.start()
        health_key = keys.health(self.service, self.instance, self.prefix)
        self._declared.append(self.session.liveliness().declare_token(health_key))
        if install_signals:
            signal.signal(signal.SIGTERM, self._on_signal)
            signal.signal(signal.SIGINT, self._on_signal)
        self.log.info("%s/%s up (pid %d)", self.service, self.instance, os.getpid())

    def run(
        self,
        handle: Callable[[str, Any], None],
        idle: Callable[[], None] | None = None,
        poll_s: float = 0.1,
        pending: Callable[[], bool] | None = None,
    ) -> None:
        """Feed inbox items to `handle` until stopped, then `drain`; `idle()` runs after
        `poll_s` of quiet; `pending()`: whether work of the service's own threads is still on
        its way into the inbox (the drain waits for it)."""
        while not self.stop_event.is_set():
            item = self.inbox.get(poll_s)
            t0 = time.perf_counter()
            for kind, message in self._take_feedback():
                self._handle(handle, kind, message)
            if item is None:
                if idle is not None:
                    self._idle(idle)
            elif item[0] != _WAKE:
                self._handle(handle, *item)
            self._busy_s += time.perf_counter() - t0
        self.drain(handle, pending)

    def stop_deadline(self) -> float:
        """When a stop's drain ends (time.monotonic): math.inf while running, else
        `inbox_drain_s` after the stop was first seen here. The outbox blocks until then too,
        so what the drain hands it is sent rather than refused."""
        if not self.stop_event.is_set():
            return math.inf
        with self._stop_lock:
            if self._stop_deadline is None:
                self._stop_deadline = time.monotonic() + self.inbox_drain_s
            return self._stop_deadline

    def drain(
        self, handle: Callable[[str, Any], None], pending: Callable[[], bool] | None = None
    ) -> None:
        """Once stopped, handle what the inbox holds and what still arrives, until nothing has
        come for DRAIN_QUIET_S (and `pending()`, if given, says nothing more is on its way) or
        `stop_deadline` passes: a message accepted off the bus is not lost on a clean stop,
        nor one an upstream service flushed at its own stop (they stop in data-flow order)
        that is still on the wire. Then the inbox closes: what it held is counted as
        inbox.dropped_at_stop and logged, later samples as refused_at_stop.<kind>."""
        deadline = self.stop_deadline()
        handled, quiet = 0, self.inbox_drain_s <= 0.0  # no drain: nothing to report
        while (left_s := deadline - time.monotonic()) > 0.0:
            for kind, message in self._take_feedback():
                self._handle(handle, kind, message)
            item = self.inbox.get(min(DRAIN_QUIET_S, left_s))
            if item is None and pending is not None and pending():
                continue
            if item is None:
                quiet = left_s > DRAIN_QUIET_S
                break
            if item[0] != _WAKE:
                self._handle(handle, *item)
                handled += 1
        self._count_dropped_at_stop(self.inbox.close())
        for kind, message in self._take_feedback():  # what came with the last items
            self._handle(handle, kind, message)
        if handled:
            self.log.info("stopping: handled the %d messages left in the inbox", handled)
        if not quiet:  # input or feedback kept coming (say another robot's own client)
            self.counters.add("drain.hit_deadline")
            self.log.warning("stopping: input still arriving after inbox_drain_s=%.1f s",
                             self.inbox_drain_s)

    def _count_dropped_at_stop(self, items: list[tuple[str, Any]]) -> None:
        for kind, item in items:
            if kind == _RETIRE:  # its asker hears why at once, rather than time out
                QueryReply(item[1], "").refuse(f"{self.service}/{self.instance} is busy: stopping")
        left = sum(1 for kind, _ in items if kind != _WAKE)
        if left:
            self.counters.add("inbox.dropped_at_stop", left)
            self.log.warning(
                "stopping: %d messages left in the inbox were not handled within "
                "inbox_drain_s=%.1f s", left, self.inbox_drain_s,
            )

    def _idle(self, idle: Callable[[], None]) -> None:
        try:
            idle()
        except Exception:  # periodic work (snapshots, notices) must not stop the service
            n = self.counters.add("errors.idle")
            if worth_logging(n):
                self.log.exception("idle work failed (%d so far)", n)

    def _handle(self, handle: Callable[[str, Any], None], kind: str, message: Any) -> None:
        if kind == _RETIRE:
            handle = self._answer_retire
        t0, put0, get0 = time.perf_counter(), self._put_s, self._get_s
        try:
            handle(kind, message)
        except Exception:  # a bad message must not stop the service
            self.failed(kind)
        took_s = time.perf_counter() - t0
        self._handle_max_s = max(self._handle_max_s, took_s)
        if took_s > self.slow_message_s:  # everything behind it waited that long too
            n = self.counters.add(f"slow.{kind}")
            # Where the time went: a full outbox (a slow subscriber somewhere downstream) or
            # another service's answer, else this service's own work.
            self.log.warning(
                "a %s message took %.2f s to handle (%.2f s waiting to publish, %.2f s waiting "
                "on queries; slow_message_s=%.2f; %d so far), inbox now %d", kind, took_s,
                self._put_s - put0, self._get_s - get0, self.slow_message_s, n,
                self.inbox.depth(),
            )

    def failed(self, kind: str) -> None:
        """(In an except block.) Count (`errors.<kind>`) and log the exception that a `kind`
        message raised; the service goes on."""
        n = self.counters.add(f"errors.{kind}")
        if worth_logging(n):  # one bad source at the scan rate must not flood the log
            self.log.exception("failed to handle a %s message (%d so far)", kind, n)

    def stop(self) -> None:
        """Set the stop event: `run` returns after the item in hand; nothing is closed here."""
        self.stop_event.set()

    def __enter__(self) -> ServiceShell:
        return self

    def __exit__(self, exc_type: object, exc: BaseException | None, tb: object) -> None:
        """Close the shell however the block ends: after an uncaught error an open session's
        Zenoh threads keep the process, and its health token, alive for good (SIGTERM only
        sets the stop event), where it should exit and be restarted."""
        if exc is not None:
            self.log.critical("%s/%s stops on an error: %r", self.service, self.instance, exc)
        if not self._closed.is_set():
            self.close(flush_s=0.0 if exc is not None else 0.2)

    def close(self, flush_s: float = 0.2, drain_s: float = 10.0) -> None:
        """Send what the outbox holds (at most `drain_s`), let Zenoh's queues empty for
        `flush_s`, then undeclare everything and close the session."""
        self.stop_event.set()
        # A callback blocked on a full inbox returns (refused) at once; what a shell that never
        # drained (never ran) still held is counted.
        self._count_dropped_at_stop(self.inbox.close())
        left = self.outbox.close(drain_s)
        if left:
            self.log.warning("%d queued messages not sent within %.0f s", left, drain_s)
        time.sleep(flush_s)
        for entity in reversed(self._declared):
            try:
                entity.undeclare()
            except zenoh.ZError:
                self.log.debug("undeclare failed during close", exc_info=True)
        self._declared.clear()
        self._publishers.clear()
        self._closed.set()  # queries were answered up to here, through the drain
        if self._side is not None:
            self._side.close()
        self.session.close()
        self.log.info("%s/%s closed", self.service, self.instance)

    # -- stats --------------------------------------------------------------------------
    def stats(self) -> ServiceStatsMessage:
        """Counters (incl. per-stream seq gaps), queue depths, RSS and service gauges."""
        counters = self.counters.snapshot()
        counters.update({"puts.failed": self.outbox.failed, "puts.refused": self.outbox.refused})
        gauges: dict[str, float] = {
            "pid": os.getpid(),
            "uptime_s": time.monotonic() - self._started_s,
            "rss_bytes": rss_bytes(),
            "inbox_depth": self.inbox.depth(),
            "inbox_high_water": self.inbox.high_water,
            "worker_busy_s": self._busy_s,
            "put_s": self._put_s,
            "get_s": self._get_s,
            "handle_max_s": self._handle_max_s,
            "send_s": self.outbox.send_s,
            "outbox_depth": self.outbox.depth(),
        }
        for stream, figures in self.seqs.snapshot().items():
            gauges[f"seq.{stream}.last"] = figures.pop("last_seq")
            counters.update({f"seq.{stream}.{name}": n for name, n in figures.items()})
        for source in self._stats_sources:
            gauges.update(source())
        return ServiceStatsMessage(
            service=self.service,
            instance=self.instance,
            stamp_s=time.time(),
            counters=counters,
            gauges=gauges,
        )

    def _reply_stats(self, query: zenoh.Query) -> None:
        # Reply on our own concrete key: replies on the queried wildcard would be
        # consolidated into one across all services.
        try:
            query.reply(keys.stats(self.service, self.instance, self.prefix), self.stats().encode())
        except Exception as exc:  # a failing gauge source: the asker hears why, not silence
            self.counters.add("stats.failed")
            self.log.warning("stats failed: %s: %s", type(exc).__name__, exc)
            query.reply_err(f"{self.service}/{self.instance} stats: {type(exc).__name__}: {exc}")
        finally:
            query.drop()  # the reply is final now, not when the query object is collected

    def _serve_queries(self) -> None:
        while not self._closed.is_set():
            try:
                handler, query = self._queries.get(timeout=0.1)
            except queue.Empty:
                continue
            self._answer(handler, query)

    def _answer(self, handler: QueryHandler, query: zenoh.Query) -> None:
        try:
            handler(query)
            self.counters.add("queries.answered")
        except Exception as exc:  # a bad query gets an error reply, the service goes on
            self.counters.add("queries.failed")
            self.log.warning("query %s failed: %s", query.selector, exc)
            query.reply_err(f"{type(exc).__name__}: {exc}")
        finally:
            query.drop()

    def _count_malformed(self, kind: str, key: str, exc: Exception) -> None:
        n = self.counters.add(f"malformed.{kind}")
        if worth_logging(n):
            self.log.warning("malformed %s message #%d on %s: %s", kind, n, key, exc)

    def _on_signal(self, signum: int, _frame: object) -> None:
        self.log.info("signal %d: stopping", signum)
        self.stop_event.set()


def robots_only(handler: QueryHandler, prefix: str) -> QueryHandler:
    """`handler`, for queries on robots' keys: a query for the services' keys (a metrics
    scrape on `stats/*/*`) that reaches a `<prefix>/*/...` queryable is left unanswered,
    quietly (it used to fail there as robot 'stats', a warning per scrape)."""

    def answer(query: zenoh.Query) -> None:
        if not keys.addresses_services(str(query.key_expr), prefix):
            handler(query)

    return answer


def rss_bytes() -> int:
    """Resident set size of this process (Linux /proc; 0 where unavailable)."""
    try:
        with open("/proc/self/statm") as f:
            return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")
    except (OSError, ValueError, IndexError):
        return 0


def _has_subscribers(pub: zenoh.Publisher) -> bool:
    """Whether something subscribes to `pub`'s key now. zenoh's stub types `matching_status` as
    a bool; it is a MatchingStatus (zenoh 1.10), whose `matching` says so."""
    return cast(zenoh.MatchingStatus, pub.matching_status).matching
