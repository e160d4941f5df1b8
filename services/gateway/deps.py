"""Shared request dependencies: settings, the Zenoh backend, API-key guards, robot ids."""

from __future__ import annotations

import secrets
from typing import Annotated

from fastapi import Depends, HTTPException, Path, Request, Security
from fastapi.exceptions import RequestValidationError
from fastapi.security import APIKeyHeader
from scanflow import keys
from scanflow.config import GatewaySettings

from services.gateway.backend import ZenohBackend

API_PREFIX = "/api/v1"
# The answer of every route whose answer comes from a service (app._unreadable_reply, and an
# error reply the gateway has no status for: backend.error_status).
BAD_GATEWAY: dict[int | str, dict[str, str]] = {
    502: {"description": "a service's answer is unreadable, or it failed unexpectedly"}
}
# The answers of a route behind the API key (require_key).
KEY_ANSWERS: dict[int | str, dict[str, str]] = {
    401: {"description": "API key missing"},
    403: {"description": "API key wrong"},
}
api_key_header = APIKeyHeader(
    name="X-API-Key", auto_error=False, description="SCANFLOW_GATEWAY_API_KEY"
)


def get_settings(request: Request) -> GatewaySettings:
    """The app's GatewaySettings (app.state.settings), as a dependency."""
    return request.app.state.settings


def get_backend(request: Request) -> ZenohBackend:
    """The app's ZenohBackend (app.state.backend), as a dependency."""
    return request.app.state.backend


def require_key(
    settings: Annotated[GatewaySettings, Depends(get_settings)],
    given: Annotated[str | None, Security(api_key_header)],
) -> None:
    """Writes and compute (ingest, match) need the API key when one is configured; reads
    too with SCANFLOW_GATEWAY_GUARD_READS=true (create_app adds it to every router then)."""
    expected = settings.api_key
    if expected is None:
        return
    if given is None:
        raise HTTPException(401, "missing X-API-Key header", {"WWW-Authenticate": "X-API-Key"})
    if not secrets.compare_digest(given.encode(), expected.get_secret_value().encode()):
        raise HTTPException(403, "X-API-Key is not valid")


def robot_id(
    robot: Annotated[
        str, Path(pattern=r"^[A-Za-z0-9_\-.]{1,64}$", description="robot id", examples=["robot"])
    ],
) -> str:
    """The {robot} path parameter, checked like every key chunk (reserved ids refused): a 422
    shaped as the schema's HTTPValidationError, like an id outside the pattern."""
    try:
        return keys.check_robot_id(robot)
    except keys.KeyExprError as exc:
        raise RequestValidationError(
            [{"loc": ("path", "robot"), "msg": str(exc), "type": "value_error"}]
        ) from exc


Backend = Annotated[ZenohBackend, Depends(get_backend)]
Settings = Annotated[GatewaySettings, Depends(get_settings)]
Robot = Annotated[str, Depends(robot_id)]
