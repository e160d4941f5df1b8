"""events.py: bus events handed from any thread to each interested stream client's queue."""

from __future__ import annotations

import asyncio
import threading

from services.gateway.events import EventHub, Subscription


def test_an_event_reaches_its_robots_and_the_every_robot_subscriptions_only():
    async def scenario() -> tuple[list, list, bool, int]:
        hub = EventHub(queue_len=8)
        mine, every, other = hub.subscribe("r1"), hub.subscribe(None), hub.subscribe("r2")
        clients = hub.clients
        thread = threading.Thread(target=hub.publish, args=("r1", "pose", {"x_m": 1.0}))
        thread.start()  # published from a Zenoh-like thread, not the loop's
        thread.join()
        got = [await asyncio.wait_for(s.queue.get(), 5.0) for s in (mine, every)]
        await asyncio.sleep(0)
        return got, [mine.dropped, every.dropped], other.queue.empty(), clients

    got, dropped, other_empty, clients = asyncio.run(scenario())
    assert got == [("r1", "pose", {"x_m": 1.0})] * 2
    assert dropped == [0, 0] and other_empty and clients == 3


def test_a_full_queue_drops_the_oldest_event_and_counts_it():
    async def scenario() -> tuple[list, int]:
        sub = Subscription("r1", asyncio.get_running_loop(), asyncio.Queue(2))
        for n in range(3):
            sub.offer(("r1", "pose", {"n": n}))
        return [sub.queue.get_nowait()[2]["n"] for _ in range(2)], sub.dropped

    assert asyncio.run(scenario()) == ([1, 2], 1)


def test_an_unsubscribed_client_gets_nothing_and_leaving_twice_is_no_error():
    async def scenario() -> tuple[int, bool]:
        hub = EventHub(queue_len=4)
        sub = hub.subscribe(None)
        hub.unsubscribe(sub)
        hub.unsubscribe(sub)
        hub.publish("r1", "map", {"revision": 2})
        await asyncio.sleep(0)
        return hub.clients, sub.queue.empty()

    assert asyncio.run(scenario()) == (0, True)


def test_a_client_whose_loop_has_closed_is_unsubscribed_on_publish():
    hub = EventHub(queue_len=4)

    async def subscribe() -> Subscription:
        return hub.subscribe("r1")

    asyncio.run(subscribe())  # the loop closes with the client still subscribed
    assert hub.clients == 1
    hub.publish("r1", "pose", {})
    assert hub.clients == 0
