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


class ServiceSettings(BaseSettings):
    """Fields every service process shares; each service subclass sets its env prefix."""

    model_config = SettingsConfigDict(extra="ignore")

    instance: str = "0"
    queue_size: int = Field(64, ge=1, description="bounded inbox between Zenoh and the worker")
    log_level: Literal["DEBUG", "INFO", "WARNING", "ERROR"] = "INFO"


class RouterSettings(ServiceSettings):
    """The Zenoh router process (SCANFLOW_ROUTER_*): where it listens, which routers it joins."""

    model_config = SettingsConfigDict(env_prefix="SCANFLOW_ROUTER_", extra="ignore")

    listen: Annotated[list[str], NoDecode] = Field(default_factory=lambda: ["tcp/0.0.0.0:7447"])
    connect: Annotated[list[str], NoDecode] = Field(default_factory=list)

    _split = field_validator("connect", "listen", mode="before")(_split_csv)


class IngestSettings(ServiceSettings):
    """The ingest service (SCANFLOW_INGEST_*): source, pacing and backpressure window."""

    model_config = SettingsConfigDict(env_prefix="SCANFLOW_INGEST_", extra="ignore")

    log: str | None = Field(None, description="CARMEN log (.log/.gz) or ROS bag; None = simulator")
    robot_id: str = "robot"
    rate: float = Field(1.0, ge=0.0, description="multiple of real time; 0 = as fast as possible")
    limit: int | None = Field(None, ge=1, description="publish at most this many scans")
    window: int = Field(32, ge=0, description="scans in flight before waiting for poses; 0 = off")
    replays: int = Field(1, ge=1, description="publish the source this many times in a row")
    sim_duration_s: float = Field(60.0, gt=0.0)
    sim_seed: int = 0
    stall_timeout_s: float = Field(10.0, gt=0.0, description="no pose for this long: resume")
    drain_timeout_s: float = Field(60.0, ge=0.0, description="wait for the last pose at the end")


class DeskewSettings(ServiceSettings):
    """The deskew service (SCANFLOW_DESKEW_*): how long a scan may wait for odometry."""

    model_config = SettingsConfigDict(env_prefix="SCANFLOW_DESKEW_", extra="ignore")

    odom_wait_s: float = Field(0.05, ge=0.0, description="latency budget for covering odometry")


class MatcherSettings(ServiceSettings):
    """The matcher service (SCANFLOW_MATCHER_*): which robots this instance tracks."""

    model_config = SettingsConfigDict(env_prefix="SCANFLOW_MATCHER_", extra="ignore")

    shard: str = Field("0/1", description="'i/n': track robots whose id hashes to i of n")
    robots: Annotated[list[str], NoDecode] = Field(
        default_factory=list, description="track only these robots (empty = by shard)"
    )

    _split = field_validator("robots", mode="before")(_split_csv)

    @field_validator("shard")
    @classmethod
    def _check_shard(cls, value: str) -> str:
        index, _, count = value.partition("/")
        if not (index.isdigit() and count.isdigit() and 0 <= int(index) < int(count)):
            raise ValueError(f"shard must be 'i/n' with 0 <= i < n, got {value!r}")
        return value


class MapServerSettings(ServiceSettings):
    """The map server (SCANFLOW_MAPSERVER_*): snapshot directory and notice rate."""

    model_config = SettingsConfigDict(env_prefix="SCANFLOW_MAPSERVER_", extra="ignore")

    data_dir: str = "scanflow-data"
    snapshot_interval_s: float = Field(10.0, gt=0.0)
    changed_rate_hz: float = Field(2.0, gt=0.0, description="at most this many change notices/s")
    pending_limit: int = Field(2000, ge=1, description="scans held while waiting for their pose")
