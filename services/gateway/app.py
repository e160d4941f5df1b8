"""The FastAPI application: routers under /api/v1, /metrics, the web page at /, safety layers."""

from __future__ import annotations

import logging
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from pathlib import Path
from typing import Any

import anyio.to_thread
from fastapi import Depends, FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.openapi.utils import get_openapi
from fastapi.responses import FileResponse, JSONResponse
from fastapi.staticfiles import StaticFiles
from pydantic import BaseModel
from scanflow.config import GatewaySettings, ZenohSettings
from scanflow.wire import DecodeError

from services.gateway.backend import BackendError, ZenohBackend
from services.gateway.deps import KEY_ANSWERS, require_key
from services.gateway.limits import BodyLimit, RequestTiming
from services.gateway.metrics import Metrics
from services.gateway.models import MatchIn, OdometryIn, ScanIn
from services.gateway.routers import ROUTERS, health

STATIC_DIR = Path(__file__).parent / "static"
BODY_MODELS: tuple[type[BaseModel], ...] = (MatchIn, ScanIn, OdometryIn)
log = logging.getLogger("scanflow.gateway")


class GatewayApp(FastAPI):
    """The gateway's FastAPI: its schema also lists the body models routes read by hand."""

    def openapi(self) -> dict[str, Any]:
        """The generated schema plus the body models routes read by hand (JSON or msgpack),
        built once."""
        if self.openapi_schema is None:
            schema = get_openapi(
                title=self.title, version=self.version, summary=self.summary, routes=self.routes
            )
            components = schema.setdefault("components", {}).setdefault("schemas", {})
            for model in BODY_MODELS:
                body = model.model_json_schema(ref_template="#/components/schemas/{model}")
                components.update(body.pop("$defs", {}))
                components[model.__name__] = body
            self.openapi_schema = schema
        return self.openapi_schema


def create_app(
    settings: GatewaySettings | None = None,
    backend: ZenohBackend | None = None,
    zenoh_settings: ZenohSettings | None = None,
) -> FastAPI:
    """The gateway app; without `backend` it opens (and closes) its own Zenoh session."""
    settings = settings or GatewaySettings()

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        if backend is None:
            z = zenoh_settings or ZenohSettings()
            app.state.backend = await anyio.to_thread.run_sync(ZenohBackend.open, settings, z)
        if settings.api_key is None:
            log.warning("SCANFLOW_GATEWAY_API_KEY is not set: ingest, match, setting a pose "
                        "and retiring a robot are open")
        try:
            yield
        finally:
            if backend is None:
                app.state.backend.close()

    app = GatewayApp(
        title="scanflow gateway",
        version="1",
        summary="HTTP access to the scanflow 2D LiDAR pipeline (poses, match, maps, ingest).",
        lifespan=lifespan,
    )
    app.state.settings = settings
    app.state.backend = backend
    app.state.metrics = Metrics()
    reads = [Depends(require_key)] if settings.guard_reads else []  # documented only if on
    for router in ROUTERS:
        # Health stays open: container health checks and load balancers' probes send no key.
        guarded = reads if router is not health.router else []
        app.include_router(
            router, dependencies=guarded, responses=KEY_ANSWERS if guarded else None
        )
    # FastAPI's decorator, called: Starlette's add_exception_handler types a handler as taking
    # any Exception, so one that takes its own kind does not fit it.
    app.exception_handler(BackendError)(_backend_error)
    app.exception_handler(RequestValidationError)(_invalid)
    app.exception_handler(DecodeError)(_unreadable_reply)
    app.add_middleware(BodyLimit, max_body_bytes=settings.max_body_bytes)
    app.add_middleware(RequestTiming, metrics=app.state.metrics)
    app.mount("/static", StaticFiles(directory=STATIC_DIR), name="static")

    @app.get("/", include_in_schema=False)
    def index() -> FileResponse:
        return FileResponse(STATIC_DIR / "index.html")

    return app


async def _backend_error(_request: Request, exc: BackendError) -> JSONResponse:
    return JSONResponse({"detail": exc.reason}, status_code=exc.status_code)


async def _unreadable_reply(request: Request, exc: DecodeError) -> JSONResponse:
    """502 for a service's answer the gateway cannot decode (bodies' DecodeErrors are 422s
    before this: read_body)."""
    log.warning("unreadable answer from the bus for %s: %s", request.url.path, exc)
    return JSONResponse(
        {"detail": f"a service's answer is unreadable: {exc}"}, status_code=502
    )


async def _invalid(_request: Request, exc: RequestValidationError) -> JSONResponse:
    """422 naming each bad field; inputs are not echoed (they may be huge or not JSON, e.g. NaN)."""
    detail = [
        {"loc": list(e.get("loc", ())), "msg": str(e.get("msg", "")), "type": e.get("type", "")}
        for e in exc.errors()
    ]
    return JSONResponse({"detail": detail}, status_code=422)
