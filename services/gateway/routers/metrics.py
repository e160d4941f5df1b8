"""GET /metrics: Prometheus text with the gateway's figures and every service's stats."""

from __future__ import annotations

import anyio.to_thread
from fastapi import APIRouter, Request
from fastapi.responses import PlainTextResponse

from services.gateway.deps import Backend
from services.gateway.metrics import render_service_stats

router = APIRouter(tags=["health"])
CONTENT_TYPE = "text/plain; version=0.0.4; charset=utf-8"


@router.get(
    "/metrics", response_class=PlainTextResponse,
    responses={200: {"content": {"text/plain": {}}, "description": "Prometheus text format"}},
    summary="Prometheus metrics: scans, drops, gaps, match and request latencies",
)
async def metrics(request: Request, backend: Backend) -> PlainTextResponse:
    """Prometheus text: the gateway's request and match figures, then every service's counters."""
    stats = await anyio.to_thread.run_sync(backend.service_stats)
    text = (
        request.app.state.metrics.render()
        + backend.metrics.render()
        + render_service_stats(stats)
    )
    return PlainTextResponse(text, media_type=CONTENT_TYPE)
