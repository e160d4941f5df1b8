"""The bounded inbox: it blocks a producer instead of dropping, until it is closed."""

from __future__ import annotations

import threading

from hypothesis import given, settings
from hypothesis import strategies as st

from services.common.inbox import Inbox


def test_inbox_blocks_instead_of_dropping_and_releases_on_close():
    inbox = Inbox(2)
    assert inbox.put("a", 1) and inbox.put("a", 2)
    assert inbox.offer("a", 9) is False  # full: offer does not wait
    done = threading.Event()
    results: list[bool] = []

    def producer():
        results.append(inbox.put("a", 3))
        results.append(inbox.put("a", 4))  # full again: waits until the close
        done.set()

    threading.Thread(target=producer, daemon=True).start()
    assert inbox.get(0.3) == ("a", 1)  # room: the producer's first put goes in
    assert not done.wait(0.3)  # its second waits
    assert inbox.close() == [("a", 2), ("a", 3)]  # what was left, oldest first
    assert done.wait(2.0) and results == [True, False]  # released, refused: never half taken
    assert inbox.put("a", 5) is False and inbox.offer("a", 6) is False
    assert inbox.close() == [] and inbox.get(0.0) is None and inbox.depth() == 0
    assert inbox.high_water == 2


@settings(max_examples=20, deadline=None)
@given(st.lists(st.integers(), max_size=60), st.integers(1, 8))
def test_every_item_put_is_got_or_handed_back_at_close_in_order(items, size):
    """One producer, one consumer that stops early: nothing put is lost or duplicated."""
    inbox = Inbox(size)
    accepted: list[int] = []

    def producer():
        for item in items:
            if inbox.put("k", item):
                accepted.append(item)

    thread = threading.Thread(target=producer, daemon=True)
    thread.start()
    got = []
    for _ in range(len(items) // 2):
        item = inbox.get(1.0)
        if item is None:
            break
        got.append(item[1])
    left = [item for _, item in inbox.close()]
    thread.join(5.0)
    assert got + left == accepted == items[: len(accepted)]
