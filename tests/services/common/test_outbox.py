"""The outbox: puts leave in order from one thread; a full outbox blocks, close drains it."""

from __future__ import annotations

import math
import threading
import time

from hypothesis import given, settings
from hypothesis import strategies as st

from services.common.outbox import Outbox


class GatedPublisher:
    """Records payloads; each put waits until the gate is open (a slow subscriber)."""

    def __init__(self, open_gate: bool = True, fail_on: bytes | None = None) -> None:
        self.sent: list[bytes] = []
        self.gate = threading.Event()
        self.fail_on = fail_on
        if open_gate:
            self.gate.set()

    def put(self, payload: bytes) -> None:
        self.gate.wait()
        if payload == self.fail_on:
            raise RuntimeError("session closing")
        self.sent.append(payload)


@settings(max_examples=25, deadline=None)
@given(st.lists(st.tuples(st.sampled_from("ab"), st.binary(max_size=8)), max_size=40))
def test_every_payload_leaves_in_order_per_publisher_and_overall(items):
    publishers = {"a": GatedPublisher(), "b": GatedPublisher()}
    outbox = Outbox(4, lambda: math.inf)
    for key, payload in items:
        assert outbox.put(publishers[key], payload)
    assert outbox.close(5.0) == 0
    for key, pub in publishers.items():
        assert pub.sent == [p for k, p in items if k == key]


def test_a_full_outbox_blocks_the_worker_and_close_sends_everything():
    pub = GatedPublisher(open_gate=False)
    outbox = Outbox(2, lambda: math.inf)
    for payload in (b"0", b"1", b"2"):  # one held by the blocked sender, two queued
        assert outbox.put(pub, payload)
    done = threading.Event()
    threading.Thread(target=lambda: (outbox.put(pub, b"3"), done.set()), daemon=True).start()
    assert not done.wait(0.3)  # full: the worker waits, nothing is dropped
    pub.gate.set()
    assert done.wait(2.0)
    assert outbox.close(5.0) == 0
    assert pub.sent == [b"0", b"1", b"2", b"3"]


def test_a_failed_put_is_counted_and_the_sender_goes_on():
    pub = GatedPublisher(fail_on=b"bad")
    outbox = Outbox(4, lambda: math.inf)
    for payload in (b"a", b"bad", b"b"):
        outbox.put(pub, payload)
    assert outbox.close(5.0) == 0
    assert pub.sent == [b"a", b"b"]
    assert outbox.failed == 1


def test_past_the_stop_deadline_a_full_outbox_refuses_and_close_reports_what_is_left():
    """While stopping, a full outbox still waits until the stop's deadline (what the drain
    hands it is sent); past it, it refuses rather than hold the stop up."""
    deadline = [math.inf]
    pub = GatedPublisher(open_gate=False)
    outbox = Outbox(1, lambda: deadline[0])
    assert outbox.put(pub, b"held") and outbox.put(pub, b"queued")
    deadline[0] = time.monotonic() + 0.6
    answers: list[bool] = []
    late = threading.Thread(target=lambda: answers.append(outbox.put(pub, b"late")))
    late.start()
    late.join(0.2)
    assert late.is_alive()  # before the deadline it waits for room
    late.join(5.0)
    assert answers == [False] and outbox.refused == 1
    assert outbox.close(0.3) == 1  # the sender is still stuck on "held"
    pub.gate.set()
