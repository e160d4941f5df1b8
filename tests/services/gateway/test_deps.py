"""deps.py: the shared dependencies (settings, backend, API-key guard, robot id path check)."""

from __future__ import annotations

from types import SimpleNamespace

import pytest
from fastapi import HTTPException
from fastapi.exceptions import RequestValidationError
from scanflow.config import GatewaySettings

from services.gateway.deps import get_backend, get_settings, require_key, robot_id

from .conftest import API_KEY


def test_settings_and_backend_come_from_the_apps_state():
    state = SimpleNamespace(settings=object(), backend=object())
    request = SimpleNamespace(app=SimpleNamespace(state=state))
    assert get_settings(request) is state.settings and get_backend(request) is state.backend


def test_without_a_configured_key_everything_is_open():
    assert require_key(GatewaySettings(api_key=None), None) is None


@pytest.mark.parametrize(("given", "status"), [(None, 401), ("", 403), ("test-ke", 403),
                                               (API_KEY + "x", 403)])
def test_a_missing_key_is_401_a_wrong_one_403(given, status):
    with pytest.raises(HTTPException) as info:
        require_key(GatewaySettings(api_key=API_KEY), given)
    assert info.value.status_code == status and "X-API-Key" in info.value.detail
    if status == 401:
        assert info.value.headers == {"WWW-Authenticate": "X-API-Key"}


def test_the_right_key_passes():
    assert require_key(GatewaySettings(api_key=API_KEY), API_KEY) is None


@pytest.mark.parametrize("robot", ["r1", "robot_7", "a.b-c", "x" * 64])
def test_a_valid_robot_id_is_returned(robot):
    assert robot_id(robot) == robot


@pytest.mark.parametrize("robot", ["health", "stats"])
def test_a_reserved_robot_id_is_a_422_naming_it(robot):
    with pytest.raises(RequestValidationError) as info:
        robot_id(robot)
    (error,) = info.value.errors()
    assert error["loc"] == ("path", "robot") and repr(robot) in error["msg"]


def test_a_robot_id_outside_the_pattern_is_refused_before_any_route(client):
    r = client.get(f"/api/v1/robots/{'x' * 65}/pose")
    assert r.status_code == 422 and r.json()["detail"][0]["loc"] == ["path", "robot"]


def test_reserved_robot_id_is_refused(client):
    """As the schema says a 422 is: detail a list of errors, each with its loc (schemathesis
    found the bare string this was)."""
    r = client.get("/api/v1/robots/stats/pose")
    assert r.status_code == 422
    (error,) = r.json()["detail"]
    assert error["loc"] == ["path", "robot"] and "'stats' is reserved" in error["msg"]
