"""One router per resource; `ROUTERS` in mounting order (paths carry their prefix)."""

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

ROUTERS = (
    robots.router, poses.router, match.router, maps.router, health.router, ingest.router,
    stream.router, metrics.router,
)
