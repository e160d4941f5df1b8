"""Sessions from `ZenohSettings`: a reader held up for longer than Zenoh's default 5 s (a
service whose worker stalls: its inbox fills and the Zenoh callback waits) loses nothing, as
the services' backpressure design needs. With Zenoh's default, the router closes that link
after 5 s and every message behind it is gone (measured in BENCHMARKS.md, "Services")."""

from __future__ import annotations

import threading
import time

import pytest
import zenoh
from scanflow.config import ZenohSettings

from services.common.launch import free_port
from services.common.zsession import open_session, zenoh_config

pytestmark = [pytest.mark.integration, pytest.mark.slow]

MESSAGES = 20_000  # 8 kB each: far more than the router's and the sockets' buffers hold
STALL_S = 6.0  # longer than Zenoh's own 5 s


def test_the_block_close_setting_reaches_the_zenoh_config() -> None:
    config = zenoh_config(ZenohSettings(block_close_s=12.5))
    key = "transport/link/tx/queue/congestion_control/block/wait_before_close"
    assert config.get_json(key) == "12500000"


def test_a_reader_that_stalls_longer_than_zenohs_default_loses_nothing() -> None:
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    router = open_session(ZenohSettings(mode="router", listen=[endpoint], connect=[]))
    reader = open_session(ZenohSettings(connect=[endpoint]))
    writer = open_session(ZenohSettings(connect=[endpoint]))
    got: list[int] = []
    done = threading.Event()

    def on_sample(sample: zenoh.Sample) -> None:
        got.append(int(sample.payload.to_bytes()[:8]))
        if len(got) == 1:
            time.sleep(STALL_S)  # the worker stalls; Zenoh's callback waits with it
        if len(got) == MESSAGES:
            done.set()

    try:
        subscriber = reader.declare_subscriber("scanflow-test/stall", on_sample)
        publisher = writer.declare_publisher(
            "scanflow-test/stall",
            congestion_control=zenoh.CongestionControl.BLOCK,
            reliability=zenoh.Reliability.RELIABLE,
        )
        time.sleep(0.5)  # the subscription reaches the router
        for i in range(MESSAGES):
            publisher.put(f"{i:08d}".encode() + bytes(8000))
        done.wait(60.0)
        assert got == list(range(MESSAGES)), f"{len(got)} of {MESSAGES} came"
        subscriber.undeclare()
        publisher.undeclare()
    finally:
        for session in (writer, reader, router):
            session.close()
