"""Fixtures for service tests: a real router on a free loopback port and a bus client."""

from __future__ import annotations

import os
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest
import zenoh
from scanflow import keys
from scanflow.config import ZenohSettings
from scanflow.maps.export import load_npz
from scanflow.maps.occupancy import OccupancyGrid
from scanflow.wire import ServiceStatsMessage, decode_any

from services.common.launch import Launcher, free_port
from services.common.zsession import open_session

_DEFAULT_DATA = Path(__file__).resolve().parents[2] / ".." / "shared" / "data"
DATA_DIR = Path(os.environ.get("SCANFLOW_DATA_DIR", _DEFAULT_DATA))


@pytest.fixture
def data_file() -> Callable[[str], Path]:
    """Path of a real log by name; skips the test when the data is not there."""

    def find(name: str) -> Path:
        path = DATA_DIR / name
        if not path.exists():
            pytest.skip(f"real log {path} is not available (set SCANFLOW_DATA_DIR)")
        return path

    return find


def wait_until(predicate: Callable[[], object], timeout_s: float, what: str) -> object:
    """Poll `predicate` until it returns something truthy; fail naming `what` on timeout."""
    deadline = time.monotonic() + timeout_s
    while True:
        value = predicate()
        if value:
            return value
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out after {timeout_s} s waiting for {what}")
        time.sleep(0.1)


class Bus:
    """A test's own Zenoh client: record topics, query stats, put raw bytes."""

    def __init__(self, port: int) -> None:
        self.session = open_session(ZenohSettings(connect=[f"tcp/127.0.0.1:{port}"]))
        self.received: dict[str, list] = {}
        self._subs = []

    def record(self, key: str) -> list:
        """Decode and keep every message on `key` (wildcards allowed)."""
        bucket = self.received.setdefault(key, [])
        self._subs.append(
            self.session.declare_subscriber(
                key, lambda s: bucket.append(decode_any(s.payload.to_bytes()))
            )
        )
        return bucket

    def get(self, selector: str, timeout_s: float = 5.0, payload: bytes | None = None) -> list:
        """Decoded OK replies to a query; error replies raise AssertionError with the text."""
        out = []
        for reply in self.session.get(selector, timeout=timeout_s, payload=payload):
            if reply.ok is None:
                raise AssertionError(f"{selector}: {reply.err.payload.to_string()}")
            out.append(decode_any(reply.ok.payload.to_bytes()))
        return out

    def map_grid(self, robot: str = "robot") -> OccupancyGrid:
        """The map server's map of `robot`, as its native .npz image."""
        (image,) = self.get(f"{keys.map_key(robot, 'image')}?format=npz")
        with tempfile.TemporaryDirectory() as tmp:
            path = Path(tmp) / "map.npz"
            path.write_bytes(image.data)
            return load_npz(path)

    def stats(self, service: str, instance: str = "0") -> ServiceStatsMessage | None:
        replies = self.get(keys.stats(service, instance), timeout_s=3.0)
        return replies[0] if replies else None

    def alive(self) -> set[str]:
        """`service/instance` of every health token present."""
        tokens = set()
        for reply in self.session.liveliness().get(keys.health(), timeout=2.0):
            if reply.ok is not None:
                tokens.add("/".join(str(reply.ok.key_expr).split("/")[-2:]))
        return tokens

    def put(self, key: str, payload: bytes) -> None:
        self.session.put(key, payload, congestion_control=zenoh.CongestionControl.BLOCK)

    wait_until = staticmethod(wait_until)

    def close(self) -> None:
        self.session.close()


# The kernel services start here without their warm-up run (a short simulated run and every
# matcher: ~4 s of CPU a stack, ~40 stacks a suite): their first scans load the compiled
# kernels instead, which no test here times. A test may pass the setting back on; the warm-up
# itself is checked by tests/scanflow/test_warmup.py, and `scanflow up` and the containers run
# with it.
NO_WARM_UP = {f"SCANFLOW_{name}_WARM_UP": "false" for name in ("DESKEW", "MATCHER", "MAPSERVER")}


@pytest.fixture
def launcher(tmp_path: Path) -> Iterator[Launcher]:
    """A router on a free port; services started through it are all stopped at the end."""
    launch = Launcher.local(
        tmp_path / "logs",
        free_port(),
        SCANFLOW_MAPSERVER_DATA_DIR=str(tmp_path / "data"),
        SCANFLOW_INGEST_RATE="0",
        SCANFLOW_INGEST_DRAIN_TIMEOUT_S="30",
        **NO_WARM_UP,
    )
    launch.start("router")
    yield launch
    # The test has checked what it checks: nothing waits for what a stop flushes downstream
    # (`stop_all`, one at a time, added 3-4 s to every test here).
    codes = launch.stop_together(last=("router",))
    for name in launch.processes:
        print(f"---- {name} (exit {codes.get(name)}) ----\n{launch.log_text(name)[-3000:]}")


@pytest.fixture
def bus(launcher: Launcher) -> Iterator[Bus]:
    client = Bus(launcher.zenoh_port)
    yield client
    client.close()


@pytest.fixture
def start(launcher: Launcher, bus: Bus) -> Callable[..., None]:
    """start(name, label=None, **settings): start a service, wait for its health token."""

    def start_service(name: str, label: str | None = None, **settings: str) -> None:
        launcher.start(name, label, **settings)
        instance = settings.get(f"SCANFLOW_{name.upper()}_INSTANCE", "0")
        wait_until(lambda: f"{name}/{instance}" in bus.alive(), 30.0, f"{name} health token")

    return start_service


def stats_failures_while(stats: Callable[[], object], admit: Callable[[int], None]) -> list:
    """Gather `stats()` again and again on another thread (as Zenoh's stats queryable does)
    while `admit(i)` adds 20,000 robots as the worker would; the RuntimeErrors it raised (a
    dict that changed size while iterated: the stats query went unanswered)."""
    interval = sys.getswitchinterval()
    sys.setswitchinterval(1e-6)  # hand the GIL over often: the race shows at once
    failures: list[Exception] = []
    done = threading.Event()

    def scrape() -> None:
        while not done.is_set():
            try:
                stats()
            except RuntimeError as exc:
                failures.append(exc)

    scraper = threading.Thread(target=scrape)
    scraper.start()
    try:
        for i in range(20_000):
            admit(i)
    finally:
        done.set()
        scraper.join()
        sys.setswitchinterval(interval)
    return failures
