"""The ingest service on real processes: it publishes nothing before a subscriber is there."""

from __future__ import annotations

import pytest
from scanflow import keys

pytestmark = [pytest.mark.integration]

def test_ingest_waits_for_a_subscriber_before_publishing(launcher, bus, start):
    deskewed = bus.record(keys.deskewed_scan())
    launcher.start(
        "ingest",
        SCANFLOW_INGEST_WINDOW="0",
        SCANFLOW_INGEST_DRAIN_TIMEOUT_S="0.5",
        SCANFLOW_INGEST_SIM_DURATION_S="1",
    )
    bus.wait_until(lambda: "ingest/0" in bus.alive(), 30.0, "ingest up")
    start("deskew")
    bus.wait_until(lambda: len(deskewed) == 10, 30.0, "all 10 scans, none published into nothing")
    assert [m.seq for m in deskewed] == list(range(10))
