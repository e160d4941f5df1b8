"""Sessions from `ZenohSettings`: a reader held up for longer than Zenoh's default 5 s (a
service whose worker stalls: its inbox fills and the Zenoh callback waits) loses nothing, as
the services' backpressure design needs. With Zenoh's default, the router closes that link
after 5 s and every message behind it is gone (bench.link_stall; BENCHMARKS.md, "Services")."""

from __future__ import annotations

import pytest
from scanflow.config import ZenohSettings

from bench.link_stall import run
from services.common.zsession import zenoh_config

pytestmark = [pytest.mark.integration, pytest.mark.slow]

MESSAGES = 20_000  # 8 kB each: far more than the router's and the sockets' buffers hold
STALL_S = 6.0  # longer than Zenoh's own 5 s


def test_the_block_close_setting_reaches_the_zenoh_config() -> None:
    config = zenoh_config(ZenohSettings(block_close_s=12.5))
    key = "transport/link/tx/queue/congestion_control/block/wait_before_close"
    assert config.get_json(key) == "12500000"


def test_a_reader_that_stalls_longer_than_zenohs_default_loses_nothing() -> None:
    report = run(ZenohSettings().block_close_s, STALL_S, MESSAGES, 8000)
    assert report["lost"] == 0 and report["in_order"], report
