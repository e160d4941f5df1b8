"""Server-sent events of live poses (event `pose`) and map changes (event `map`)."""

from __future__ import annotations

import asyncio
import json
from collections.abc import AsyncIterator
from typing import Annotated

from fastapi import APIRouter, Query, Request
from fastapi.sse import EventSourceResponse, ServerSentEvent

from services.gateway.deps import API_PREFIX, Backend, Robot
from services.gateway.events import EventHub

router = APIRouter(prefix=API_PREFIX, tags=["stream"])
Limit = Annotated[int | None, Query(ge=1, le=1_000_000, description="close after this many events")]
IDLE_CHECK_S = 1.0
DESCRIPTION = (
    "text/event-stream: `event: pose` with a PoseOut as data, `event: map` with "
    "{robot_id, revision, box_m}. `limit` ends the stream after that many events."
)


@router.get("/robots/{robot}/poses/stream", response_class=EventSourceResponse,
            summary="Live poses and map changes of one robot", description=DESCRIPTION)
async def robot_stream(
    request: Request, robot: Robot, backend: Backend, limit: Limit = None
) -> AsyncIterator[ServerSentEvent]:
    """One robot's pose and map events as they come (the route's `description` is the doc)."""
    async for event in _events(request, backend.events, robot, limit):
        yield event


@router.get("/poses/stream", response_class=EventSourceResponse,
            summary="Live poses and map changes of every robot", description=DESCRIPTION)
async def all_stream(
    request: Request, backend: Backend, limit: Limit = None
) -> AsyncIterator[ServerSentEvent]:
    """Every robot's pose and map events as they come (the route's `description` is the doc)."""
    async for event in _events(request, backend.events, None, limit):
        yield event


async def _events(
    request: Request, hub: EventHub, robot: str | None, limit: int | None
) -> AsyncIterator[ServerSentEvent]:
    sub = hub.subscribe(robot)
    sent = 0
    try:
        while limit is None or sent < limit:
            try:
                robot_id, name, data = await asyncio.wait_for(sub.queue.get(), IDLE_CHECK_S)
            except TimeoutError:
                if await request.is_disconnected():
                    return
                continue
            payload = json.dumps({"robot_id": robot_id, **data}, allow_nan=False)
            yield ServerSentEvent(event=name, raw_data=payload)
            sent += 1
    finally:
        hub.unsubscribe(sub)
