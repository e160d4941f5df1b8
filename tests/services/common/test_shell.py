"""The service shell: worker, lanes and queries on a real session, robot filter, stats replies."""

from __future__ import annotations

import logging
import re
import threading
import time
from types import SimpleNamespace

from scanflow import keys
from scanflow.config import DeskewSettings, MatcherSettings, ZenohSettings
from scanflow.wire import RetiredMessage, RetireMessage

from services.common.counters import LOG_EVERY, LOG_FIRST
from services.common.launch import free_port
from services.common.retire import Dropped
from services.common.shell import DRAIN_QUIET_S, ServiceShell, robots_only
from services.common.zsession import open_session


def run_to_stop(shell: ServiceShell, caplog, level: int, handle, idle=None):
    """Run the deskew shell's worker until a handler stops it, logging at `level` into
    caplog; close it however that ends; its stats."""
    try:
        with caplog.at_level(level, logger="scanflow.deskew"):
            shell.run(handle, idle, poll_s=0.01)
        return shell.stats()
    finally:
        shell.close(flush_s=0.0)


def wait_until_answered(shell: ServiceShell, key: str, payload: bytes) -> None:
    """Query `key` until `payload` comes back: the shell's side session opens at its first
    `get`, and a queryable declared a moment before may not have reached the router yet."""
    deadline = time.monotonic() + 30.0
    while shell.get(key, 1.0) != ([payload], []):
        assert time.monotonic() < deadline, f"nothing answered on {key} within 30 s"
        time.sleep(0.05)


def wait_until_served(session, key: str) -> None:
    """Block until a queryable on `key` has reached `session`'s router: a query sent before
    meets no match and comes back empty (a fresh declaration takes a moment to propagate,
    longer under load)."""
    querier = session.declare_querier(key)
    deadline = time.monotonic() + 30.0
    try:
        while not querier.matching_status.matching:
            assert time.monotonic() < deadline, f"nothing serves {key}"
            time.sleep(0.05)
    finally:
        querier.undeclare()


def test_a_slow_message_is_logged_counted_and_measured(caplog) -> None:
    """A message handled for longer than slow_message_s holds up everything behind it: it is
    logged with its kind and duration, counted as slow.<kind>, and handle_max_s shows it."""
    settings = DeskewSettings.model_construct(slow_message_s=0.05)
    shell = ServiceShell("deskew", settings, ZenohSettings(mode="peer", connect=[]))
    handled: list[str] = []

    def handle(kind: str, sleep_s: float) -> None:
        time.sleep(sleep_s)
        handled.append(kind)
        if len(handled) == 2:
            shell.stop()

    shell.inbox.put("quick", 0.0)
    shell.inbox.put("scan", 0.2)
    stats = run_to_stop(shell, caplog, logging.WARNING, handle)
    assert handled == ["quick", "scan"]
    assert stats.counters["slow.scan"] == 1 and "slow.quick" not in stats.counters
    assert stats.gauges["handle_max_s"] >= 0.2
    assert "a scan message took 0.2" in caplog.text and "slow_message_s=0.05" in caplog.text
    # Its own work: no time waiting on the outbox or on queries.
    assert "(0.00 s waiting to publish, 0.00 s waiting on queries;" in caplog.text


def test_a_slow_message_says_how_long_it_waited_on_a_query(caplog) -> None:
    """A message slowed by another service's answer says so: the time its `get` waited is
    named in the slow-message log and summed in the get_s gauge."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    router = open_session(ZenohSettings(mode="router", listen=[endpoint], connect=[]))
    settings = MatcherSettings.model_construct(slow_message_s=0.1)
    shell = ServiceShell("matcher", settings, ZenohSettings(connect=[endpoint]))
    answers = open_session(ZenohSettings(connect=[endpoint]))
    delay_s = {"value": 0.0}

    def reply(query) -> None:
        time.sleep(delay_s["value"])
        query.reply(query.key_expr, b"map")

    queryable = answers.declare_queryable("scanflow-test/slow", reply)
    try:
        wait_until_answered(shell, "scanflow-test/slow", b"map")
        delay_s["value"] = 0.4
        before = shell.stats().gauges["get_s"]

        answered: list[tuple[list[bytes], list[str]]] = []

        def handle(_kind: str, _message: object) -> None:
            try:
                answered.append(shell.get("scanflow-test/slow", 5.0))
            finally:
                shell.stop()

        shell.inbox.put("scan", None)
        with caplog.at_level(logging.WARNING, logger="scanflow.matcher"):
            shell.run(handle, poll_s=0.01)
        waited = shell.stats().gauges["get_s"] - before
    finally:
        shell.close(flush_s=0.0)
        queryable.undeclare()
        answers.close()
        router.close()
    assert answered == [([b"map"], [])]
    assert waited >= 0.4
    found = re.search(r"a scan message took ([\d.]+) s to handle \(0\.00 s waiting to "
                      r"publish, ([\d.]+) s waiting on queries;", caplog.text)
    assert found, caplog.text
    assert float(found[1]) >= float(found[2]) >= 0.4


def test_failing_idle_work_is_logged_counted_and_the_worker_goes_on(caplog) -> None:
    """A snapshot that cannot be written (say) must not end the service: the idle call's error
    is counted as errors.idle, logged, and the next messages are still handled."""
    shell = ServiceShell("deskew", DeskewSettings(), ZenohSettings(mode="peer", connect=[]))
    handled: list[str] = []
    idles = []

    def idle() -> None:
        idles.append(1)
        if len(idles) == 1:
            shell.inbox.put("scan", None)
            raise OSError("disk full")

    def handle(kind: str, _message: object) -> None:
        handled.append(kind)
        shell.stop()

    stats = run_to_stop(shell, caplog, logging.ERROR, handle, idle)
    assert handled == ["scan"] and stats.counters["errors.idle"] == 1
    assert "idle work failed" in caplog.text and "disk full" in caplog.text


def test_a_message_that_fails_every_time_is_counted_and_logged_sparingly(caplog) -> None:
    """A source sending one bad message after another: every failure is counted, the first
    LOG_FIRST logged with their traceback, then one in LOG_EVERY; the worker goes on."""
    shell = ServiceShell("deskew", DeskewSettings(), ZenohSettings(mode="peer", connect=[]))
    total = LOG_EVERY + 5
    for _ in range(total):
        shell.inbox.put("scan", None)
    seen: list[int] = []

    def handle(_kind: str, _message: object) -> None:
        seen.append(1)
        if len(seen) == total:
            shell.stop()
        raise ValueError("bad ranges")

    stats = run_to_stop(shell, caplog, logging.ERROR, handle)
    assert len(seen) == total and stats.counters["errors.scan"] == total
    logged = [r for r in caplog.records if "failed to handle a scan message" in r.getMessage()]
    assert len(logged) == LOG_FIRST + 1 and all(r.exc_info for r in logged)
    assert f"({LOG_EVERY} so far)" in logged[-1].getMessage()


def test_a_full_feedback_lane_drops_the_oldest_hint_but_never_what_it_must_keep() -> None:
    """Feedback past queue_size drops the oldest waiting item, counted, except the ones
    `keep` marks (deskew: a pose carrying a map frame's correction)."""
    settings = DeskewSettings.model_construct(queue_size=3)
    shell = ServiceShell("deskew", settings, ZenohSettings(mode="peer", connect=[]))
    try:
        shell._keep["pose"] = lambda message: message.startswith("correction")
        for message in ("correction 0", "hint 1", "hint 2", "hint 3", "hint 4"):
            shell._feed("pose", message)
        shell._keep["pose"] = lambda message: True
        shell._feed("pose", "correction 5")  # everything waiting must stay: the lane grows
        assert [m for _, m in shell._take_feedback()] == [
            "correction 0", "hint 3", "hint 4", "correction 5"
        ]
        assert shell.counters.get("feedback_overflow.pose") == 2
    finally:
        shell.close(flush_s=0.0)


def test_a_side_query_is_answered_while_a_slow_query_holds_the_query_thread() -> None:
    """Queryables served `side=True` (the matcher's resend) answer at once, not queued behind
    a slow query on the query thread (a whole-map search takes seconds)."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    router = open_session(ZenohSettings(mode="router", listen=[endpoint], connect=[]))
    shell = ServiceShell("matcher", MatcherSettings(), ZenohSettings(connect=[endpoint]))
    started = threading.Event()

    def slow(query) -> None:
        started.set()
        time.sleep(3.0)
        query.reply(query.key_expr, b"slow")

    shell.serve("scanflow-test/slow", slow)
    shell.serve("scanflow-test/side", lambda q: q.reply(q.key_expr, b"side"), side=True)
    shell.start(install_signals=False)
    probe = open_session(ZenohSettings(connect=[endpoint]))
    try:
        for key in ("scanflow-test/slow", "scanflow-test/side"):
            wait_until_served(probe, key)
        waiting = threading.Thread(target=shell.get, args=("scanflow-test/slow", 10.0))
        waiting.start()
        assert started.wait(5.0)
        assert shell.get("scanflow-test/side", 1.0) == ([b"side"], [])
        waiting.join()
    finally:
        probe.close()
        shell.close(flush_s=0.0)
        router.close()


def test_a_query_for_the_services_keys_passes_robot_queryables_by():
    """A metrics scrape (stats/*/*) also reaches `*/map/resend`: not a robot named 'stats'."""
    seen = []
    handler = robots_only(seen.append, "site/sf")
    for key in ("site/sf/stats/matcher/0", "site/sf/health/deskew/0", "site/sf/r1/map/resend",
                "site/sf/statsbot/initial_pose"):
        handler(SimpleNamespace(key_expr=key))
    assert [q.key_expr for q in seen] == ["site/sf/r1/map/resend", "site/sf/statsbot/initial_pose"]


def test_wildcard_stats_query_gets_one_reply_per_service_instance(start, bus):
    start("deskew", SCANFLOW_DESKEW_INSTANCE="0")
    start("deskew", "deskew-1", SCANFLOW_DESKEW_INSTANCE="1")
    replies = bus.get(keys.stats("*", "*"), timeout_s=5.0)
    answered = sorted((r.service, r.instance) for r in replies)
    assert answered == [("deskew", "0"), ("deskew", "1"), ("router", "0")]


def test_a_failing_stats_source_is_an_error_reply_naming_it() -> None:
    """A gauge source that raises (say a robot's map mid-reset) must not leave the stats query
    unanswered: the asker gets an error reply naming the service and the cause, it is counted,
    and the next query, once the source works again, gets the stats."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    router = open_session(ZenohSettings(mode="router", listen=[endpoint], connect=[]))
    shell = ServiceShell("deskew", DeskewSettings(), ZenohSettings(connect=[endpoint]))
    broken = [True]

    def gauges() -> dict[str, float]:
        if broken[0]:
            raise KeyError("robot r7")
        return {"robots": 1.0}

    shell.add_stats(gauges)
    shell.start(install_signals=False)
    probe = open_session(ZenohSettings(connect=[endpoint]))
    try:
        key = keys.stats("deskew", "*", shell.prefix)
        wait_until_served(probe, keys.stats("deskew", shell.instance, shell.prefix))
        payloads, errors = shell.get(key, 5.0)
        assert payloads == [] and len(errors) == 1
        assert "deskew/" in errors[0] and "KeyError" in errors[0] and "robot r7" in errors[0]
        broken[0] = False
        payloads, errors = shell.get(key, 5.0)
        assert errors == [] and len(payloads) == 1
        assert shell.counters.get("stats.failed") == 1
    finally:
        probe.close()
        shell.close(flush_s=0.0)
        router.close()


def test_messages_waiting_in_the_inbox_at_stop_are_handled_not_dropped(caplog) -> None:
    """A clean stop (SIGTERM) arrives while scans wait in the inbox: they were accepted off the
    bus, so the worker handles them, in order, before `run` returns."""
    shell = ServiceShell("deskew", DeskewSettings(), ZenohSettings(mode="peer", connect=[]))
    handled: list[int] = []

    def handle(_kind: str, n: int) -> None:
        handled.append(n)
        if n == 0:
            shell.stop()  # the signal lands while 1..4 wait behind this one

    for n in range(5):
        shell.inbox.put("scan", n)
    try:
        with caplog.at_level(logging.INFO, logger="scanflow.deskew"):
            shell.run(handle, poll_s=0.01)
        assert shell.inbox.put("scan", 5) is False  # nothing new is taken once stopping
    finally:
        shell.close(flush_s=0.0)
    assert handled == [0, 1, 2, 3, 4]
    assert shell.counters.get("inbox.dropped_at_stop") == 0
    assert "handled the 4 messages left in the inbox" in caplog.text


def test_what_the_inbox_holds_past_the_drain_limit_is_counted_and_logged(caplog) -> None:
    """The drain is bounded (inbox_drain_s, within the container's stop grace period): what
    it could not handle is counted as inbox.dropped_at_stop and named in a warning."""
    settings = DeskewSettings.model_construct(inbox_drain_s=0.15)
    shell = ServiceShell("deskew", settings, ZenohSettings(mode="peer", connect=[]))
    handled: list[int] = []

    def handle(_kind: str, n: int) -> None:
        handled.append(n)
        if n == 0:
            shell.stop()
        else:
            time.sleep(0.1)

    for n in range(6):
        shell.inbox.put("scan", n)
    try:
        with caplog.at_level(logging.WARNING, logger="scanflow.deskew"):
            shell.run(handle, poll_s=0.01)
    finally:
        shell.close(flush_s=0.0)
    assert handled[0] == 0 and 2 <= len(handled) < 6
    left = 6 - len(handled)
    assert shell.counters.get("inbox.dropped_at_stop") == left
    assert f"{left} messages left in the inbox were not handled" in caplog.text


def test_what_arrives_during_the_drain_is_handled_and_after_it_refused() -> None:
    """Services stop in data-flow order: what the upstream one flushed at its stop may still
    be on the wire at this one's stop. The inbox takes it until the drain ends (nothing for
    DRAIN_QUIET_S); once the drain has closed it, a sample is counted as refused_at_stop."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    router = open_session(ZenohSettings(mode="router", listen=[endpoint], connect=[]))
    shell = ServiceShell("deskew", DeskewSettings(), ZenohSettings(connect=[endpoint]))
    shell.subscribe("scanflow-test/in", "raw", bytes)
    shell.start(install_signals=False)
    publisher = open_session(ZenohSettings(connect=[endpoint]))
    handled: list[bytes] = []

    def handle(_kind: str, message: bytes) -> None:
        handled.append(message)
        if message == b"before":
            shell.stop()
            publisher.put("scanflow-test/in", b"on the wire")  # arrives during the drain

    try:
        publisher.put("scanflow-test/in", b"before")
        shell.run(handle)
        publisher.put("scanflow-test/in", b"after")
        deadline = time.monotonic() + 5.0
        while shell.counters.get("refused_at_stop.raw") == 0 and time.monotonic() < deadline:
            time.sleep(0.01)
    finally:
        publisher.close()
        shell.close(flush_s=0.0)
        router.close()
    assert handled == [b"before", b"on the wire"]
    assert shell.counters.get("received.raw") == 3
    assert shell.counters.get("refused_at_stop.raw") == 1


def test_a_drain_waits_for_work_its_service_says_is_on_its_way() -> None:
    """A service thread's answer (the matcher's resume query) comes after the drain's quiet
    spell: while `pending()` says so the drain goes on, up to its deadline."""
    shell = ServiceShell("deskew", DeskewSettings(inbox_drain_s=5.0),
                         ZenohSettings(mode="peer", connect=[]))
    handled: list[str] = []
    answer = threading.Timer(4 * DRAIN_QUIET_S, shell.inbox.put, ("answer", None))

    def handle(kind: str, _message: object) -> None:
        handled.append(kind)
        if kind == "scan":
            shell.stop()
            answer.start()

    shell.inbox.put("scan", None)
    try:
        shell.run(handle, pending=lambda: "answer" not in handled)
    finally:
        answer.join()
        shell.close(flush_s=0.0)
    assert handled == ["scan", "answer"]
    assert "inbox.dropped_at_stop" not in shell.counters.snapshot()


def test_feedback_keeps_one_wake_in_the_inbox_and_a_drain_it_keeps_busy_ends_at_its_deadline(
    caplog,
) -> None:
    """Every feedback sample used to post its own wake item (filling inbox slots samples need);
    one waits now, and takes the whole lane. Feedback that never stops (another robot's own
    client) keeps the drain from going quiet: it ends at inbox_drain_s, counted and logged."""
    settings = DeskewSettings.model_construct(inbox_drain_s=0.5)
    shell = ServiceShell("deskew", settings, ZenohSettings(mode="peer", connect=[]))
    for n in range(10):
        shell._feed("pose", n)
    assert shell.inbox.depth() == 1
    handled: list[object] = []
    feeding = threading.Event()

    def feed() -> None:
        n = 10
        while not feeding.wait(0.05):
            shell._feed("pose", n)
            n += 1

    def handle(kind: str, message: object) -> None:
        handled.append(message)
        shell.stop()

    feeder = threading.Thread(target=feed, daemon=True)
    feeder.start()
    try:
        with caplog.at_level(logging.WARNING, logger="scanflow.deskew"):
            shell.run(handle, poll_s=0.01)
    finally:
        feeding.set()
        feeder.join()
        shell.close(flush_s=0.0)
    assert handled[:10] == list(range(10)) and len(handled) > 15  # fed through the drain
    assert shell.counters.get("drain.hit_deadline") == 1
    assert "input still arriving after inbox_drain_s=0.5 s" in caplog.text


def test_queries_are_answered_through_the_drain() -> None:
    """The query thread serves until close(), not until the stop: a map query to a map server
    that is draining is answered, not left to time out."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    router = open_session(ZenohSettings(mode="router", listen=[endpoint], connect=[]))
    shell = ServiceShell("mapserver", MatcherSettings(), ZenohSettings(connect=[endpoint]))
    shell.serve("scanflow-test/map", lambda q: q.reply(q.key_expr, b"map"))
    shell.start(install_signals=False)
    wait_until_answered(shell, "scanflow-test/map", b"map")
    answers: list[tuple[list[bytes], list[str]]] = []

    def handle(_kind: str, _message: object) -> None:
        shell.stop()
        answers.append(shell.get("scanflow-test/map", 5.0))  # the drain is under way

    shell.inbox.put("scan", None)
    shell.inbox.put("scan", None)
    try:
        shell.run(handle, poll_s=0.01)
    finally:
        shell.close(flush_s=0.0)
        router.close()
    assert answers == [([b"map"], []), ([b"map"], [])]


def test_a_block_that_raises_closes_the_shell_and_passes_the_error_on(caplog) -> None:
    """`with shell:` closes the session on an uncaught error (an open one keeps Zenoh's
    threads, so the process, alive), logs it, and lets it propagate; a clean block is closed
    once, however it closed itself."""
    shell = ServiceShell("deskew", DeskewSettings(), ZenohSettings(mode="peer", connect=[]))
    with caplog.at_level(logging.CRITICAL, logger="scanflow.deskew"):
        try:
            with shell:
                shell.start(install_signals=False)
                raise RuntimeError("a bug")
        except RuntimeError as exc:
            assert str(exc) == "a bug"
        else:
            raise AssertionError("the error was swallowed")
    assert shell._closed.is_set()
    assert "deskew/0 stops on an error: RuntimeError('a bug')" in caplog.text
    with ServiceShell("deskew", DeskewSettings(), ZenohSettings(mode="peer", connect=[])) as other:
        other.close(flush_s=0.0)  # closed inside: the exit does not close it again
    assert other._closed.is_set()


def test_a_sample_the_network_delivers_twice_is_handled_once_and_counted() -> None:
    """Two routes can copy a sample: the copy has the sample's timestamp, and to a service it
    would be a seq that does not advance, a restart that wipes the robot's map. It is dropped
    (duplicates.<kind>); a sample without a timestamp (a robot's own client) always passes,
    and the shell's own puts carry one."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    router = open_session(ZenohSettings(mode="router", listen=[endpoint], connect=[]))
    shell = ServiceShell("deskew", DeskewSettings(), ZenohSettings(connect=[endpoint]))
    client = open_session(ZenohSettings(connect=[endpoint]))
    got: list[str] = []
    stamps: list[object] = []
    shell.subscribe("scanflow-test/in", "scan", bytes.decode, lambda _k, m: got.append(m))
    watcher = client.declare_subscriber("scanflow-test/out", lambda s: stamps.append(s.timestamp))
    shell.start(install_signals=False)
    try:
        publisher = client.declare_publisher("scanflow-test/in")
        deadline = time.monotonic() + 30.0
        while not got:  # until the subscription has reached the router
            publisher.put(b"probe")
            assert time.monotonic() < deadline, "the shell's subscription never came up"
            time.sleep(0.05)
        stamp = client.new_timestamp()
        for payload, options in ((b"one", {"timestamp": stamp}), (b"one", {"timestamp": stamp}),
                                 (b"two", {}), (b"two", {})):
            publisher.put(payload, **options)
        while got.count("two") < 2:  # sent last: everything before it has come
            assert time.monotonic() < deadline, f"the samples did not all come: {got}"
            time.sleep(0.05)
        assert [m for m in got if m != "probe"] == ["one", "two", "two"]
        assert shell.counters.get("duplicates.scan") == 1
        shell.put("scanflow-test/out", b"x")
        while not stamps:
            assert time.monotonic() < deadline, "the shell's put never came"
            time.sleep(0.05)
        assert stamps[0] is not None
    finally:
        watcher.undeclare()
        shell.close(flush_s=0.0)
        client.close()
        router.close()


class RetireBus:
    """A router, a deskew shell serving retire queries, a worker thread running it and a client
    that asks; the worker holds each inbox item until `gate` opens."""

    def __init__(self, drop) -> None:
        endpoint = f"tcp/127.0.0.1:{free_port()}"
        self.router = open_session(ZenohSettings(mode="router", listen=[endpoint], connect=[]))
        self.shell = ServiceShell("deskew", DeskewSettings(), ZenohSettings(connect=[endpoint]))
        self.client = open_session(ZenohSettings(connect=[endpoint]))
        self.gate = threading.Event()
        self.handled: list[object] = []
        self.shell.serve_retire(drop)
        self.shell.start(install_signals=False)
        self.worker = threading.Thread(target=self.shell.run, args=(self.handle,),
                                       kwargs={"poll_s": 0.01})

    def handle(self, _kind: str, message: object) -> None:
        assert self.gate.wait(30.0), "the test never opened the gate"
        self.handled.append(message)
        self.shell.put("scanflow-test/out", b"out")

    def ask(self, key: str, payload: bytes | None) -> list:
        """The replies to a retire query (ok: RetiredMessage, error: its text), once the
        shell's queryable has reached the router."""
        wait_until_served(self.client, key)
        return [
            RetiredMessage.decode(r.ok.payload.to_bytes()) if r.ok is not None
            else r.err.payload.to_string()
            for r in self.client.get(key, payload=payload, timeout=30.0)
        ]

    def close(self) -> None:
        self.gate.set()
        self.shell.stop()
        if self.worker.is_alive():
            self.worker.join()
        self.shell.close(flush_s=0.0)
        self.client.close()
        self.router.close()


def test_a_robot_is_retired_on_the_worker_behind_what_came_before_and_answered_behind_its_puts():
    """The drop runs on the worker, after the inbox items that came before the query (they
    cannot start the robot again afterwards); the answer is queued in the outbox behind what
    the worker published before it; the shell forgets the robot's seqs and seen samples."""
    dropped_on: list[str] = []

    def drop(robot_id: str) -> Dropped:
        dropped_on.append(threading.current_thread().name)
        return Dropped(False, {"scans_pending": 2})

    bus = RetireBus(drop)
    shell = bus.shell
    queued: list[str] = []
    send = shell.outbox.put

    def spy(publisher, payload, **options):
        queued.append(type(publisher).__name__)
        return send(publisher, payload, **options)

    shell.outbox.put = spy
    for stream in ("r/scan", "r2/scan"):
        shell.seqs.observe(stream, 3)
    for key in ("scan:scanflow/r/scan/raw", "scan:scanflow/r2/scan/raw"):
        shell._seen.first(key, 1)
    shell.inbox.put("scan", "before")
    bus.worker.start()
    answers: list = []
    try:
        asking = threading.Thread(target=lambda: answers.extend(
            bus.ask(keys.retire("r", "deskew"), RetireMessage("r").encode())))
        asking.start()
        deadline = time.monotonic() + 30.0
        while shell.inbox.depth() == 0:  # the retire waits behind the held item
            assert time.monotonic() < deadline, "the retire query never reached the inbox"
            time.sleep(0.02)
        assert not dropped_on
        bus.gate.set()
        asking.join()
    finally:
        bus.close()
    assert bus.handled == ["before"] and dropped_on == [bus.worker.name]
    assert queued == ["Publisher", "QueryReply"]
    (answer,) = answers
    assert (answer.robot_id, answer.service, answer.instance) == ("r", "deskew", "0")
    assert answer.known and answer.dropped == {"scans_pending": 2}  # it had seqs here
    assert sorted(shell.seqs.snapshot()) == ["r2/scan"]
    assert shell._seen.first("scan:scanflow/r/scan/raw", 1)  # forgotten: new again
    assert not shell._seen.first("scan:scanflow/r2/scan/raw", 1)
    assert shell.counters.get("robots_retired") == 1


def test_a_bad_retire_query_or_a_failing_drop_is_an_error_reply_and_the_worker_goes_on():
    """Each names why (the service too, for a drop that failed); a metrics scrape on stats/*/*
    that reaches the retire queryable is left to the stats queryable."""
    def drop(robot_id: str) -> Dropped:
        if robot_id == "broken":
            raise OSError("disk gone")
        return Dropped(False)

    bus = RetireBus(drop)
    bus.gate.set()
    bus.worker.start()
    try:
        (wrong,) = bus.ask(keys.retire("r", "deskew"), RetireMessage("other").encode())
        (junk,) = bus.ask(keys.retire("r", "deskew"), b"junk")
        (failed,) = bus.ask(keys.retire("broken", "deskew"), RetireMessage("broken").encode())
        (unknown,) = bus.ask(keys.retire("r", "deskew"), RetireMessage("r").encode())
        scrape = bus.client.get(keys.stats("*", "*"), timeout=10.0)  # reaches */retire/* too
        assert [r.ok is not None for r in scrape] == [True]  # the stats; no error from retire
    finally:
        bus.close()
    assert wrong.startswith("ValueError: retiring 'other' from deskew must be asked on")
    assert junk.startswith("DecodeError: ")
    assert failed == "OSError: deskew/0: disk gone"
    assert not unknown.known and unknown.dropped == {}
    counters = bus.shell.counters
    assert counters.get("malformed.retire") == 2 and counters.get("retire.failed") == 1
    assert counters.get("retire.answered") == 1 and counters.get("robots_retired") == 0
