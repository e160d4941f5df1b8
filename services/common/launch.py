"""Start and stop service processes locally: used by `scanflow up`, the tests and the benchmark."""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

from scanflow import keys
from scanflow.config import LaunchSettings, ZenohSettings

from services.common.process import CpuPlan, available_cpus, cpu_plan
from services.common.zsession import open_session

ORDER = ("router", "deskew", "matcher", "mapserver", "gateway", "ingest")
PIPELINE = ("deskew", "matcher", "mapserver")  # what must listen before ingest publishes
# A clean stop goes with the data: the sources first, then each stage once the one feeding it
# has exited, so what a stage handles and flushes at its stop reaches a stage still running;
# the router (started first) goes last.
STOP_ORDER = ("ingest", "gateway", *PIPELINE)
# A service's clean stop: its inbox drain (SCANFLOW_<SERVICE>_INBOX_DRAIN_S, 5 s), its outbox
# sent (up to 10 s), a snapshot; past this it is killed (compose: stop_grace_period, the same).
STOP_TIMEOUT_S = 25.0


def _reap(proc: subprocess.Popen[bytes], timeout_s: float) -> int:
    """Wait for a process sent SIGTERM (SIGKILL after `timeout_s`); its exit code, 0 also when
    it died of that SIGTERM (uvicorn re-raises the signal after its graceful shutdown)."""
    try:
        proc.wait(timeout_s)
    except subprocess.TimeoutExpired:
        proc.kill()
        return proc.wait()
    return 0 if proc.returncode == -signal.SIGTERM else proc.returncode


def free_port() -> int:
    """A TCP port on loopback that nothing listens on right now."""
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


def wait_for_port(port: int, timeout_s: float = 10.0) -> None:
    """Block until something accepts TCP connections on 127.0.0.1:`port`."""
    deadline = time.monotonic() + timeout_s
    while True:
        try:
            with socket.create_connection(("127.0.0.1", port), timeout=0.2):
                return
        except OSError as exc:
            if time.monotonic() > deadline:
                message = f"nothing listens on 127.0.0.1:{port} after {timeout_s} s"
                raise TimeoutError(message) from exc
            time.sleep(0.05)


@dataclass
class Launcher:
    """Service subprocesses sharing one environment (router endpoint, prefix, settings).

    Each service logs to `<log_dir>/<name>.log`. `stop_all` sends SIGTERM to one service at a
    time (in a given order, the rest last started first) and waits for each, killing one that
    does not stop. With a `cpus` plan each service is started with
    its `SCANFLOW_<SERVICE>_CPUS` and `_IO_CPUS`, unless the environment already sets them.
    """

    env: dict[str, str]
    log_dir: Path
    cpus: CpuPlan | None = None
    processes: dict[str, subprocess.Popen[bytes]] = field(default_factory=dict)

    @classmethod
    def local(cls, log_dir: Path, zenoh_port: int, **settings: str) -> Launcher:
        """A launcher whose router listens on 127.0.0.1:`zenoh_port` and services connect there."""
        endpoint = f"tcp/127.0.0.1:{zenoh_port}"
        env = dict(os.environ)
        env.update(
            SCANFLOW_ROUTER_LISTEN=endpoint,
            SCANFLOW_ZENOH_CONNECT=endpoint,
            SCANFLOW_ZENOH_MODE="client",
            PYTHONUNBUFFERED="1",
        )
        env.update(settings)
        log_dir.mkdir(parents=True, exist_ok=True)
        return cls(env, log_dir, cpu_plan(available_cpus(), LaunchSettings().matcher_cpus))

    @property
    def zenoh_port(self) -> int:
        """The router's port, read from the services' SCANFLOW_ZENOH_CONNECT endpoint."""
        return int(self.env["SCANFLOW_ZENOH_CONNECT"].rsplit(":", 1)[1])

    def start(
        self, name: str, label: str | None = None, **settings: str
    ) -> subprocess.Popen[bytes]:
        """Start `python -m services.<name>` with the shared env plus `settings`; `label`
        (default: the name) tells two instances of one service apart."""
        label = label or name
        if label in self.processes and self.processes[label].poll() is None:
            raise RuntimeError(f"service {label!r} is already running")
        env = {**self.env, **settings}
        if self.cpus is not None:
            for key, cpus in (
                (f"SCANFLOW_{name.upper()}_CPUS", self.cpus.cpus_for(name, label)),
                (f"SCANFLOW_{name.upper()}_IO_CPUS", self.cpus.io_cpus_for(name, label)),
            ):
                env.setdefault(key, ",".join(map(str, cpus)))
        log = (self.log_dir / f"{label}.log").open("ab")
        # A session of its own: a terminal's Ctrl-C reaches only the launcher, which then
        # stops the services one at a time (`stop_all`) instead of all at once.
        proc = subprocess.Popen(
            [sys.executable, "-m", f"services.{name}"],
            env=env, stdout=log, stderr=log, start_new_session=True,
        )
        log.close()
        self.processes[label] = proc
        if name == "router":
            wait_for_port(self.zenoh_port)
        return proc

    def stop(self, name: str, timeout_s: float = STOP_TIMEOUT_S) -> int | None:
        """SIGTERM one service and wait for it (SIGKILL after `timeout_s`); its exit code.

        0 also when the service died of the SIGTERM sent here (uvicorn re-raises the signal
        after its graceful shutdown): that is the clean stop that was asked for.
        """
        proc = self.processes.get(name)
        if proc is None:
            return None
        if proc.poll() is not None:
            return proc.returncode
        proc.send_signal(signal.SIGTERM)
        return _reap(proc, timeout_s)

    def kill(self, name: str) -> None:
        """SIGKILL one service (a crash, for recovery tests)."""
        proc = self.processes[name]
        proc.kill()
        proc.wait()

    def stop_all(self, order: Sequence[str] = ()) -> dict[str, int | None]:
        """Stop every service, one at a time: those named in `order` first, in that order,
        then the rest last started first; their exit codes."""
        first = [name for name in order if name in self.processes]
        rest = [name for name in reversed(list(self.processes)) if name not in first]
        return {name: self.stop(name) for name in [*first, *rest]}

    def stop_together(
        self, last: Sequence[str] = (), timeout_s: float = STOP_TIMEOUT_S
    ) -> dict[str, int | None]:
        """Stop every service but those in `last` at once (SIGTERM to all, then wait, killing
        one not gone within `timeout_s`), then those in `last` one at a time; exit codes as
        `stop` gives them. For a stop where nothing needs what a stop flushes downstream (a
        test that has checked what it checks): each service's drain and exit (~0.9 s) then
        overlap instead of adding up as in `stop_all`."""
        running = {name: proc for name, proc in self.processes.items()
                   if name not in last and proc.poll() is None}
        for proc in running.values():
            proc.send_signal(signal.SIGTERM)
        deadline = time.monotonic() + timeout_s
        codes = {name: _reap(proc, max(0.0, deadline - time.monotonic()))
                 for name, proc in running.items()}
        rest = [name for name in self.processes if name not in running and name not in last]
        return {**codes, **{name: self.stop(name, timeout_s)
                            for name in [*rest, *(n for n in last if n in self.processes)]}}

    def exited(self) -> dict[str, int]:
        """Services that have ended, with their exit codes."""
        return {n: p.returncode for n, p in self.processes.items() if p.poll() is not None}

    def wait_healthy(self, services: Iterable[str], timeout_s: float = 180.0) -> None:
        """Block until every named service shows its health token (any instance)."""
        wanted = set(services)
        session = open_session(ZenohSettings(connect=[f"tcp/127.0.0.1:{self.zenoh_port}"]))
        try:
            deadline = time.monotonic() + timeout_s
            while True:
                replies = session.liveliness().get(keys.health(), timeout=2.0)
                alive = {str(r.ok.key_expr).split("/")[-2] for r in replies if r.ok is not None}
                if wanted <= alive:
                    return
                if time.monotonic() > deadline:
                    missing = sorted(wanted - alive)
                    raise TimeoutError(f"services {missing} not up after {timeout_s} s")
                time.sleep(0.2)
        finally:
            session.close()

    def log_text(self, name: str) -> str:
        """The log so far of the service started under `name`; empty when there is none."""
        path = self.log_dir / f"{name}.log"
        return path.read_text(errors="replace") if path.exists() else ""
