"""Every service answers a wildcard stats query with its own reply (none merged away)."""

from __future__ import annotations

from scanflow import keys


def test_wildcard_stats_query_gets_one_reply_per_service_instance(start, bus):
    start("deskew", SCANFLOW_DESKEW_INSTANCE="0")
    start("deskew", "deskew-1", SCANFLOW_DESKEW_INSTANCE="1")
    replies = bus.get(keys.stats("*", "*"), timeout_s=5.0)
    answered = sorted((r.service, r.instance) for r in replies)
    assert answered == [("deskew", "0"), ("deskew", "1"), ("router", "0")]
