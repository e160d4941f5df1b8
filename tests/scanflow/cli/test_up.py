"""`scanflow up` without processes: its options as settings, what it starts in which order, how
it stops and its exit code. Real processes: tests/services/test_up.py."""

from __future__ import annotations

import importlib.util
import os
import signal
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import pytest
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st
from scanflow.cli import _register, app
from scanflow.cli import up as up_module
from scanflow.maps.export import save_map
from scanflow.maps.occupancy import OccupancyGrid
from typer.testing import CliRunner, Result

from services.common import launch

EVERY_SERVICE = ["router", "deskew", "matcher", "mapserver", "gateway", "ingest"]
FAST = settings(
    max_examples=30, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)


@dataclass
class Plan:
    """What the fake launcher reports, and what `scanflow up` asked of it."""

    codes: dict[str, int] = field(default_factory=dict)  # stop_all's exit codes (default 0)
    exits: dict[str, int] = field(default_factory=dict)  # services that ended on their own
    polls: int = 1  # `exited()` calls before a SIGINT arrives
    signal_after_start: str | None = None  # a SIGTERM arrives once this service started
    handlers: dict[int, Callable[[int, object], None]] = field(default_factory=dict)
    launchers: list[FakeLauncher] = field(default_factory=list)

    def send(self, signum: int) -> None:
        self.handlers[signum](signum, None)


@dataclass
class FakeLauncher:
    """Records the calls of `scanflow up`; starts nothing."""

    plan: Plan
    log_dir: Path
    zenoh_port: int
    settings: dict[str, str]
    calls: list[str] = field(default_factory=list)

    def start(self, name: str) -> None:
        self.calls.append(name)
        if name == self.plan.signal_after_start:
            self.plan.send(signal.SIGTERM)

    def wait_healthy(self, services: tuple[str, ...]) -> None:
        self.calls.append(f"wait for {','.join(services)}")

    def exited(self) -> dict[str, int]:
        self.plan.polls -= 1
        if self.plan.polls <= 0:
            self.plan.send(signal.SIGINT)
        return dict(self.plan.exits)

    def stop_all(self, order: tuple[str, ...] = ()) -> dict[str, int]:
        self.calls.append(f"stop {','.join(order)}, then the rest")
        started = [c for c in self.calls if c in EVERY_SERVICE]
        first = [name for name in order if name in started]
        rest = [name for name in reversed(started) if name not in first]
        return {name: self.plan.codes.get(name, 0) for name in [*first, *rest]}


@pytest.fixture
def run_up(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> Callable[..., tuple[Result, Plan]]:
    """run_up(*args, **plan): `scanflow up *args` on a fake launcher, signals and log dir; no
    SCANFLOW_* variable of the caller's, the current directory `tmp_path`."""
    _register()
    for name in [n for n in os.environ if n.startswith("SCANFLOW_")]:
        monkeypatch.delenv(name)
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(up_module, "time", SimpleNamespace(sleep=lambda _s: None))
    logs = tmp_path / "logs"
    monkeypatch.setattr(up_module, "tempfile", SimpleNamespace(mkdtemp=lambda prefix: str(logs)))

    def run(*args: str, **plan_fields: Any) -> tuple[Result, Plan]:
        plan = Plan(**plan_fields)

        def local(log_dir: Path, zenoh_port: int, **env: str) -> FakeLauncher:
            plan.launchers.append(FakeLauncher(plan, log_dir, zenoh_port, env))
            return plan.launchers[-1]

        def on(signum: int, handler: Callable[[int, object], None]) -> None:
            plan.handlers[signum] = handler

        monkeypatch.setattr(launch, "Launcher", SimpleNamespace(local=local))
        fake_signal = SimpleNamespace(SIGTERM=signal.SIGTERM, SIGINT=signal.SIGINT, signal=on)
        monkeypatch.setattr(up_module, "signal", fake_signal)
        return CliRunner().invoke(app, ["up", *args]), plan

    return run


def test_up_starts_every_service_in_order_and_ingest_once_the_pipeline_listens(run_up) -> None:
    result, plan = run_up()
    assert result.exit_code == 0, result.output
    (launcher,) = plan.launchers
    assert launcher.calls == [
        "router", "deskew", "matcher", "mapserver", "gateway",
        "wait for deskew,matcher,mapserver", "ingest",
        "stop ingest,gateway,deskew,matcher,mapserver, then the rest",  # with the data
    ]
    assert set(plan.handlers) == {signal.SIGINT, signal.SIGTERM}


def test_up_gives_every_service_its_defaults_as_settings(run_up, tmp_path) -> None:
    result, plan = run_up()
    assert result.exit_code == 0, result.output
    (launcher,) = plan.launchers
    assert launcher.zenoh_port == 7447 and launcher.log_dir == tmp_path / "logs"
    assert launcher.settings == {
        "SCANFLOW_INGEST_RATE": "1.0",
        "SCANFLOW_MAPSERVER_DATA_DIR": str(tmp_path / "scanflow-data"),
        "SCANFLOW_GATEWAY_PORT": "8000",
    }


def test_up_passes_every_option_on_as_a_setting_with_absolute_paths(run_up, tmp_path) -> None:
    prior = OccupancyGrid()
    prior.insert_scan([[1.0, 0.0]], (0.0, 0.0))  # one occupied cell: a usable prior map
    save_map(prior, tmp_path / "prior.npz")
    (tmp_path / "run.log").write_text("")
    result, plan = run_up(
        "--log", "run.log", "--rate", "0", "--port", "8123", "--zenoh-port", "7500",
        "--data-dir", "data", "--limit", "15", "--prior-map", "prior.npz", "--loop-closure",
    )
    assert result.exit_code == 0, result.output
    (launcher,) = plan.launchers
    assert launcher.zenoh_port == 7500
    assert launcher.settings == {
        "SCANFLOW_INGEST_RATE": "0.0",
        "SCANFLOW_MAPSERVER_DATA_DIR": str(tmp_path / "data"),
        "SCANFLOW_GATEWAY_PORT": "8123",
        "SCANFLOW_INGEST_LOG": str(tmp_path / "run.log"),
        "SCANFLOW_INGEST_LIMIT": "15",
        "SCANFLOW_FRONTEND_PRIOR_MAP": str(tmp_path / "prior.npz"),
        "SCANFLOW_BACKEND_LOOP_CLOSURE": "true",
    }


@FAST
@given(
    rate=st.floats(0.0, 1e3, allow_nan=False),
    port=st.integers(1, 65535),
    zenoh_port=st.integers(1, 65535),
    limit=st.none() | st.integers(1, 10**9),
)
@example(rate=0.0, port=1, zenoh_port=65535, limit=1)  # as fast as possible; one scan
def test_up_carries_rates_ports_and_limits_unchanged(
    run_up, rate: float, port: int, zenoh_port: int, limit: int | None
) -> None:
    args = ["--rate", repr(rate), "--port", str(port), "--zenoh-port", str(zenoh_port)]
    result, plan = run_up(*args, *([] if limit is None else ["--limit", str(limit)]))
    assert result.exit_code == 0, result.output
    (launcher,) = plan.launchers
    assert float(launcher.settings["SCANFLOW_INGEST_RATE"]) == rate
    assert launcher.settings["SCANFLOW_GATEWAY_PORT"] == str(port)
    assert launcher.zenoh_port == zenoh_port
    assert launcher.settings.get("SCANFLOW_INGEST_LIMIT") == (None if limit is None else str(limit))
    assert f"zenoh:    tcp/127.0.0.1:{zenoh_port} (SCANFLOW_ZENOH_CONNECT)" in result.output
    assert f"gateway:  http://127.0.0.1:{port}/" in result.output


def test_up_reports_the_source_and_where_the_logs_are(run_up, tmp_path) -> None:
    result, _ = run_up("--rate", "2")
    assert result.exit_code == 0, result.output
    assert "source:   built-in simulator at rate 2.0" in result.output
    assert f"logs:     {tmp_path / 'logs'}" in result.output
    assert result.output.index("Ctrl-C stops everything.") < result.output.index("stopping...")


def test_up_skips_a_gateway_that_is_not_installed(run_up, monkeypatch) -> None:
    real = importlib.util.find_spec
    monkeypatch.setattr(
        importlib.util, "find_spec", lambda name: None if name == "services.gateway" else real(name)
    )
    result, plan = run_up()
    assert result.exit_code == 0, result.output
    assert "gateway: not installed, skipped" in result.output
    assert "gateway" not in plan.launchers[0].calls
    assert "ingest" in plan.launchers[0].calls


def test_up_reports_a_service_that_ended_once_while_it_waits(run_up, tmp_path) -> None:
    result, _ = run_up(exits={"ingest": 0}, polls=3)
    assert result.exit_code == 0, result.output
    line = f"ingest exited with code 0 (log: {tmp_path / 'logs' / 'ingest.log'})"
    assert result.output.count(line) == 1


def test_up_exits_1_naming_the_services_that_did_not_stop_cleanly(run_up) -> None:
    result, _ = run_up(codes={"matcher": 1, "deskew": -9})
    assert result.exit_code == 1
    assert "  matcher: exit 1" in result.output and "  router: exit 0" in result.output
    assert "not a clean stop: deskew, matcher (logs: " in result.stderr


def test_a_signal_while_starting_starts_nothing_more_and_stops_what_runs(run_up) -> None:
    result, plan = run_up(signal_after_start="deskew")
    assert result.exit_code == 0, result.output
    assert plan.launchers[0].calls == [
        "router", "deskew", "stop ingest,gateway,deskew,matcher,mapserver, then the rest"
    ]
    assert "  deskew: exit 0" in result.output and "  router: exit 0" in result.output


def test_up_refuses_a_bad_environment_variable_before_starting_anything(
    run_up, monkeypatch
) -> None:
    monkeypatch.setenv("SCANFLOW_INGEST_RATE", "fast")
    result, plan = run_up()
    assert result.exit_code == 2
    assert "SCANFLOW_INGEST_RATE" in result.output
    assert plan.launchers == []


def test_up_refuses_a_missing_prior_map_before_starting_anything(run_up) -> None:
    result, plan = run_up("--prior-map", "none.npz")
    assert result.exit_code == 2 and "no file at none.npz" in result.output
    assert plan.launchers == []


@pytest.mark.parametrize(
    ("variable", "value", "named"),
    [("SCANFLOW_FRONTEND_PRIOR_MAP", "none.npz", "no file at none.npz"),
     ("SCANFLOW_FRONTEND_UPDATE_MAP", "false", "prior_map is unset")],
)
def test_up_refuses_the_environments_unusable_start_before_starting_anything(
    run_up, monkeypatch, variable: str, value: str, named: str
) -> None:
    """A prior map the environment names, or its lack where localising only: read first as
    with --prior-map (before, every service started, and the matcher and map server exited)."""
    monkeypatch.setenv(variable, value)
    result, plan = run_up()
    assert result.exit_code == 2 and named in result.output, result.output
    assert plan.launchers == []


@pytest.mark.parametrize(
    ("option", "value", "named"),
    [("--limit", "0", "--limit"), ("--rate", "-1", "--rate"), ("--rate", "nan", "--rate"),
     ("--rate", "inf", "--rate"),
     ("--port", "0", "--port"), ("--zenoh-port", "70000", "--zenoh-port"),
     ("--log", ".", "is a directory")],
)
def test_up_refuses_an_option_a_service_would_refuse_before_starting_anything(
    run_up, option: str, value: str, named: str
) -> None:
    """Before, each became a setting its service refused at its own start: every other
    service ran on, and `up` with them, until Ctrl-C."""
    result, plan = run_up(option, value)
    assert result.exit_code == 2 and named in result.output, result.output
    assert plan.launchers == []


def test_up_refuses_a_missing_log_before_starting_anything(run_up) -> None:
    result, plan = run_up("--log", "none.log.gz")
    assert result.exit_code == 2 and "none.log.gz" in result.output, result.output
    assert "does not exist" in result.output
    assert plan.launchers == []


def test_up_with_loop_closure_says_so_and_how_keyframes_are_culled(run_up, monkeypatch) -> None:
    monkeypatch.setenv("SCANFLOW_BACKEND_CULL_M", "0.3")
    result, plan = run_up("--loop-closure")
    assert result.exit_code == 0, result.output
    assert plan.launchers[0].settings["SCANFLOW_BACKEND_LOOP_CLOSURE"] == "true"
    assert "back end: loop closure on" in result.output
    assert "keyframes culled within 0.3 m / 10.0 deg of one drawn" in result.output
    result, plan = run_up()
    assert "SCANFLOW_BACKEND_LOOP_CLOSURE" not in plan.launchers[0].settings
    assert "back end:" not in result.output


def test_up_refuses_an_unusable_prior_map_before_starting_anything(run_up, tmp_path) -> None:
    """A prior map that is there but cannot be used (corrupt, or nothing occupied) stopped the
    matcher and map server at their start, and `up` then waited for their health for minutes
    before a traceback: it is read here first, as the services will read it."""
    (tmp_path / "bad.npz").write_bytes(b"not a map")
    result, plan = run_up("--prior-map", "bad.npz")
    assert result.exit_code == 2, result.output
    assert "prior_map bad.npz" in result.output
    assert plan.launchers == []
