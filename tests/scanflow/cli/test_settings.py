"""`scanflow settings`: the reference covers every setting, matches docs/settings.md, and
--json reports the environment's values and names a bad one."""

from __future__ import annotations

import json
import os
import typing
from pathlib import Path

import pytest
from pydantic import SecretStr
from scanflow.cli import _register, app
from scanflow.cli.settings import all_settings, current_values, reference_markdown
from scanflow.config import SettingsError
from typer.testing import CliRunner

_register()
runner = CliRunner()


@pytest.fixture(autouse=True)
def _clean_env(monkeypatch):
    """No SCANFLOW_* variable of the caller's: each test sets its own."""
    for name in [n for n in os.environ if n.startswith("SCANFLOW_")]:
        monkeypatch.delenv(name)
DOC = Path(__file__).resolve().parents[3] / "docs" / "settings.md"


def test_every_setting_says_what_it_does():
    assert [s.name for s in all_settings() if not (s.info.description or "").strip()] == []


def test_docs_settings_md_is_the_commands_output():
    assert DOC.read_text() == reference_markdown(), (
        "docs/settings.md is stale: run `scanflow settings > docs/settings.md`"
    )


def test_the_reference_names_each_variable_and_its_default():
    text = reference_markdown()
    assert "| `SCANFLOW_GATEWAY_PORT` | int, >= 1, <= 65535 | `8000` |" in text
    assert "| `SCANFLOW_FRONTEND_METHOD` | csm \\| csm+plicp \\| csm_exhaustive" in text
    assert "\\| plicp \\| svd | `gn` |" in text
    assert ("| `SCANFLOW_ZENOH_CONNECT` | list (comma-separated or JSON) | `tcp/127.0.0.1:7447` |"
            in text)
    assert "`SCANFLOW_<SERVICE>_LOG_LEVEL` | DEBUG \\| INFO \\| WARNING \\| ERROR | `INFO`" in text
    # A shared field read by some services only says which.
    assert "`SCANFLOW_<SERVICE>_WARM_UP`" in text and "only DESKEW, MATCHER, MAPSERVER" in text
    # Shared fields are listed once, not under every service's prefix.
    assert "SCANFLOW_DESKEW_LOG_LEVEL" not in text


def _free_text(setting) -> bool:
    """Settings any text is valid for (a bad value cannot show that the name is read)."""
    annotation = setting.info.annotation
    kinds = [a for a in typing.get_args(annotation) if a is not type(None)] or [annotation]
    return any(k in (str, SecretStr) or k == list[str] for k in kinds)


@pytest.mark.parametrize("setting", [s for s in all_settings() if not _free_text(s)],
                         ids=lambda s: s.name)
def test_each_listed_name_is_the_variable_its_section_reads(setting, monkeypatch):
    """Setting the listed variable to a bad value fails, naming it: the name is really read."""
    monkeypatch.setenv(setting.name, "x")
    with pytest.raises(SettingsError, match=setting.name):
        current_values()


def test_json_gives_the_environments_values_and_hides_secrets(monkeypatch):
    monkeypatch.setenv("SCANFLOW_GATEWAY_PORT", "9001")
    monkeypatch.setenv("SCANFLOW_GATEWAY_API_KEY", "hunter2")
    monkeypatch.setenv("SCANFLOW_MATCHER_ROBOTS", "a,b")
    result = runner.invoke(app, ["settings", "--json"])
    assert result.exit_code == 0, result.output
    rows = {row["name"]: row for row in json.loads(result.stdout)}
    assert rows["SCANFLOW_GATEWAY_PORT"] == {**rows["SCANFLOW_GATEWAY_PORT"], "default": "8000",
                                             "value": "9001"}
    assert rows["SCANFLOW_MATCHER_ROBOTS"]["value"] == "a,b"
    assert rows["SCANFLOW_GATEWAY_API_KEY"]["value"] == "set (hidden)"
    assert "hunter2" not in result.stdout
    assert rows["SCANFLOW_DESKEW_LOG_LEVEL"]["default"] == "INFO"


def test_a_bad_value_exits_2_naming_the_variable(monkeypatch):
    monkeypatch.setenv("SCANFLOW_FRONTEND_MIN_POINTS", "2")
    monkeypatch.setenv("SCANFLOW_ZENOH_MODE", "server")
    result = runner.invoke(app, ["settings", "--json"])
    assert result.exit_code == 2
    assert "SCANFLOW_FRONTEND_MIN_POINTS" in result.output
    assert "SCANFLOW_ZENOH_MODE='server'" in result.output

