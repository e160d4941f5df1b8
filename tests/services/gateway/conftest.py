"""Gateway fixtures: a real Zenoh peer on loopback (the test's side of the bus) and the app.

No mocks: the gateway's backend opens its own peer session connected to the test's peer; the
test publishes messages and declares tiny queryables that answer with wire messages.
"""

from __future__ import annotations

import asyncio
import importlib
import math
import time
from collections.abc import Callable, Iterator

import numpy as np
import pytest
import zenoh
from fastapi.testclient import TestClient
from scanflow import keys
from scanflow.config import GatewaySettings, ZenohSettings
from scanflow.geometry import Pose2D
from scanflow.wire import PoseEstimateMessage, RetiredMessage, RetireMessage

from services.common.launch import free_port
from services.common.zsession import open_session
from services.gateway.app import create_app
from services.gateway.backend import ZenohBackend

API_KEY = "test-key"
# A small valid scan for POST /robots/{robot}/scans (ingest and its numbering).
INGEST_SCAN = {"ranges_m": [1.0, 2.0], "angle_min_rad": 0.0, "angle_increment_rad": 0.1}


class Peer:
    """The test's Zenoh session: publish, answer queries, hold liveliness tokens."""

    def __init__(self, port: int) -> None:
        self.session = open_session(
            ZenohSettings(mode="peer", connect=[], listen=[f"tcp/127.0.0.1:{port}"])
        )
        self._declared: list = []
        self._subscribed: set[str] = set()
        self.gateway_session: zenoh.Session | None = None  # set by the `backend` fixture

    def put(self, key: str, payload: bytes) -> None:
        """Put on `key`, the first time only once a subscriber of it (the gateway's) is known
        here: a put that meets none is dropped, and the gateway's subscriptions reach this
        session after the sessions connect (under load, after a test's first puts)."""
        if key not in self._subscribed:
            publisher = self.session.declare_publisher(
                key, allowed_destination=zenoh.Locality.REMOTE  # not this session's own
            )
            eventually(lambda: publisher.matching_status.matching, f"a subscriber of {key}")
            publisher.undeclare()
            self._subscribed.add(key)
        self.session.put(key, payload, congestion_control=zenoh.CongestionControl.BLOCK)

    def answer(self, key: str, reply: Callable[[zenoh.Query], bytes | None]) -> None:
        """A queryable on `key`: reply(query) bytes are the answer (None: stay silent)."""
        held: list[zenoh.Query] = []

        def on_query(query: zenoh.Query) -> None:
            try:
                payload = reply(query)
            except Exception as exc:  # forwarded like ServiceShell does
                query.reply_err(f"{type(exc).__name__}: {exc}")
                return
            if payload is None:
                held.append(query)  # never answered: the gateway must time out
            else:
                query.reply(query.key_expr, payload)

        self._declared.append(self.session.declare_queryable(key, on_query))
        self._wait_gateway_sees(key, "querier")

    def token(self, key: str) -> None:
        self._declared.append(self.session.liveliness().declare_token(key))

    def subscribe(self, key: str) -> list[bytes]:
        got: list[bytes] = []
        self._declared.append(
            self.session.declare_subscriber(key, lambda s: got.append(s.payload.to_bytes()))
        )
        self._wait_gateway_sees(key, "publisher")
        return got

    def _wait_gateway_sees(self, key: str, probe: str) -> None:
        """Block until a `probe` ('querier' for a queryable, 'publisher' for a subscriber)
        declared on the gateway's session matches `key` remotely: Zenoh drops a put or query
        that meets no known match, so a test must not race its declaration to the gateway.
        Remote only: the gateway's own subscribers (raw scans, odometry: remote samples only)
        would match a probe at once, and the first post then raced this session's subscriber
        to the gateway (1 in ~30 runs under load lost it)."""
        if self.gateway_session is None:
            return
        entity = getattr(self.gateway_session, f"declare_{probe}")(
            key, allowed_destination=zenoh.Locality.REMOTE
        )
        eventually(lambda: entity.matching_status.matching, f"the gateway to see {key}")
        entity.undeclare()

    def close(self) -> None:
        for entity in self._declared:
            entity.undeclare()
        self.session.close()


def eventually(check: Callable[[], object], what: str, timeout_s: float = 5.0) -> object:
    """Poll `check` until truthy; fail naming `what`."""
    deadline = time.monotonic() + timeout_s
    while not (value := check()):
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out waiting for {what}")
        time.sleep(0.02)
    return value


def off_the_loop(monkeypatch: pytest.MonkeyPatch, target: str) -> list[bool]:
    """Wrap the function at `target` ("module.name") so each call records whether it ran with
    no event loop in its thread: CPU work on the loop holds up every other request."""
    module, name = target.rsplit(".", 1)
    work = getattr(importlib.import_module(module), name)
    calls: list[bool] = []

    def recorded(*args: object, **kwargs: object) -> object:
        try:
            asyncio.get_running_loop()
            calls.append(False)
        except RuntimeError:  # no loop here: a worker thread
            calls.append(True)
        return work(*args, **kwargs)

    monkeypatch.setattr(target, recorded)
    return calls


def estimate(robot: str, seq: int, stamp_s: float, x: float, y: float, theta: float = 0.0,
             status: str = "ok") -> PoseEstimateMessage:
    cov = np.diag([1e-4, 1e-4, 1e-5]) if status == "ok" else np.diag([math.inf] * 3)
    return PoseEstimateMessage(robot, seq, stamp_s, Pose2D(x, y, theta), cov, status, "gn", 5, 0.9)


def serve_retire(
    peer: Peer, backend: ZenohBackend, services: dict[str, list[str]], asked: list | None = None,
    dropped: dict[str, int] | None = None, silent: str | None = None,
) -> None:
    """Liveliness tokens and retire queryables of the services' instances (`services`: name ->
    instances): each answers RetiredMessage naming itself (`silent`, "name/instance": never
    answers); `asked` records (service/instance, the request)."""
    for service, instances in services.items():
        for instance in instances:
            peer.token(keys.health(service, instance))
            name = f"{service}/{instance}"

            def answer(query, service=service, instance=instance, name=name):
                request = RetireMessage.decode(query.payload.to_bytes())
                if asked is not None:
                    asked.append((name, request))
                if name == silent:
                    return None
                return RetiredMessage(request.robot_id, service, instance, True,
                                      dropped or {}).encode()

            peer.answer(keys.retire("*", service), answer)
    total = sum(len(i) for i in services.values())
    eventually(lambda: len(backend.alive_services()) >= total, "the services' tokens")


@pytest.fixture
def zenoh_port() -> int:
    return free_port()


@pytest.fixture
def peer(zenoh_port: int) -> Iterator[Peer]:
    p = Peer(zenoh_port)
    yield p
    p.close()


@pytest.fixture
def settings() -> GatewaySettings:
    return GatewaySettings(api_key=API_KEY, query_timeout_s=1.0, max_beams=1024,
                           max_body_bytes=64 * 1024, trajectory_cache_len=100)


@pytest.fixture
def backend(peer: Peer, zenoh_port: int, settings: GatewaySettings) -> Iterator[ZenohBackend]:
    z = ZenohSettings(mode="peer", connect=[f"tcp/127.0.0.1:{zenoh_port}"])
    b = ZenohBackend.open(settings, z)
    eventually(lambda: b.session_info()["peers"], "the gateway to join the test peer")
    peer.gateway_session = b.session
    yield b
    b.close()


@pytest.fixture
def client(backend: ZenohBackend, settings: GatewaySettings) -> Iterator[TestClient]:
    with TestClient(create_app(settings, backend)) as c:
        yield c


@pytest.fixture
def auth() -> dict[str, str]:
    return {"X-API-Key": API_KEY}


@pytest.fixture
def publish_poses(peer: Peer, backend: ZenohBackend) -> Callable[..., None]:
    """publish_poses(robot, [(stamp_s, x, y, theta), ...]): put them, wait until cached."""

    def publish(robot: str, poses: list[tuple[float, float, float, float]], seq0: int = 0) -> None:
        for i, (t, x, y, th) in enumerate(poses):
            peer.put(keys.pose(robot), estimate(robot, seq0 + i, t, x, y, th).encode())
        last = seq0 + len(poses) - 1
        eventually(
            lambda: (e := backend.tracks.latest(robot)) is not None and e.seq == last,
            f"pose seq {last} of {robot} to reach the gateway",
        )

    return publish
