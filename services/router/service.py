"""Router: a Zenoh session in router mode listening on the configured endpoints."""

from __future__ import annotations

from scanflow.config import RouterSettings, ZenohSettings

from services.common.process import init_process, require_settings
from services.common.shell import ServiceShell


def router_zenoh_settings(settings: RouterSettings, zenoh: ZenohSettings) -> ZenohSettings:
    """The Zenoh settings of a router: `zenoh` (SCANFLOW_ZENOH_*: prefix, how long a blocked
    link waits, scouting) in router mode, listening (and joining other routers) as `settings`
    say. The mode and endpoints `scanflow up` gives every process are the clients', not its."""
    return zenoh.model_copy(
        update={"mode": "router", "listen": settings.listen, "connect": settings.connect}
    )


def main() -> None:
    """Run the router until SIGTERM/Ctrl-C."""
    require_settings("router", RouterSettings, ZenohSettings)
    settings = RouterSettings()
    init_process(settings)
    zenoh_settings = router_zenoh_settings(settings, ZenohSettings())
    with ServiceShell("router", settings, zenoh_settings) as shell:
        shell.start()
        shell.log.info("router listening on %s", ", ".join(settings.listen))
        shell.run(lambda _kind, _message: None)
        shell.close(flush_s=0.0)
