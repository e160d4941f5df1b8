"""create_app: routers, guard_reads, error handlers, the OpenAPI schema and the web page."""

from __future__ import annotations

import logging

from fastapi.testclient import TestClient
from scanflow import keys
from scanflow.config import GatewaySettings, ZenohSettings

from services.gateway.app import STATIC_DIR, create_app

from .conftest import eventually


def test_reads_are_open_without_guard_reads(client):
    assert client.get("/api/v1/robots").status_code == 200
    assert client.get("/metrics").status_code == 200
    operation = client.get("/openapi.json").json()["paths"]["/api/v1/robots"]["get"]
    assert "security" not in operation


def test_a_bad_body_is_a_422_naming_the_field_without_echoing_the_input(client, auth):
    body = {"stamp_s": "secret-looking-input", "pose": {}}
    r = client.post("/api/v1/robots/r1/odometry", json=body, headers=auth)
    assert r.status_code == 422
    (error,) = r.json()["detail"]
    assert set(error) == {"loc", "msg", "type"} and error["loc"] == ["body", "stamp_s"]
    assert "secret-looking-input" not in r.text


def test_a_backend_error_is_answered_with_its_status_and_reason(client):
    r = client.get("/api/v1/robots/r1/map")  # no map server on the bus
    assert r.status_code == 503 and "no service answers" in r.json()["detail"]


def test_the_schema_lists_the_body_models_routes_read_by_hand(client):
    schemas = client.get("/openapi.json").json()["components"]["schemas"]
    for name in ("MatchIn", "ScanIn", "OdometryIn", "PoseIn", "VelocityIn"):
        assert name in schemas, name
    assert "$defs" not in schemas["MatchIn"]
    assert client.app.openapi() is client.app.openapi()  # built once


def test_the_web_page_and_its_files_are_served(client):
    page = client.get("/")
    assert page.status_code == 200 and page.headers["content-type"].startswith("text/html")
    assert page.content == (STATIC_DIR / "index.html").read_bytes()
    assert client.get("/static/app.js").status_code == 200


def test_the_body_cap_of_the_settings_applies(backend, auth):
    tight = GatewaySettings(api_key="test-key", max_body_bytes=1024)
    with TestClient(create_app(tight, backend)) as c:
        r = c.post("/api/v1/robots/r1/odometry", content=b"{" + b" " * 1024 + b"}", headers=auth)
    assert r.status_code == 413 and "max_body_bytes=1024" in r.json()["detail"]


def test_without_a_backend_the_app_opens_and_closes_its_own_session(peer, zenoh_port):
    z = ZenohSettings(mode="peer", connect=[f"tcp/127.0.0.1:{zenoh_port}"])
    app = create_app(GatewaySettings(api_key="k"), zenoh_settings=z)
    with TestClient(app) as c:
        eventually(lambda: c.get("/api/v1/health").json()["zenoh"]["peers"], "the test peer")
        backend = app.state.backend
    assert backend.session_info()["open"] is False


def test_an_unset_api_key_is_warned_about(backend, caplog):
    caplog.set_level(logging.WARNING, logger="scanflow.gateway")
    with TestClient(create_app(GatewaySettings(api_key=None), backend)):
        pass
    assert any("SCANFLOW_GATEWAY_API_KEY is not set" in r.getMessage() for r in caplog.records)


def test_guard_reads_puts_the_key_on_every_endpoint_but_health(backend, settings, auth):
    from fastapi.testclient import TestClient

    from services.gateway.app import create_app

    guarded = settings.model_copy(update={"guard_reads": True})
    with TestClient(create_app(guarded, backend)) as c:
        assert c.get("/api/v1/robots").status_code == 401
        assert c.get("/metrics").status_code == 401
        assert c.get("/api/v1/health").status_code in (200, 503)  # probes send no key
        assert c.get("/api/v1/robots", headers=auth).status_code == 200
        operation = c.get("/openapi.json").json()["paths"]["/api/v1/robots"]["get"]
        assert operation["security"] == [{"APIKeyHeader": []}]


def test_an_unreadable_answer_from_a_service_is_a_502_naming_it(peer, backend, settings):
    """A service that answers with bytes the gateway cannot decode (another schema version
    in a rolling upgrade, a broken service) is a bad gateway, named, not a bare 500."""
    peer.answer(keys.map_key("r1", "meta"), lambda q: b"\x00not msgpack")
    with TestClient(create_app(settings, backend), raise_server_exceptions=False) as c:
        r = c.get("/api/v1/robots/r1/map")
    assert r.status_code == 502
    assert "unreadable" in r.json()["detail"] and "msgpack" in r.json()["detail"]


def test_the_statuses_of_the_routes_that_ask_a_service_are_in_the_schema(client, publish_poses):
    """A pose at a time before the gateway's cache asks the map server: 503 with none, 504
    when it is slow; any service's unreadable answer is a 502. The schema listed neither."""
    publish_poses("r1", [(10.0, 0.0, 0.0, 0.0)])
    r = client.get("/api/v1/robots/r1/pose", params={"t": 1.0})  # no map server
    assert r.status_code == 503
    paths = client.get("/openapi.json").json()["paths"]
    pose = paths["/api/v1/robots/{robot}/pose"]
    assert {"502", "503", "504"} <= set(pose["get"]["responses"])
    for path, method in [
        ("/api/v1/robots/{robot}/pose", "put"), ("/api/v1/robots/{robot}/trajectory", "get"),
        ("/api/v1/match", "post"), ("/api/v1/robots/{robot}/map", "get"),
        ("/api/v1/robots/{robot}/map.{fmt}", "get"),
    ]:
        assert "502" in paths[path][method]["responses"], (method, path)


def test_guarded_reads_list_the_keys_answers_in_the_schema(backend, settings):
    """With guard_reads every read answers 401 without the key and 403 with a wrong one; the
    schema listed neither (only the security scheme)."""
    guarded = settings.model_copy(update={"guard_reads": True})
    with TestClient(create_app(guarded, backend)) as c:
        assert c.get("/api/v1/robots", headers={"X-API-Key": "wrong"}).status_code == 403
        paths = c.get("/openapi.json").json()["paths"]
    for path in ("/api/v1/robots", "/api/v1/robots/{robot}/pose", "/metrics"):
        assert {"401", "403"} <= set(paths[path]["get"]["responses"]), path
    assert "401" not in paths["/api/v1/health"]["get"]["responses"]
    open_paths = create_app(settings, backend).openapi()["paths"]
    assert "401" not in open_paths["/api/v1/robots"]["get"]["responses"]
