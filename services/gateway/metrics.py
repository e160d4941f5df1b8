"""Prometheus text exposition (format 0.0.4) for the gateway's own figures and the services'.

Written by hand: counters and histograms with labels are all the gateway needs, and the
services' figures are gathered per scrape from their stats queryables.
"""

from __future__ import annotations

import math
import re
import threading
from collections import defaultdict
from collections.abc import Iterable

from scanflow.wire import ServiceStatsMessage

Labels = tuple[tuple[str, str], ...]
LATENCY_BUCKETS_S = (0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0)
HELP = {
    "scanflow_http_request_duration_seconds": "HTTP request latency by route, method and status",
    "scanflow_match_duration_seconds": "matcher compute time of match requests (its time_s)",
    "scanflow_match_round_trip_seconds": "time the gateway waited for a match answer",
    "scanflow_gateway_poses_received_total": "pose estimates the gateway received",
    "scanflow_gateway_malformed_total": "bus messages the gateway could not decode",
    "scanflow_gateway_ingested_total": "messages ingested over HTTP and published",
    "scanflow_gateway_publish_failed_total": "posts whose put Zenoh refused (answered 503)",
    "scanflow_scans_processed_total": "scans a service received (its received.scan counter)",
    "scanflow_seq_received_total": "messages a service received per sequenced stream",
    "scanflow_seq_gaps_total": "sequence numbers missed per stream (drops upstream)",
    "scanflow_seq_restarts_total": "times a stream's sequence numbers restarted",
    "scanflow_malformed_total": "messages a service could not decode, by kind",
    "scanflow_service_events_total": "every other counter a service reports",
    "scanflow_service_gauge": "point-in-time figures a service reports",
    "scanflow_service_up": "1 for each service that answered the stats query",
}
_SEQ_RE = re.compile(r"^seq\.(?P<stream>.+)\.(?P<what>received|missed|restarts)$")
_SEQ_FAMILY = {
    "received": "scanflow_seq_received_total",
    "missed": "scanflow_seq_gaps_total",
    "restarts": "scanflow_seq_restarts_total",
}


def _labels(**labels: str) -> Labels:
    return tuple(sorted(labels.items()))


def _escape(value: str) -> str:
    return value.replace("\\", "\\\\").replace("\n", "\\n").replace('"', '\\"')


def _fmt_labels(labels: Labels) -> str:
    if not labels:
        return ""
    return "{" + ",".join(f'{k}="{_escape(v)}"' for k, v in labels) + "}"


def _fmt_value(value: float) -> str:
    if math.isinf(value):
        return "+Inf" if value > 0 else "-Inf"
    return repr(float(value)) if isinstance(value, float) else str(value)


def _family(name: str, kind: str, samples: Iterable[str]) -> list[str]:
    lines = list(samples)
    if not lines:
        return []
    return [f"# HELP {name} {HELP.get(name, name)}", f"# TYPE {name} {kind}", *lines]


class Histogram:
    """Cumulative-bucket histogram of one label set."""

    def __init__(self, buckets: tuple[float, ...]) -> None:
        self.buckets = buckets
        self.counts = [0] * len(buckets)
        self.total = 0
        self.sum = 0.0

    def observe(self, value: float) -> None:
        """Count `value` in every bucket it does not exceed, and in the total and the sum."""
        for i, bound in enumerate(self.buckets):
            if value <= bound:
                self.counts[i] += 1
        self.total += 1
        self.sum += value

    def lines(self, name: str, labels: Labels) -> list[str]:
        """The `_bucket` (cumulative, then +Inf), `_sum` and `_count` sample lines of `name`."""
        out = [
            f"{name}_bucket{_fmt_labels((*labels, ('le', repr(bound))))} {n}"
            for bound, n in zip(self.buckets, self.counts, strict=True)
        ]
        out.append(f"{name}_bucket{_fmt_labels((*labels, ('le', '+Inf')))} {self.total}")
        out.append(f"{name}_sum{_fmt_labels(labels)} {self.sum!r}")
        out.append(f"{name}_count{_fmt_labels(labels)} {self.total}")
        return out


class Metrics:
    """The gateway's own counters and histograms, safe to update from any thread."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._counters: dict[str, dict[Labels, int]] = defaultdict(dict)
        self._histograms: dict[str, dict[Labels, Histogram]] = defaultdict(dict)

    def count(self, name: str, amount: int = 1, **labels: str) -> int:
        """Add `amount` to the labelled counter; its new value."""
        key = _labels(**labels)
        with self._lock:
            family = self._counters[name]
            family[key] = value = family.get(key, 0) + amount
            return value

    def observe(self, name: str, value_s: float, **labels: str) -> None:
        """Record `value_s` (seconds) in the labelled latency histogram, made on first use."""
        key = _labels(**labels)
        with self._lock:
            family = self._histograms[name]
            hist = family.get(key)
            if hist is None:
                hist = family[key] = Histogram(LATENCY_BUCKETS_S)
            hist.observe(value_s)

    def render(self) -> str:
        """These counters and histograms as exposition text; empty when there are none yet."""
        with self._lock:
            lines: list[str] = []
            for name, family in sorted(self._counters.items()):
                samples = (f"{name}{_fmt_labels(k)} {v}" for k, v in sorted(family.items()))
                lines += _family(name, "counter", samples)
            for name, hists in sorted(self._histograms.items()):
                samples = (line for k, h in sorted(hists.items()) for line in h.lines(name, k))
                lines += _family(name, "histogram", samples)
        return "\n".join(lines) + "\n" if lines else ""


def render_service_stats(stats: Iterable[ServiceStatsMessage]) -> str:
    """The services' counters and gauges as Prometheus families (labels service, instance)."""
    families: dict[str, list[str]] = defaultdict(list)
    kinds: dict[str, str] = {}
    for s in sorted(stats, key=lambda m: (m.service, m.instance)):
        base = {"service": s.service, "instance": s.instance}
        _add(families, kinds, "scanflow_service_up", "gauge", base, 1)
        for counter, count in sorted(s.counters.items()):
            name, labels = _counter_family(counter)
            _add(families, kinds, name, "counter", {**base, **labels}, count)
        for gauge, value in sorted(s.gauges.items()):
            _add(families, kinds, "scanflow_service_gauge", "gauge", {**base, "name": gauge}, value)
    lines: list[str] = []
    for name in sorted(families):
        lines += _family(name, kinds[name], families[name])
    return "\n".join(lines) + "\n" if lines else ""


def _counter_family(counter: str) -> tuple[str, dict[str, str]]:
    """Which family a service counter belongs to, and its extra labels."""
    seq = _SEQ_RE.match(counter)
    if seq:
        return _SEQ_FAMILY[seq["what"]], {"stream": seq["stream"]}
    if counter == "received.scan":
        return "scanflow_scans_processed_total", {}
    if counter.startswith("malformed."):
        return "scanflow_malformed_total", {"kind": counter.removeprefix("malformed.")}
    return "scanflow_service_events_total", {"event": counter}


def _add(
    families: dict[str, list[str]],
    kinds: dict[str, str],
    name: str,
    kind: str,
    labels: dict[str, str],
    value: float,
) -> None:
    kinds[name] = kind
    families[name].append(f"{name}{_fmt_labels(_labels(**labels))} {_fmt_value(value)}")
