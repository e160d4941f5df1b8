"""A robot's map from the map server: metadata, PNG, PGM + YAML (map_server) apart or in one
zip, optionally a region.

The whole map comes from the map server's image queryable as it exported it; a region (world
box x0, y0, x1, y1 in metres) comes from its region queryable and is written by the library's
exporters here.
"""

from __future__ import annotations

from typing import Annotated, Literal

from fastapi import APIRouter, HTTPException, Query
from fastapi.responses import Response
from scanflow import keys
from scanflow.maps.export import RosGrid, map_file_bytes
from scanflow.wire import MapImageMessage, MapMetaMessage, MapRegionMessage
from starlette.concurrency import run_in_threadpool

from services.gateway.backend import BackendError
from services.gateway.deps import API_PREFIX, BAD_GATEWAY, Backend, Robot
from services.gateway.models import MapMetaOut

router = APIRouter(prefix=API_PREFIX, tags=["maps"])
Bound = Annotated[float | None, Query(ge=-1e6, le=1e6, description="metres")]
MEDIA = {"png": "image/png", "pgm": "image/x-portable-graymap", "yaml": "application/yaml",
         "zip": "application/zip"}
ANSWERS = {404: {"description": "no map for this robot"}, 422: {"description": "bad region"},
           503: {"description": "no map server answers"}, 504: {"description": "timed out"},
           **BAD_GATEWAY}


@router.get("/robots/{robot}/map", response_model=MapMetaOut, responses=ANSWERS,
            summary="Map metadata: resolution, origin, size, revision")
async def map_meta(robot: Robot, backend: Backend) -> MapMetaOut:
    """The robot's map as the map server holds it now: resolution, origin, size and revision."""
    replies = await backend.aquery(keys.map_key(robot, "meta", backend.prefix))
    return MapMetaOut.from_message(MapMetaMessage.decode(replies[0].payload))


@router.get(
    "/robots/{robot}/map.{fmt}",
    response_class=Response,
    responses={**ANSWERS, 200: {"content": {m: {} for m in MEDIA.values()},
                                "description": "the map file"}},
    summary="The map as PNG, or PGM + YAML for ROS map_server, or both of those in one zip "
    "(optionally a region)",
)
async def map_file(
    robot: Robot,
    backend: Backend,
    fmt: Literal["png", "pgm", "yaml", "zip"],
    x0: Bound = None,
    y0: Bound = None,
    x1: Bound = None,
    y1: Bound = None,
) -> Response:
    """The whole map as the map server exported it, or with all of x0, y0, x1, y1 (metres, map
    frame) the cells inside that box; `X-Map-Revision` says which revision it is. A growing map
    can change between a .yaml and a .pgm download: .zip holds the two of one revision. Every
    file is named `<robot>.<fmt>` (Content-Disposition), the name a .yaml's `image:` gives."""
    bounds = (x0, y0, x1, y1)
    headers = {"Cache-Control": "no-cache",
               "Content-Disposition": f'inline; filename="{robot}.{fmt}"'}
    if all(b is None for b in bounds):
        selector = f"{keys.map_key(robot, 'image', backend.prefix)}?format={fmt}"
        try:
            replies = await backend.aquery(selector)
        except BackendError as exc:
            if exc.status_code == 422 and "empty" in exc.reason:
                raise HTTPException(404, f"the map of {robot!r} is still empty") from exc
            raise
        image = MapImageMessage.decode(replies[0].payload)
        headers["X-Map-Revision"] = str(image.revision)
        return Response(image.data, media_type=MEDIA[fmt], headers=headers)
    if x0 is None or y0 is None or x1 is None or y1 is None:
        raise HTTPException(422, f"query: give all of x0, y0, x1, y1 or none, got {bounds}")
    if x0 > x1 or y0 > y1:
        raise HTTPException(422, f"query: need x0 <= x1 and y0 <= y1, got {bounds}")
    selector = f"{keys.map_key(robot, 'region', backend.prefix)}?x0={x0};y0={y0};x1={x1};y1={y1}"
    region = MapRegionMessage.decode((await backend.aquery(selector))[0].payload)
    if region.occupancy.size == 0:
        raise HTTPException(404, f"the map of {robot!r} has no cells in {bounds}")
    headers["X-Map-Revision"] = str(region.meta.revision)
    data = await run_in_threadpool(export_region, region, fmt, robot)  # CPU: off the event loop
    return Response(data, media_type=MEDIA[fmt], headers=headers)


def export_region(region: MapRegionMessage, fmt: str, name: str) -> bytes:
    """The region written by the library's PNG or map_server exporter from the percentages the
    map server sent, which its whole-map export draws from too: each cell comes out alike
    (map_server's files named `name`, as the whole map's are)."""
    return map_file_bytes(RosGrid(region.occupancy, region.window_spec), fmt, name)
