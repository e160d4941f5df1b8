"""The compose files set only variables scanflow reads, and docs/containers.md names every one
a user can pass from the shell (no Docker needed: this reads the files)."""

from __future__ import annotations

import re
from pathlib import Path

import pytest
from scanflow.cli.settings import all_settings

REPO = Path(__file__).resolve().parents[2]
COMPOSE = ("docker-compose.yml", "docker-compose.replay.yml")
# Read by compose itself, not by a scanflow process.
COMPOSE_ONLY = {"SCANFLOW_IMAGE", "SCANFLOW_GATEWAY_PUBLISH", "SCANFLOW_REPLAY_DIR",
                "SCANFLOW_REPLAY_FILE"}


def _text(name: str) -> str:
    return (REPO / name).read_text()


@pytest.mark.parametrize("name", COMPOSE)
def test_every_variable_a_compose_file_sets_is_a_setting(name):
    """A misspelt variable would be ignored without a word: each key must be a real setting."""
    known = {s.name for s in all_settings()} | COMPOSE_ONLY
    keys = set(re.findall(r"^\s+(SCANFLOW_[A-Z0-9_]+):", _text(name), flags=re.MULTILINE))
    passed = set(re.findall(r"\$\{(SCANFLOW_[A-Z0-9_]+)", _text(name)))
    assert keys | passed, f"{name} sets no SCANFLOW_* variable: the pattern is wrong"
    assert (keys | passed) - known == set()


def test_the_docs_name_every_variable_compose_takes_from_the_shell():
    docs = _text("docs/containers.md")
    passed = {v for name in COMPOSE
              for v in re.findall(r"\$\{(SCANFLOW_[A-Z0-9_]+)", _text(name))}
    passed |= set(re.findall(r"^\s+(SCANFLOW_[A-Z0-9_]+):\s*(?:#.*)?$", _text(COMPOSE[0]),
                             flags=re.MULTILINE))  # passed through when set
    assert "SCANFLOW_GATEWAY_API_KEY" in passed
    assert sorted(v for v in passed if not re.search(rf"\b{v}\b", docs)) == []
