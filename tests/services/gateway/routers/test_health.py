"""GET /health: the gateway's Zenoh session and each service's liveliness token."""

from __future__ import annotations

from scanflow import keys

from ..conftest import eventually


def test_health_lists_liveliness_tokens(client, peer):
    body = client.get("/api/v1/health").json()
    assert body["status"] == "degraded" and "matcher" in body["missing"]
    assert body["zenoh"]["open"] and body["zenoh"]["peers"]
    for service in ("router", "deskew", "matcher", "mapserver"):
        peer.token(keys.health(service, "0"))
    eventually(lambda: client.get("/api/v1/health").json()["status"] == "ok", "all services up")


def test_a_closed_session_is_down_with_503(client, backend):
    backend.close()
    r = client.get("/api/v1/health")
    assert r.status_code == 503
    body = r.json()
    assert body["status"] == "down" and body["zenoh"]["open"] is False
    assert body["missing"] == ["deskew", "mapserver", "matcher", "router"]
