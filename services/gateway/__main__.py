"""`python -m services.gateway`: serve the gateway with uvicorn (SCANFLOW_GATEWAY_*, _ZENOH_*)."""

from __future__ import annotations

import uvicorn
from scanflow.config import GatewaySettings, ZenohSettings

from services.common.process import init_process, require_settings
from services.gateway.app import create_app


def main() -> None:
    """Check the settings, set up logging and CPUs, then serve the app with uvicorn."""
    require_settings("gateway", GatewaySettings, ZenohSettings)
    settings = GatewaySettings()
    init_process(settings)
    uvicorn.run(
        create_app(settings),
        host=settings.host,
        port=settings.port,
        log_level=settings.log_level.lower(),
        timeout_graceful_shutdown=2,
    )


if __name__ == "__main__":
    main()
