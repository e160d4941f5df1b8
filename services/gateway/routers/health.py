"""GET /health: the gateway's Zenoh session and each service's liveliness token."""

from __future__ import annotations

from fastapi import APIRouter
from fastapi.responses import JSONResponse

from services.gateway.backend import EXPECTED_SERVICES
from services.gateway.deps import API_PREFIX, Backend
from services.gateway.models import HealthOut, ServiceOut, ZenohOut

router = APIRouter(prefix=API_PREFIX, tags=["health"])


@router.get(
    "/health", response_model=HealthOut,
    responses={503: {"model": HealthOut, "description": "the gateway's Zenoh session is down"}},
    summary="Liveliness of every service and of the gateway's own Zenoh session",
)
def health(backend: Backend) -> JSONResponse:
    """Liveliness of the gateway's Zenoh session and of each service's token: "ok", "degraded"
    (a service missing) or "down" (the session closed or cut off from its router: 503)."""
    zenoh = ZenohOut(**backend.session_info())
    alive = backend.alive_services()
    missing = sorted(set(EXPECTED_SERVICES) - {service for service, _ in alive})
    cut_off = zenoh.mode == "client" and not zenoh.routers
    status = "down" if not zenoh.open or cut_off else ("degraded" if missing else "ok")
    body = HealthOut(
        status=status,
        zenoh=zenoh,
        services=[ServiceOut(service=s, instance=i) for s, i in alive],
        missing=missing,
        stream_clients=backend.events.clients,
    )
    return JSONResponse(body.model_dump(), status_code=503 if status == "down" else 200)
