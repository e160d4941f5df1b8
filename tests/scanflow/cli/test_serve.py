"""`scanflow serve <service>`: runs `services.<name>` as __main__, refuses what it cannot run."""

from __future__ import annotations

import importlib.util
import pkgutil
from types import SimpleNamespace

import pytest
from scanflow.cli import _register, app
from scanflow.cli import serve as serve_module
from scanflow.cli.serve import ServiceName
from typer.testing import CliRunner

import services


@pytest.fixture
def runs(monkeypatch: pytest.MonkeyPatch) -> list[tuple[str, dict[str, object]]]:
    """The modules `serve` hands to runpy (none is actually run), with runpy's keywords."""
    _register()
    calls: list[tuple[str, dict[str, object]]] = []
    fake = SimpleNamespace(run_module=lambda module, **kwargs: calls.append((module, kwargs)))
    monkeypatch.setattr(serve_module, "runpy", fake)
    return calls


def _text(output: str) -> str:
    """The output's words on one line: the error box's borders and wrapping removed."""
    return " ".join(output.replace("│", " ").split())


def test_serve_refuses_an_unknown_service_naming_the_choices(runs) -> None:
    result = CliRunner().invoke(app, ["serve", "bogus"])
    assert result.exit_code == 2
    text = _text(result.output)
    assert "'bogus' is not one of" in text
    for name in ("router", "ingest", "deskew", "matcher", "mapserver", "gateway"):
        assert f"'{name}'" in text
    assert runs == []


@pytest.mark.parametrize("name", [s.value for s in ServiceName])
def test_serve_runs_the_services_package_as_main(runs, name: str) -> None:
    """The same as `python -m services.<name>`: run as __main__, with sys.argv[0] set."""
    result = CliRunner().invoke(app, ["serve", name])
    assert result.exit_code == 0, result.output
    assert runs == [(f"services.{name}", {"run_name": "__main__", "alter_sys": True})]


def test_serve_names_a_service_that_is_not_installed(runs, monkeypatch) -> None:
    """A slim image without the gateway: a clear refusal, not an ImportError traceback."""
    real = importlib.util.find_spec
    monkeypatch.setattr(
        importlib.util, "find_spec", lambda name: None if name == "services.gateway" else real(name)
    )
    result = CliRunner().invoke(app, ["serve", "gateway"])
    assert result.exit_code == 2
    assert "service 'gateway' is not installed (services.gateway is missing)" in _text(
        result.output
    )
    assert runs == []


def test_the_choices_are_exactly_the_runnable_services() -> None:
    """Every `services/<name>/__main__.py` can be served, and nothing else is offered."""
    runnable = {
        info.name
        for info in pkgutil.iter_modules(services.__path__)
        if info.ispkg and importlib.util.find_spec(f"services.{info.name}.__main__") is not None
    }
    assert {s.value for s in ServiceName} == runnable
