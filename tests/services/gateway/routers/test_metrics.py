"""GET /metrics: the gateway's own figures and every service's stats in Prometheus text."""

from __future__ import annotations

from scanflow import keys
from scanflow.wire import ServiceStatsMessage


def test_metrics_aggregate_service_stats(client, peer, auth):
    stats = ServiceStatsMessage("deskew", "0", 1.0, {
        "received.scan": 12, "seq.r1/scan.missed": 2, "malformed.scan": 1, "queries.busy": 3,
    }, {"inbox_depth": 0.0, "limit": float("inf")})
    peer.answer(keys.stats("deskew", "0"), lambda q: stats.encode())
    client.get("/api/v1/robots")
    text = client.get("/metrics").text
    assert 'scanflow_scans_processed_total{instance="0",service="deskew"} 12' in text
    assert 'scanflow_seq_gaps_total{instance="0",service="deskew",stream="r1/scan"} 2' in text
    assert 'scanflow_malformed_total{instance="0",kind="scan",service="deskew"} 1' in text
    assert 'name="limit",service="deskew"} +Inf' in text
    assert 'scanflow_http_request_duration_seconds_count{method="GET",route="/api/v1/robots"' \
           in text
    assert text.count("# TYPE scanflow_service_gauge gauge") == 1


def test_metrics_are_prometheus_text_with_the_gateways_own_counters(client, backend):
    backend.metrics.count("scanflow_gateway_ingested_total", kind="scan")
    r = client.get("/metrics")
    assert r.headers["content-type"] == "text/plain; version=0.0.4; charset=utf-8"
    assert 'scanflow_gateway_ingested_total{kind="scan"} 1' in r.text
    assert "scanflow_service_up" not in r.text  # no service answers the stats query
