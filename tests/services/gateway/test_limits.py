"""limits.py: the request body cap (413 before parsing) and the per-route latency timing."""

from __future__ import annotations

import asyncio

from fastapi import FastAPI, Request
from fastapi.testclient import TestClient

from services.gateway.limits import BodyLimit, RequestTiming
from services.gateway.metrics import Metrics

CAP = 100


def echo_app() -> FastAPI:
    """An app answering POST /echo with the size of the body it read (the middleware are added
    as create_app adds them: inside Starlette's error middleware)."""
    app = FastAPI()

    @app.post("/echo")
    async def echo(request: Request) -> dict[str, int]:
        return {"read": len(await request.body())}

    return app


def capped() -> TestClient:
    app = echo_app()
    app.add_middleware(BodyLimit, max_body_bytes=CAP)
    return TestClient(app)


def test_a_body_at_the_cap_passes():
    r = capped().post("/echo", content=b"x" * CAP)
    assert r.status_code == 200 and r.json() == {"read": CAP}


def test_a_declared_length_over_the_cap_is_413_naming_the_limit():
    r = capped().post("/echo", content=b"x" * (CAP + 1))
    assert r.status_code == 413 and r.headers["content-type"] == "application/json"
    assert r.json()["detail"] == f"body: {CAP + 1} bytes or more, over max_body_bytes={CAP}"


def test_a_streamed_body_over_the_cap_is_413_naming_the_limit():
    chunks = (b"x" * 60 for _ in range(3))  # no Content-Length: counted as it comes
    r = capped().post("/echo", content=chunks)
    assert r.status_code == 413 and f"max_body_bytes={CAP}" in r.json()["detail"]


def test_a_content_length_that_is_no_number_is_400():
    r = capped().post("/echo", content=b"{}", headers={"Content-Length": "2x"})
    assert r.status_code == 400 and "'2x' is invalid" in r.json()["detail"]


def test_other_scopes_pass_through_untouched():
    seen: list[str] = []

    async def app(scope, receive, send) -> None:
        seen.append(scope["type"])

    asyncio.run(BodyLimit(app, max_body_bytes=CAP)({"type": "lifespan"}, None, None))
    asyncio.run(RequestTiming(app, Metrics())({"type": "websocket"}, None, None))
    assert seen == ["lifespan", "websocket"]


def test_every_request_is_timed_by_route_template_method_and_status():
    metrics = Metrics()
    app = echo_app()

    @app.get("/items/{item}")
    def item(item: int) -> dict[str, int]:
        return {"item": item}

    app.add_middleware(RequestTiming, metrics=metrics)
    with TestClient(app) as client:
        client.get("/items/1")
        client.get("/items/2")
        client.get("/items/no")
        client.get("/nowhere")
    text = metrics.render()
    name = "scanflow_http_request_duration_seconds_count"
    assert f'{name}{{method="GET",route="/items/{{item}}",status="200"}} 2' in text
    assert f'{name}{{method="GET",route="/items/{{item}}",status="422"}} 1' in text
    assert f'{name}{{method="GET",route="unmatched",status="404"}} 1' in text


def test_a_request_that_raises_is_timed_as_a_500():
    metrics = Metrics()
    app = echo_app()

    @app.get("/boom")
    def boom() -> None:
        raise RuntimeError("boom")

    app.add_middleware(RequestTiming, metrics=metrics)
    with TestClient(app, raise_server_exceptions=False) as client:
        assert client.get("/boom").status_code == 500
    assert 'route="/boom",status="500"} 1' in metrics.render()


def test_body_over_the_limit_is_413_before_parsing(client, auth):
    r = client.post("/api/v1/match", content=b"{" + b" " * 70_000 + b"}", headers=auth)
    assert r.status_code == 413 and "max_body_bytes" in r.json()["detail"]


def test_streamed_body_over_the_limit_is_413(client, auth):
    chunks = (b" " * 16_384 for _ in range(8))  # no Content-Length: chunked upload
    r = client.post("/api/v1/match", content=chunks, headers=auth)
    assert r.status_code == 413


def test_a_clients_made_up_methods_do_not_grow_the_label_sets():
    """uvicorn (h11) passes any token as the method: one label set per made-up method would
    grow /metrics, and the gateway's memory, without bound."""
    metrics = Metrics()
    app = echo_app()
    app.add_middleware(RequestTiming, metrics=metrics)
    with TestClient(app) as client:
        for i in range(50):
            client.request(f"X{i}", "/echo")
            client.request(f"Y{i}", "/nowhere")
        client.request("DELETE", "/echo")
    text = metrics.render()
    name = "scanflow_http_request_duration_seconds_count"
    assert f'{name}{{method="other",route="/echo",status="405"}} 50' in text
    assert f'{name}{{method="other",route="unmatched",status="404"}} 50' in text
    assert f'{name}{{method="DELETE",route="/echo",status="405"}} 1' in text
    assert text.count(f"{name}{{") == 3
