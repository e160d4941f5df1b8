"""The router: its Zenoh settings from SCANFLOW_ROUTER_*, and a real one relaying, reporting
health and stats, joining another router and stopping cleanly on SIGTERM."""

from __future__ import annotations

import pytest
import zenoh
from hypothesis import given, settings
from hypothesis import strategies as st
from scanflow.config import RouterSettings, ZenohSettings

from services.common.launch import free_port, wait_for_port
from services.common.zsession import open_session
from services.router.service import router_zenoh_settings

endpoints = st.lists(
    st.builds("tcp/127.0.0.1:{}".format, st.integers(1, 65535)), max_size=3, unique=True
)


@settings(max_examples=30, deadline=None)
@given(
    listen=endpoints.filter(bool), connect=endpoints, prefix=st.sampled_from(["scanflow", "b"]),
    block_close_s=st.floats(0.5, 120.0), scouting=st.booleans(),
)
def test_a_router_listens_and_joins_where_its_settings_say(
    listen, connect, prefix, block_close_s, scouting
) -> None:
    """Endpoints from SCANFLOW_ROUTER_*, the rest of SCANFLOW_ZENOH_* as given (the router is
    the one that waits on a cut-off reader: it must wait as long as the services do)."""
    zenoh = ZenohSettings(prefix=prefix, block_close_s=block_close_s,
                          multicast_scouting=scouting)
    zenoh_settings = router_zenoh_settings(RouterSettings(listen=listen, connect=connect), zenoh)
    assert zenoh_settings.mode == "router"
    assert (zenoh_settings.listen, zenoh_settings.connect) == (listen, connect)
    assert zenoh_settings.prefix == prefix and zenoh_settings.block_close_s == block_close_s
    assert zenoh_settings.multicast_scouting == scouting


def test_the_services_zenoh_variables_do_not_make_the_router_a_client(monkeypatch) -> None:
    """`scanflow up` gives every process, the router too, SCANFLOW_ZENOH_MODE=client and
    SCANFLOW_ZENOH_CONNECT=<the router>: the router must not become a client of itself."""
    monkeypatch.setenv("SCANFLOW_ZENOH_MODE", "client")
    monkeypatch.setenv("SCANFLOW_ZENOH_CONNECT", "tcp/127.0.0.1:7447")
    monkeypatch.setenv("SCANFLOW_ROUTER_LISTEN", "tcp/127.0.0.1:7447")
    monkeypatch.delenv("SCANFLOW_ROUTER_CONNECT", raising=False)
    monkeypatch.setenv("SCANFLOW_ZENOH_BLOCK_CLOSE_S", "15")
    zenoh_settings = router_zenoh_settings(RouterSettings(), ZenohSettings())
    assert zenoh_settings.mode == "router" and zenoh_settings.block_close_s == 15.0
    assert zenoh_settings.listen == ["tcp/127.0.0.1:7447"] and zenoh_settings.connect == []


@pytest.mark.integration
def test_a_router_relays_reports_its_health_and_stops_cleanly(launcher, bus) -> None:
    """The `launcher` fixture started `python -m services.router` on a free port."""
    assert bus.wait_until(lambda: "router/0" in bus.alive(), 10.0, "the router's health token")
    stats = bus.stats("router")
    assert stats is not None and (stats.service, stats.instance) == ("router", "0")
    _heard_through(bus, launcher.zenoh_port, "scanflow/test/relay", 10.0)
    assert launcher.stop("router") == 0
    assert "router listening on" in launcher.log_text("router")


@pytest.mark.integration
def test_a_router_joins_the_routers_it_is_told_to_connect_to(launcher, bus) -> None:
    """A client of a second router, started with SCANFLOW_ROUTER_CONNECT=<the first>, hears
    what a client of the first one puts."""
    port = free_port()
    launcher.start(
        "router", "router2", SCANFLOW_ROUTER_LISTEN=f"tcp/127.0.0.1:{port}",
        SCANFLOW_ROUTER_CONNECT=f"tcp/127.0.0.1:{launcher.zenoh_port}",
        SCANFLOW_ROUTER_INSTANCE="1",
    )
    wait_for_port(port)
    _heard_through(bus, port, "scanflow/test/joined", 15.0)
    assert bus.wait_until(lambda: "router/1" in bus.alive(), 10.0, "router 1 seen from 0")
    assert launcher.stop("router2") == 0


def _heard_through(bus, port: int, key: str, timeout_s: float) -> None:
    """A client of the router on `port` hears a put that `bus` makes on `key`. Routes take a
    moment to form, so `bus` puts again on every poll until one arrives."""
    listener = open_session(ZenohSettings(connect=[f"tcp/127.0.0.1:{port}"]))
    try:
        got: list[bytes] = []
        sub = listener.declare_subscriber(key, lambda s: got.append(s.payload.to_bytes()))

        def relayed() -> bool:
            bus.session.put(key, b"hello", congestion_control=zenoh.CongestionControl.BLOCK)
            return b"hello" in got

        bus.wait_until(relayed, timeout_s, f"a put on {key} heard through port {port}")
        sub.undeclare()
    finally:
        listener.close()
