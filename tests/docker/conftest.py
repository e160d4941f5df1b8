"""Container test harness: a Docker engine (or a loud skip), the built image, compose projects.

No Docker engine: every test here is skipped with a loud reason, unless Docker is required
(CI=true or SCANFLOW_REQUIRE_DOCKER=1), where that is a failure. SCANFLOW_DOCKER_NO_BUILD=1
reuses an existing scanflow:latest instead of running docker/build.sh (for iterating locally).
Works with compose v2 (`docker compose`) and v1 (`docker-compose`); every command has a timeout
and a failure raises with the command's output, so a broken stack fails with its reason.
Tests reach the helpers through fixtures (pytest's importlib mode does not import conftest).
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import signal
import socket
import subprocess
import time
import warnings
from collections.abc import Callable, Iterator, Sequence
from functools import cache
from pathlib import Path
from types import SimpleNamespace

import pytest

REPO = Path(__file__).resolve().parents[2]
IMAGE = os.environ.get("SCANFLOW_IMAGE", "scanflow:latest")
# The deployment's compose file plus the tests' override (health checks every second).
COMPOSE_FILES = ("docker-compose.yml", "tests/docker/compose.test.yml")


class DockerError(RuntimeError):
    """A docker or compose command failed or timed out; the message holds its output."""


def run(args: Sequence[str], timeout_s: float = 120.0, check: bool = True,
        env: dict[str, str] | None = None) -> subprocess.CompletedProcess[str]:
    """Run a command, capture its output; raise DockerError on failure or timeout."""
    try:
        proc = subprocess.run(list(args), capture_output=True, text=True, timeout=timeout_s,
                              env=env, cwd=REPO, check=False)
    except subprocess.TimeoutExpired as exc:
        raise DockerError(f"{' '.join(args)} timed out after {timeout_s:.0f} s:\n"
                          f"{exc.stdout or ''}{exc.stderr or ''}") from exc
    if check and proc.returncode != 0:
        raise DockerError(f"{' '.join(args)} exited {proc.returncode}:\n"
                          f"{proc.stdout[-4000:]}{proc.stderr[-4000:]}")
    return proc


def engine_problem() -> str | None:
    """None when a Docker engine answers, else why not (for a loud skip or a failure)."""
    if shutil.which("docker") is None:
        return "the `docker` command is not installed"
    try:
        proc = subprocess.run(["docker", "info", "--format", "{{.ServerVersion}}"],
                              capture_output=True, text=True, timeout=30, check=False)
    except subprocess.TimeoutExpired:
        return "`docker info` did not answer within 30 s"
    if proc.returncode != 0:
        return f"`docker info` failed: {proc.stderr.strip()[:300]}"
    if compose_command() is None:
        return "neither `docker compose` nor `docker-compose` is installed"
    return None


def docker_required() -> bool:
    """Docker tests are mandatory in CI (CI=true) or when SCANFLOW_REQUIRE_DOCKER=1."""
    return (os.environ.get("SCANFLOW_REQUIRE_DOCKER") == "1"
            or os.environ.get("CI", "").lower() == "true")


@cache
def compose_command() -> tuple[str, ...] | None:
    """`docker compose` (v2) when available, else `docker-compose` (v1), else None."""
    for candidate in (("docker", "compose"), ("docker-compose",)):
        if shutil.which(candidate[0]) is None:
            continue
        probe = subprocess.run([*candidate, "version"], capture_output=True, text=True,
                               timeout=30, check=False)
        if probe.returncode == 0:
            return candidate
    return None


def build_image(timeout_s: float = 900.0) -> str:
    """Build the base image (when missing) and scanflow:latest with docker/build.sh; its id."""
    run(["bash", str(REPO / "docker" / "build.sh"), "--tag", IMAGE], timeout_s=timeout_s)
    return image_id(IMAGE)


def image_id(image: str) -> str:
    return run(["docker", "image", "inspect", "-f", "{{.Id}}", image]).stdout.strip()


def image_layers(image: str) -> list[str]:
    """The content digests of the image's filesystem layers, base first."""
    out = run(["docker", "image", "inspect", "-f", "{{json .RootFS.Layers}}", image]).stdout
    return list(json.loads(out))


def app_wheel_digest() -> str:
    """sha256 of the scanflow wheel build.sh put in the build context."""
    wheels = sorted((REPO / "docker" / "wheels" / "app").glob("*.whl"))
    return hashlib.sha256(b"".join(w.read_bytes() for w in wheels)).hexdigest()


def docker_run(*args: str, entrypoint: str | None = None, timeout_s: float = 60.0) -> str:
    """`docker run --rm IMAGE args...`; its stdout."""
    head = ["docker", "run", "--rm"] + (["--entrypoint", entrypoint] if entrypoint else [])
    return run([*head, IMAGE, *args], timeout_s=timeout_s).stdout


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


class ComposeProject:
    """One compose project (unique name) over the repo's compose files."""

    def __init__(self, name: str, files: Sequence[str] = COMPOSE_FILES,
                 env: dict[str, str] | None = None) -> None:
        command = compose_command()
        if command is None:
            raise DockerError("no compose command: install docker compose or docker-compose")
        self.name = name
        self.env = {**os.environ, "SCANFLOW_IMAGE": IMAGE, **(env or {})}
        self._head = [*command, "-p", name]
        for file in files:
            self._head += ["-f", str(REPO / file)]

    def compose(self, *args: str, timeout_s: float = 120.0,
                check: bool = True) -> subprocess.CompletedProcess[str]:
        return run([*self._head, *args], timeout_s=timeout_s, check=check, env=self.env)

    def up(self, *services: str, timeout_s: float = 300.0) -> None:
        """Start services (all by default) detached, without building or pulling."""
        self.compose("up", "-d", "--no-build", *services, timeout_s=timeout_s)

    def down(self) -> None:
        """Remove containers, networks and volumes of the project (always safe to call)."""
        self.compose("down", "-v", "--remove-orphans", "--timeout", "10", timeout_s=180.0,
                     check=False)

    def container(self, service: str) -> str:
        """The id of the service's container (running or not)."""
        ids = self.compose("ps", "-a", "-q", service).stdout.split()
        if not ids:
            raise DockerError(f"service {service!r} has no container in project {self.name}")
        return ids[0]

    def state(self, service: str) -> dict:
        """`docker inspect` State of the service's container (Status, Health, ExitCode...)."""
        out = run(["docker", "inspect", "-f", "{{json .State}}", self.container(service)])
        return json.loads(out.stdout)

    def health(self, service: str) -> str:
        """'healthy', 'unhealthy', 'starting', or the container status when it has no check."""
        state = self.state(service)
        return (state.get("Health") or {}).get("Status") or state["Status"]

    def wait_healthy(self, services: Sequence[str], timeout_s: float = 180.0) -> float:
        """Poll until every service is healthy; seconds waited. Raises with logs on timeout."""
        start = time.monotonic()
        pending = list(services)
        while pending:
            pending = [s for s in pending if self.health(s) != "healthy"]
            if not pending:
                break
            if time.monotonic() - start > timeout_s:
                detail = {s: self.health(s) for s in pending}
                raise DockerError(f"not healthy after {timeout_s:.0f} s: {detail}\n"
                                  + "\n".join(self.describe(s) for s in pending))
            time.sleep(0.5)
        return time.monotonic() - start

    def wait_status(self, service: str, wanted: str, timeout_s: float = 60.0) -> None:
        """Poll until the service's health (or status) equals `wanted`."""
        deadline = time.monotonic() + timeout_s
        while (current := self.health(service)) != wanted:
            if time.monotonic() > deadline:
                raise DockerError(f"{service} is {current!r}, not {wanted!r} after "
                                  f"{timeout_s:.0f} s\n{self.describe(service)}")
            time.sleep(0.5)

    def describe(self, service: str) -> str:
        """Health-check log and log tail of a service, for failure messages."""
        state = self.state(service)
        checks = [c.get("Output", "").strip() for c in (state.get("Health") or {}).get("Log", [])]
        return (f"--- {service}: {state['Status']} exit={state.get('ExitCode')} "
                f"restarts={self.restarts(service)}\nhealth checks: {checks[-3:]}\n"
                f"{self.logs(service, tail=40)}")

    def restarts(self, service: str) -> int:
        out = run(["docker", "inspect", "-f", "{{.RestartCount}}", self.container(service)])
        return int(out.stdout.strip())

    def logs(self, service: str | None = None, tail: int = 200) -> str:
        args = ["logs", "--no-color", "--tail", str(tail)] + ([service] if service else [])
        proc = self.compose(*args, check=False)
        return proc.stdout + proc.stderr

    def exec(self, service: str, *cmd: str, timeout_s: float = 60.0,
             check: bool = True) -> subprocess.CompletedProcess[str]:
        """Run a command in the service's running container."""
        return self.compose("exec", "-T", service, *cmd, timeout_s=timeout_s, check=check)

    def stop(self, service: str) -> None:
        self.compose("stop", "--timeout", "20", service)

    def start(self, service: str) -> None:
        self.compose("start", service)

    def kill9(self, service: str) -> None:
        """SIGKILL the service's main process from outside: a crash, which the restart policy
        answers (`docker kill` would count as a manual stop and disable it)."""
        pid = int(run(["docker", "inspect", "-f", "{{.State.Pid}}", self.container(service)])
                  .stdout)
        try:
            os.kill(pid, signal.SIGKILL)  # the daemon shares our PID namespace
        except (ProcessLookupError, PermissionError):
            run(["docker", "run", "--rm", "--pid=host", "--user=0", "--entrypoint=bash",
                 IMAGE, "-c", f"kill -9 {pid}"])

    def network(self, service: str) -> str:
        """The (first) network the service's container is attached to."""
        out = run(["docker", "inspect", "-f", "{{json .NetworkSettings.Networks}}",
                   self.container(service)])
        return next(iter(json.loads(out.stdout)))

    def disconnect(self, service: str, network: str) -> None:
        run(["docker", "network", "disconnect", network, self.container(service)])

    def connect(self, service: str, network: str) -> None:
        run(["docker", "network", "connect", "--alias", service, network,
             self.container(service)])

    def leftovers(self) -> list[str]:
        """Containers, networks and volumes still labelled with this project."""
        label = f"label=com.docker.compose.project={self.name}"
        found = []
        for kind in (["ps", "-a"], ["network", "ls"], ["volume", "ls"]):
            out = run(["docker", *kind, "-q", "--filter", label]).stdout.split()
            found += [f"{kind[0]}:{item}" for item in out]
        return found


@pytest.fixture(scope="session")
def docker_engine() -> None:
    """A Docker engine with compose; skip loudly (or fail where required) without one."""
    problem = engine_problem()
    if problem is None:
        return
    if docker_required():
        pytest.fail(f"Docker is REQUIRED here (CI=true or SCANFLOW_REQUIRE_DOCKER=1) but {problem}")
    message = (f"!!! NO DOCKER ENGINE: the container tests (tests/docker) did NOT run: {problem}. "
               "Set SCANFLOW_REQUIRE_DOCKER=1 to make this a failure. !!!")
    warnings.warn(message, stacklevel=1)
    pytest.skip(message)


@pytest.fixture(scope="session")
def scanflow_image(docker_engine: None) -> str:
    """scanflow:latest built from this checkout (base image included); its image id."""
    if os.environ.get("SCANFLOW_DOCKER_NO_BUILD") == "1":
        return image_id(IMAGE)
    return build_image()


@pytest.fixture(scope="session")
def harness(scanflow_image: str) -> SimpleNamespace:
    """The helpers tests call directly (the image is built by then)."""
    return SimpleNamespace(run=run, docker_run=docker_run, build_image=build_image,
                           image_id=image_id, image_layers=image_layers,
                           app_wheel_digest=app_wheel_digest, free_port=free_port, image=IMAGE,
                           DockerError=DockerError)


@pytest.fixture(scope="module")
def compose_projects(scanflow_image: str) -> Iterator[Callable[..., ComposeProject]]:
    """Make compose projects; each is taken down with its volumes at the end of the module,
    whatever happened, and nothing labelled with it may remain."""
    made: list[ComposeProject] = []

    def make(prefix: str, files: Sequence[str] = COMPOSE_FILES,
             env: dict[str, str] | None = None) -> ComposeProject:
        project = ComposeProject(f"{prefix}{os.getpid()}", files, env)
        project.down()  # a leftover of an aborted run with the same name
        made.append(project)
        return project

    yield make
    left = {}
    for project in made:
        project.down()
        if remaining := project.leftovers():
            left[project.name] = remaining
    assert not left, f"`down -v` left these behind: {left}"


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """The container tests run first, the rest after them in their own order. `make test` runs
    them in its second process with the tests marked second_lane, beside the first process: on
    a fresh clone the first process compiles the numba kernels (cache=True) early on, while the
    containers here use the ones compiled into the image, so the second process's own service
    tests, run after these, find the kernels on disk instead of compiling them again in every
    service at once (`bench.pipeline`'s throughput test, first in that process until now, took
    114 s here on a fresh clone beside the first process, 13 s with the kernels on disk)."""
    items.sort(key=lambda item: item.get_closest_marker("docker") is None)
