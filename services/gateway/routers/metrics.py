"""GET /metrics: Prometheus text with the gateway's figures and every service's stats."""

from __future__ import annotations

from fastapi import APIRouter, Request
from fastapi.responses import PlainTextResponse
from scanflow import keys
from scanflow.wire import DecodeError, ServiceStatsMessage

from services.gateway.backend import BackendError
from services.gateway.deps import Backend
from services.gateway.metrics import render_service_stats

router = APIRouter(tags=["health"])
CONTENT_TYPE = "text/plain; version=0.0.4; charset=utf-8"
STATS_TIMEOUT_S = 1.0


@router.get(
    "/metrics", response_class=PlainTextResponse,
    responses={200: {"content": {"text/plain": {}}, "description": "Prometheus text format"}},
    summary="Prometheus metrics: scans, drops, gaps, match and request latencies",
)
async def metrics(request: Request, backend: Backend) -> PlainTextResponse:
    try:
        replies = await backend.aquery(keys.stats("*", "*", backend.prefix), None, STATS_TIMEOUT_S)
    except BackendError:
        replies = []  # no service up: the gateway's own figures still count
    stats = []
    for reply in replies:
        try:
            stats.append(ServiceStatsMessage.decode(reply.payload))
        except DecodeError:
            backend.metrics.count("scanflow_gateway_malformed_total", kind="stats")
    text = (
        request.app.state.metrics.render()
        + backend.metrics.render()
        + render_service_stats(stats)
    )
    return PlainTextResponse(text, media_type=CONTENT_TYPE)
