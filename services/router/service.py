"""Router: a Zenoh session in router mode listening on the configured endpoints."""

from __future__ import annotations

from scanflow.config import RouterSettings, ZenohSettings

from services.common.process import init_process, require_settings
from services.common.shell import ServiceShell


def router_zenoh_settings(settings: RouterSettings, prefix: str) -> ZenohSettings:
    """The Zenoh settings of a router: listen (and optionally join other routers)."""
    return ZenohSettings(
        mode="router", listen=settings.listen, connect=settings.connect, prefix=prefix
    )


def main() -> None:
    """Run the router until SIGTERM/Ctrl-C."""
    require_settings("router", RouterSettings, ZenohSettings)
    settings = RouterSettings()
    init_process(settings)
    zenoh_settings = router_zenoh_settings(settings, ZenohSettings().prefix)
    with ServiceShell("router", settings, zenoh_settings) as shell:
        shell.start()
        shell.log.info("router listening on %s", ", ".join(settings.listen))
        shell.run(lambda _kind, _message: None)
        shell.close(flush_s=0.0)
