"""Sessions from `ZenohSettings`: a bulk message past 16 MiB crosses a router whole, and a
reader held up for longer than Zenoh's default 5 s (a service whose worker stalls: its inbox
fills and the Zenoh callback waits) loses nothing, as the services' backpressure design needs.
With Zenoh's default, the router closes that link after 5 s and every message behind it is
gone (bench.link_stall; BENCHMARKS.md, "Services")."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest
import zenoh
from scanflow.config import MapServerSettings, MatcherSettings, ZenohSettings
from scanflow.wire import MAX_PAYLOAD_BYTES, KeyframesMessage, ResumeMessage, decode_any

from bench.link_stall import run
from services.common.launch import free_port
from services.common.shell import ServiceShell
from services.common.zsession import open_session, sorted_replies, zenoh_config

pytestmark = [pytest.mark.integration, pytest.mark.slow]

MESSAGES = 20_000  # 8 kB each: far more than the router's and the sockets' buffers hold
STALL_S = 6.0  # longer than Zenoh's own 5 s


def test_the_block_close_setting_reaches_the_zenoh_config() -> None:
    config = zenoh_config(ZenohSettings(block_close_s=12.5))
    key = "transport/link/tx/queue/congestion_control/block/wait_before_close"
    assert config.get_json(key) == "12500000"


def test_a_querys_replies_are_sorted_into_answers_and_errors() -> None:
    """Each answer with its key, each error reply's text (UTF-8 or not), none merged away."""
    session = open_session(ZenohSettings(mode="peer", connect=[]))

    def answer(query: zenoh.Query) -> None:
        query.reply("scanflow-test/sorted/a", b"one")
        query.reply("scanflow-test/sorted/a", b"two")
        query.reply_err("refused: busy")
        query.reply_err(b"\xff\xfe not text")  # any queryable may answer: still read

    queryable = session.declare_queryable("scanflow-test/sorted/*", answer)
    try:
        replies = session.get("scanflow-test/sorted/a", timeout=5.0,
                              consolidation=zenoh.ConsolidationMode.NONE)
        answers, errors = sorted_replies(replies)
    finally:
        queryable.undeclare()
        session.close()
    assert answers == [("scanflow-test/sorted/a", b"one"), ("scanflow-test/sorted/a", b"two")]
    assert errors == ["refused: busy", "\ufffd\ufffd not text"]


def test_a_reader_that_stalls_longer_than_zenohs_default_loses_nothing() -> None:
    report = run(ZenohSettings().block_close_s, STALL_S, MESSAGES, 8000)
    assert report["lost"] == 0 and report["in_order"], report


def test_a_bulk_message_past_the_payload_limit_crosses_a_router() -> None:
    """A map server's resume answer (or a path, a map) grows past 16 MiB on a long run: one reply,
    and one put (a redraw travels so), of ~40 MiB each reach the other side whole."""
    rng = np.random.default_rng(1)
    n = 5 * MAX_PAYLOAD_BYTES // 32  # 40 MiB of points
    points = rng.normal(size=(n, 2))
    kept = KeyframesMessage(
        "r", np.array([4, 9]), np.array([0.1, 0.2]), np.zeros((2, 3)), np.zeros((2, 3)),
        np.array([n - 5, 5]), points, np.array([0, 0]), np.zeros((0, 2)),
    )
    payload = ResumeMessage("r", 7, b"", np.zeros(1), np.zeros((1, 3)), kept).encode()
    assert len(payload) > 2 * MAX_PAYLOAD_BYTES
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    router = open_session(ZenohSettings(mode="router", listen=[endpoint], connect=[]))
    server = ServiceShell("mapserver", MapServerSettings(), ZenohSettings(connect=[endpoint]))
    client = ServiceShell("matcher", MatcherSettings(), ZenohSettings(connect=[endpoint]))
    heard: list[bytes] = []
    done = threading.Event()
    try:
        server.serve("scanflow-test/bulk", lambda q: q.reply(q.key_expr, payload), side=True)
        client.session.declare_subscriber(
            "scanflow-test/put", lambda s: (heard.append(s.payload.to_bytes()), done.set())
        )
        time.sleep(0.5)  # the subscriber's interest reaches the router
        replies, errors = client.get("scanflow-test/bulk", 30.0)
        server.put("scanflow-test/put", payload)  # reliable, blocking: as a redraw goes
        assert done.wait(30.0)
        for data in (*replies, *heard):
            back = decode_any(data)
            assert isinstance(back, ResumeMessage) and back.keyframes is not None
            assert back.keyframes.hits.tobytes() == points.tobytes()
        assert (len(replies), len(heard), errors) == (1, 1, [])
    finally:
        client.close(flush_s=0.0)
        server.close(flush_s=0.0)
        router.close()
