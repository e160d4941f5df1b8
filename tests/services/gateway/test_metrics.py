"""metrics.py: the gateway's counters and histograms and the services' stats in Prometheus text."""

from __future__ import annotations

import math

from hypothesis import given, settings
from hypothesis import strategies as st
from scanflow.wire import ServiceStatsMessage

from services.gateway.metrics import LATENCY_BUCKETS_S, Histogram, Metrics, render_service_stats


def test_without_figures_nothing_is_rendered():
    assert Metrics().render() == ""
    assert render_service_stats([]) == ""


def test_counters_add_up_per_label_set_and_render_with_help_and_type():
    metrics = Metrics()
    assert metrics.count("scanflow_gateway_ingested_total", kind="scan") == 1
    assert metrics.count("scanflow_gateway_ingested_total", 4, kind="scan") == 5
    assert metrics.count("scanflow_gateway_ingested_total", kind="odom") == 1
    lines = metrics.render().splitlines()
    assert lines == [
        "# HELP scanflow_gateway_ingested_total messages ingested over HTTP and published",
        "# TYPE scanflow_gateway_ingested_total counter",
        'scanflow_gateway_ingested_total{kind="odom"} 1',
        'scanflow_gateway_ingested_total{kind="scan"} 5',
    ]


def test_labels_are_sorted_and_escaped():
    metrics = Metrics()
    metrics.count("unknown_total", zeta="1", alpha='a "quoted"\\ new\nline')
    text = metrics.render()
    assert "# HELP unknown_total unknown_total" in text  # no help text: the name
    assert 'unknown_total{alpha="a \\"quoted\\"\\\\ new\\nline",zeta="1"} 1' in text
    assert text.endswith("\n")


def test_a_histogram_renders_cumulative_buckets_sum_and_count():
    metrics = Metrics()
    metrics.observe("scanflow_match_round_trip_seconds", 0.003, kind="scan_to_map")
    metrics.observe("scanflow_match_round_trip_seconds", 0.3, kind="scan_to_map")
    text = metrics.render()
    assert "# TYPE scanflow_match_round_trip_seconds histogram" in text
    name = "scanflow_match_round_trip_seconds"
    assert f'{name}_bucket{{kind="scan_to_map",le="0.001"}} 0' in text
    assert f'{name}_bucket{{kind="scan_to_map",le="0.005"}} 1' in text
    assert f'{name}_bucket{{kind="scan_to_map",le="0.25"}} 1' in text
    assert f'{name}_bucket{{kind="scan_to_map",le="0.5"}} 2' in text
    assert f'{name}_bucket{{kind="scan_to_map",le="+Inf"}} 2' in text
    assert f'{name}_sum{{kind="scan_to_map"}} {0.003 + 0.3!r}' in text
    assert f'{name}_count{{kind="scan_to_map"}} 2' in text


@settings(max_examples=50, deadline=None)
@given(st.lists(st.floats(0.0, 10.0), max_size=30))
def test_each_bucket_counts_the_values_it_does_not_exceed(values):
    hist = Histogram(LATENCY_BUCKETS_S)
    for value in values:
        hist.observe(value)
    assert hist.counts == [sum(v <= bound for v in values) for bound in LATENCY_BUCKETS_S]
    assert hist.total == len(values) and math.isclose(hist.sum, sum(values), abs_tol=1e-9)
    lines = hist.lines("h", ())
    assert lines[len(LATENCY_BUCKETS_S)] == f'h_bucket{{le="+Inf"}} {len(values)}'


def test_service_stats_fall_into_their_families():
    deskew = ServiceStatsMessage("deskew", "0", 1.0, {
        "received.scan": 12, "seq.r1/scan.received": 12, "seq.r1/scan.missed": 2,
        "seq.r1/scan.restarts": 1, "malformed.odom": 3, "queries.busy": 4,
    }, {"inbox_depth": 2.0, "floor": float("-inf")})
    matcher = ServiceStatsMessage("matcher", "1", 1.0, {"received.scan": 5}, {})
    text = render_service_stats([matcher, deskew])  # sorted by service, then instance
    deskew_labels = 'instance="0",service="deskew"'
    assert f"scanflow_scans_processed_total{{{deskew_labels}}} 12" in text
    assert f'scanflow_seq_received_total{{{deskew_labels},stream="r1/scan"}} 12' in text
    assert f'scanflow_seq_gaps_total{{{deskew_labels},stream="r1/scan"}} 2' in text
    assert f'scanflow_seq_restarts_total{{{deskew_labels},stream="r1/scan"}} 1' in text
    assert 'scanflow_malformed_total{instance="0",kind="odom",service="deskew"} 3' in text
    assert f'scanflow_service_events_total{{event="queries.busy",{deskew_labels}}} 4' in text
    assert 'scanflow_service_gauge{instance="0",name="floor",service="deskew"} -Inf' in text
    assert 'scanflow_service_gauge{instance="0",name="inbox_depth",service="deskew"} 2.0' in text
    up = [line for line in text.splitlines() if line.startswith("scanflow_service_up")]
    assert up == [f"scanflow_service_up{{{deskew_labels}}} 1",
                  'scanflow_service_up{instance="1",service="matcher"} 1']
    assert text.count("# TYPE scanflow_scans_processed_total counter") == 1
    assert "# TYPE scanflow_service_up gauge" in text
