"""One router per resource; `ROUTERS` is the order they are mounted in."""

from services.gateway.routers import (
    health,
    ingest,
    maps,
    match,
    metrics,
    poses,
    robots,
    stream,
)

API_ROUTERS = (robots.router, poses.router, match.router, maps.router, health.router,
               ingest.router, stream.router)
ROOT_ROUTERS = (metrics.router,)
