"""Typed configuration for every part of scanflow: the one place for settings.

Each section is a pydantic-settings class reading environment variables with its own prefix,
e.g. ``SCANFLOW_ZENOH_CONNECT=tcp/10.0.0.2:7447`` or ``SCANFLOW_GATEWAY_PORT=9000``. Lists take
JSON or comma-separated values. Services build their settings once at start-up and pass them
down explicitly; the core library takes plain arguments and never reads the environment.
"""

from __future__ import annotations

from typing import Annotated, Literal

from pydantic import Field, field_validator
from pydantic_settings import BaseSettings, NoDecode, SettingsConfigDict


def _split_csv(value: object) -> object:
    if isinstance(value, str):
        value = value.strip()
        if value.startswith("["):
            import json

            return json.loads(value)
        return [v.strip() for v in value.split(",") if v.strip()]
    return value


class ZenohSettings(BaseSettings):
    """How a process joins the Zenoh network (SCANFLOW_ZENOH_*)."""

    model_config = SettingsConfigDict(env_prefix="SCANFLOW_ZENOH_", extra="ignore")

    mode: Literal["client", "peer", "router"] = "client"
    connect: Annotated[list[str], NoDecode] = Field(default_factory=lambda: ["tcp/127.0.0.1:7447"])
    listen: Annotated[list[str], NoDecode] = Field(default_factory=list)
    prefix: str = "scanflow"
    multicast_scouting: bool = False

    _split = field_validator("connect", "listen", mode="before")(_split_csv)
