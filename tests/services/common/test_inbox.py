"""The bounded inbox: it blocks a producer instead of dropping, and releases it on stop."""

from __future__ import annotations

import threading

from services.common.inbox import Inbox


def test_inbox_blocks_instead_of_dropping_and_releases_on_stop():
    stop = threading.Event()
    inbox = Inbox(2, stop)
    assert inbox.put("a", 1) and inbox.put("a", 2)
    done = threading.Event()

    def producer():
        inbox.put("a", 3)
        done.set()

    threading.Thread(target=producer, daemon=True).start()
    assert not done.wait(0.3)  # full: the producer waits
    assert inbox.get() == ("a", 1)
    assert done.wait(2.0)
    assert [inbox.get(), inbox.get()] == [("a", 2), ("a", 3)]
    stop.set()
    assert inbox.put("a", 4) is False  # stopping: refuses rather than block shutdown
