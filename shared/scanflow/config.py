"""Typed configuration for every part of scanflow: the one place for settings.

Each section is a pydantic-settings class reading environment variables with its own prefix,
e.g. ``SCANFLOW_ZENOH_CONNECT=tcp/10.0.0.2:7447`` or ``SCANFLOW_GATEWAY_PORT=9000``. Lists take
JSON or comma-separated values. Services build their settings once at start-up and pass them
down explicitly; the core library takes plain arguments and never reads the environment.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Annotated, Literal, TypeVar

from pydantic import Field, SecretStr, ValidationError, field_validator
from pydantic_settings import BaseSettings, NoDecode, SettingsConfigDict

from scanflow.geometry import Pose2D
from scanflow.scan import MAX_MOUNT_M
from scanflow.sim.run import MAX_DURATION_S as MAX_SIM_DURATION_S


def _split_csv(value: object) -> object:
    if isinstance(value, str):
        value = value.strip()
        if value.startswith("["):
            import json

            return json.loads(value)
        return [v.strip() for v in value.split(",") if v.strip()]
    return value


MAX_GLOBAL_LEVEL = 4  # the whole-map search's coarsest map pyramid level


class SettingsError(ValueError):
    """Environment values a settings section cannot take; the message names each variable."""


class Section(BaseSettings):
    """A settings section: its variables share a prefix; NaN and infinities are refused (a NaN
    limit would turn its check off without a word)."""

    model_config = SettingsConfigDict(extra="ignore", allow_inf_nan=False)


S = TypeVar("S", bound=Section)


def load_settings(section: type[S]) -> S:
    """`section` read from the environment; `SettingsError` names every bad variable."""
    try:
        return section()
    except ValidationError as error:
        prefix = str(section.model_config.get("env_prefix", ""))
        raise SettingsError("; ".join(
            f"{prefix}{'_'.join(str(p) for p in e['loc'][:1])}".upper()
            + f"={_shown(e.get('input'))}: {e['msg']}"
            for e in error.errors()
        )) from None


def check_environment(*sections: type[Section]) -> dict[type[Section], Section]:
    """Each section read from the environment, by class; `SettingsError` names every bad
    variable of all of them (a deployment checked before anything starts)."""
    loaded: dict[type[Section], Section] = {}
    errors = []
    for section in sections:
        try:
            loaded[section] = load_settings(section)
        except SettingsError as error:
            errors.append(str(error))
    if errors:
        raise SettingsError("; ".join(errors))
    return loaded


def _shown(value: object) -> str:
    """An offending value as the error shows it: at most 40 characters (no secret setting can
    be invalid: any text is one)."""
    text = repr(value) if isinstance(value, str) else str(value)
    return text if len(text) <= 40 else text[:37] + "..."


def _check_pose(value: list[float]) -> list[float]:
    """A pose setting: empty (unset) or 'x_m,y_m,yaw_deg', all finite."""
    if value and (len(value) != 3 or not all(math.isfinite(v) for v in value)):
        raise ValueError(f"must be 3 finite numbers 'x_m,y_m,yaw_deg', got {value!r}")
    return value


def _check_mount(value: list[float]) -> list[float]:
    """A mount setting: a pose setting within +-MAX_MOUNT_M of the robot's origin (a scan
    would refuse one farther)."""
    if _check_pose(value) and max(abs(value[0]), abs(value[1])) > MAX_MOUNT_M:
        raise ValueError(f"must lie within +-{MAX_MOUNT_M:g} m of the robot, got {value!r}")
    return value


def _check_log(value: str | None) -> str | None:
    """A log setting: unset, or a file, or a ROS 2 bag's directory (empty is no path: it
    would name the current directory)."""
    if value is not None and not (value and (Path(value).is_file()
                                             or (Path(value) / "metadata.yaml").is_file())):
        raise ValueError(f"no log at {value!r} (a file, or a ROS 2 bag's directory)")
    return value


def _pose_of(value: list[float]) -> Pose2D | None:
    """A checked pose setting as a pose (yaw in radians), None when unset."""
    if not value:
        return None
    x, y, yaw_deg = value
    return Pose2D(x, y, math.radians(yaw_deg))


class ZenohSettings(Section):
    """How a process joins the Zenoh network (SCANFLOW_ZENOH_*)."""

    model_config = SettingsConfigDict(env_prefix="SCANFLOW_ZENOH_")

    mode: Literal["client", "peer", "router"] = Field(
        "client", description="Zenoh session mode; services are clients of a router"
    )
    connect: Annotated[list[str], NoDecode] = Field(
        default_factory=lambda: ["tcp/127.0.0.1:7447"], description="Zenoh endpoints to connect to"
    )
    listen: Annotated[list[str], NoDecode] = Field(
        default_factory=list, description="Zenoh endpoints to listen on (peer or router mode)"
    )
    prefix: str = Field(
        "scanflow", description="first segment of every key: deployments sharing a router "
        "with different prefixes do not see each other"
    )
    multicast_scouting: bool = Field(
        False, description="also find routers and peers by UDP multicast (off: `connect` only)"
    )
    block_close_s: float = Field(
        60.0, gt=0.0, description="a link whose reader holds a reliable message back this long "
        "is closed, and what it held is lost (a service whose worker stalls; Zenoh's own "
        "default is 5 s)",
    )

    _split = field_validator("connect", "listen", mode="before")(_split_csv)


class ProcessSettings(Section):
    """Fields of every scanflow process: log level and the CPUs it may run on."""

    log_level: Literal["DEBUG", "INFO", "WARNING", "ERROR"] = Field(
        "INFO", description="the process's log level (logs go to stderr)"
    )
    cpus: Annotated[list[Annotated[int, Field(ge=0)]], NoDecode] = Field(
        default_factory=list, description="CPU ids the process runs on (Linux); empty = any"
    )
    io_cpus: Annotated[list[Annotated[int, Field(ge=0)]], NoDecode] = Field(
        default_factory=list,
        description="CPU ids for the Zenoh runtime's own threads (network I/O, routing), "
        "away from a CPU-bound worker's; empty = the process's CPUs",
    )

    _split_cpus = field_validator("cpus", "io_cpus", mode="before")(_split_csv)


class ServiceSettings(ProcessSettings):
    """Fields every service process shares; each service subclass sets its env prefix."""

    instance: str = Field(
        "0", description="tells two instances of one service apart in health and stats keys"
    )
    queue_size: int = Field(
        256, ge=1, description="bounded inbox between Zenoh and the worker (> 3 x ingest window)"
    )
    slow_message_s: float = Field(
        1.0, gt=0.0, description="a message handled for longer is logged and counted as slow"
    )
    inbox_drain_s: float = Field(
        5.0, ge=0.0, description="on a clean stop, the worker handles what its inbox holds "
        "and what still arrives until 0.25 s pass without any, for at most this long (what is "
        "left is counted as inbox.dropped_at_stop)",
    )
    max_robots: int = Field(
        100, ge=1, description="robots this service keeps state for; messages naming more are "
        "dropped (counted as robots_refused, each id logged once)",
    )


class KernelServiceSettings(ServiceSettings):
    """A service that runs the compiled kernels on every scan (deskew, matcher, map server)."""

    warm_up: bool = Field(
        True, description="run the compiled kernels once before announcing health (~1 s)"
    )


class RouterSettings(ServiceSettings):
    """The Zenoh router process (SCANFLOW_ROUTER_*): where it listens, which routers it joins."""

    model_config = SettingsConfigDict(env_prefix="SCANFLOW_ROUTER_")

    listen: Annotated[list[str], NoDecode] = Field(
        default_factory=lambda: ["tcp/0.0.0.0:7447"], description="endpoints the router listens on"
    )
    connect: Annotated[list[str], NoDecode] = Field(
        default_factory=list, description="other routers to join (a multi-host deployment)"
    )

    _split = field_validator("connect", "listen", mode="before")(_split_csv)


class LaunchSettings(Section):
    """A local launch of the services: `scanflow up`, tests, benchmarks (SCANFLOW_LAUNCH_*)."""

    model_config = SettingsConfigDict(env_prefix="SCANFLOW_LAUNCH_")

    matcher_cpus: int = Field(
        1,
        ge=0,
        description="matchers given a CPU of their own (one each, at least one CPU left for "
        "the rest); 0 = no pinning; a service's own SCANFLOW_<SERVICE>_CPUS wins",
    )


class IngestSettings(ServiceSettings):
    """The ingest service (SCANFLOW_INGEST_*): source, pacing and backpressure window."""

    model_config = SettingsConfigDict(env_prefix="SCANFLOW_INGEST_")

    log: str | None = Field(None, description="CARMEN log (.log/.gz) or ROS bag; unset = simulator")
    robot_id: str = Field("robot", description="the robot id the source's scans are published as")
    rate: float = Field(1.0, ge=0.0, description="multiple of real time; 0 = as fast as possible")
    limit: int | None = Field(None, ge=1, description="publish at most this many scans")
    window: int = Field(32, ge=0, description="scans in flight before waiting for poses; 0 = off")
    replays: int = Field(1, ge=1, description="publish the source this many times in a row")
    sim_duration_s: float = Field(
        60.0, gt=0.0, le=MAX_SIM_DURATION_S, description="the simulator's run length (longer: "
        "replays)"
    )
    sim_seed: int = Field(0, ge=0, description="the simulator's seed (runs are reproducible)")
    sim_world: Literal["rooms", "corridor", "loop", "campus"] = Field(
        "rooms", description="the simulator's world (loop: a ring corridor to close a loop in; "
        "campus: outdoors, buildings 15-70 m away)"
    )
    sim_odom_scale_error: float = Field(
        0.01, ge=0.0, lt=0.5, description="the simulator's wheel odometry scale error"
    )
    sim_odom_yaw_noise: float = Field(
        0.002, ge=0.0, lt=0.5, description="the simulator's wheel odometry heading drift: a "
        "yaw-rate bias random-walking by this many rad/s per sqrt(s)"
    )
    mount: Annotated[list[float], NoDecode] = Field(
        default_factory=list,
        description="the lidar's pose on the robot, 'x_m,y_m,yaw_deg' (T_base_laser; x and y "
        f"within +-{MAX_MOUNT_M:g} m): set on every scan, over what the source says; the "
        "simulator mounts its lidar there; empty = as the source says",
    )
    stall_timeout_s: float = Field(10.0, gt=0.0, description="no pose for this long: resume")
    wait_subscribers_s: float = Field(60.0, ge=0.0, description="wait for a scan subscriber")
    drain_timeout_s: float = Field(60.0, ge=0.0, description="wait for the last pose at the end")

    _split = field_validator("mount", mode="before")(_split_csv)
    _check_mount = field_validator("mount")(_check_mount)
    _check_log = field_validator("log")(_check_log)

    def mount_pose(self) -> Pose2D | None:
        """`mount` as a pose (yaw in radians), None when unset."""
        return _pose_of(self.mount)


class DeskewSettings(KernelServiceSettings):
    """The deskew service (SCANFLOW_DESKEW_*): how long a scan may wait for odometry."""

    model_config = SettingsConfigDict(env_prefix="SCANFLOW_DESKEW_")

    odom_wait_s: float = Field(0.05, ge=0.0, description="latency budget for covering odometry")


class MatcherSettings(KernelServiceSettings):
    """The matcher service (SCANFLOW_MATCHER_*): which robots this instance tracks."""

    model_config = SettingsConfigDict(env_prefix="SCANFLOW_MATCHER_")

    shard: str = Field("0/1", description="'i/n': track robots whose id hashes to i of n")
    robots: Annotated[list[str], NoDecode] = Field(
        default_factory=list, description="track only these robots (empty = by shard)"
    )
    resend_inserts: int = Field(
        256, ge=0, description="per robot, keep the last this many map inserts to send again "
        "to a map server that missed them (about 10 kB each)",
    )
    resume_timeout_s: float = Field(
        30.0, gt=0.0, description="how long a robot seen mid-stream waits for the map server's "
        "map, path and keyframes (a long run's keyframes are hundreds of MB), and, while no map "
        "server answers at all, how long its scans are dropped before it starts afresh",
    )

    _split = field_validator("robots", mode="before")(_split_csv)

    @field_validator("shard")
    @classmethod
    def _check_shard(cls, value: str) -> str:
        index, _, count = value.partition("/")
        if not (index.isdigit() and count.isdigit() and 0 <= int(index) < int(count)):
            raise ValueError(f"shard must be 'i/n' with 0 <= i < n, got {value!r}")
        return value


class MapServerSettings(KernelServiceSettings):
    """The map server (SCANFLOW_MAPSERVER_*): snapshot directory and notice rate."""

    model_config = SettingsConfigDict(env_prefix="SCANFLOW_MAPSERVER_")

    data_dir: str = Field(
        "scanflow-data", description="snapshots of every robot's map, path and keyframes; a "
        "restart resumes from them"
    )
    snapshot_interval_s: float = Field(
        10.0, gt=0.0, description="snapshot a robot this often while its map changes"
    )
    changed_rate_hz: float = Field(2.0, gt=0.0, description="at most this many change notices/s")
    resend_timeout_s: float = Field(
        2.0, gt=0.0, description="wait this long for a matcher to send missed inserts again"
    )
    keyframes_per_file: int = Field(
        256, ge=1, description="with loop closure, snapshots keep the keyframes' scans this "
        "many to a file, each file written once (~1.4 MB at 360 beams)",
    )


class GatewaySettings(ProcessSettings):
    """The HTTP gateway (SCANFLOW_GATEWAY_*): bind address, API key, request limits, cache size."""

    model_config = SettingsConfigDict(env_prefix="SCANFLOW_GATEWAY_")

    host: str = Field("127.0.0.1", description="HTTP bind address (0.0.0.0 in containers)")
    port: int = Field(8000, ge=1, le=65535, description="HTTP port")
    api_key: SecretStr | None = Field(
        None, description="X-API-Key required by ingest, match, setting a pose and retiring a "
        "robot (unset: those are open)"
    )
    guard_reads: bool = Field(False, description="require the API key on read endpoints too "
                              "(not on /api/v1/health; the live page then shows nothing)")
    max_body_bytes: int = Field(4 * 1024 * 1024, ge=1024, description="bigger bodies get 413")
    max_beams: int = Field(8192, ge=1, le=100_000, description="beams per scan in a request")
    query_timeout_s: float = Field(5.0, gt=0.0, le=120.0, description="Zenoh query deadline")
    trajectory_cache_len: int = Field(20_000, ge=2, description="poses kept per robot")
    stream_queue_len: int = Field(256, ge=1, description="events buffered per stream client")
    max_robots: int = Field(
        100, ge=1, description="robots whose poses the gateway caches; poses of more are "
        "dropped (scanflow_gateway_robots_refused_total, each id logged once)",
    )


# `scanflow.matching`'s methods, written out so that a misspelt one is refused when settings
# load, not at the first scan (config stays free of the matchers' imports; a test keeps this
# list equal to `available_methods()`).
MatchMethod = Literal[
    "csm", "csm+plicp", "csm_exhaustive", "global", "gn", "gn+plicp", "icp", "lm", "ndt",
    "plicp", "svd",
]


class FrontendSettings(Section):
    """The scan-to-map tracking front end (SCANFLOW_FRONTEND_*): method, checks, motion filter.

    Read from the environment only when a service or the CLI constructs it; library code gets
    an instance passed in (see `scanflow.frontend`).
    """

    model_config = SettingsConfigDict(env_prefix="SCANFLOW_FRONTEND_")

    method: MatchMethod = Field(
        "gn",
        description="scan-to-map method (scanflow.matching name); 'gn+plicp' drifts far less "
        "but is less robust on sparse long-range scans (docs/frontend.md)",
    )
    fallback_method: Literal[MatchMethod, ""] = Field(
        "csm", description="global-window search that seeds `method` when it fails; '' = none"
    )
    fallback_linear_m: float = Field(
        1.0, gt=0.0, description="fallback search half-width (widened, see fallback_max_linear_m)"
    )
    fallback_angular_deg: float = Field(30.0, gt=0.0, description="fallback search half-angle")
    fallback_max_linear_m: float = Field(
        5.0, gt=0.0, le=50.0, description="the fallback search and the correction it may make "
        "widen to 3 std of the prediction's uncertainty (scans rejected in a row) up to this "
        "half-width; the first scan of a run carried on across a gap searches all of it",
    )
    fallback_max_angular_deg: float = Field(
        180.0, gt=0.0, le=180.0, description="same, half-angle"
    )
    recheck_ratio: float = Field(
        0.8, ge=0.0, le=1.0,
        description="a passing match scoring below this x the median of the last 20 accepted "
        "is searched again like a failed one (0 = never; needs fallback_method)",
    )
    recheck_margin: float = Field(
        0.1, ge=0.0, description="the searched pose replaces that match only when it scores "
        "this much higher",
    )
    map_resolution_m: float = Field(
        0.05, ge=0.001, le=100.0, description="the tracking map's cell size"
    )
    no_return_clear_m: float = Field(
        5.0, ge=0.0, description="beams with no return clear free space this far (0 = not at all)"
    )
    min_points: int = Field(30, ge=3, description="fewer valid points: scan rejected")
    max_correction_m: float = Field(
        1.0, gt=0.0, description="largest accepted |match - prediction| translation (a "
        "fallback search's match: as far as its window reached)"
    )
    max_correction_deg: float = Field(30.0, gt=0.0, description="same, heading")
    min_score: float = Field(0.2, description="lowest accepted match score")
    max_position_std_m: float = Field(0.5, gt=0.0, description="largest accepted sqrt(var x/y)")
    max_heading_std_deg: float = Field(10.0, gt=0.0, description="largest accepted heading std")
    accept_degenerate: bool = Field(
        True, description="accept matches constrained in two directions only (corridors)"
    )
    max_odom_step_m: float = Field(3.0, gt=0.0, description="larger odometry steps are jumps")
    max_odom_step_deg: float = Field(120.0, gt=0.0, description="same, heading")
    max_odom_speed_mps: float = Field(
        5.0, gt=0.0, description="after a longer gap, odometry steps faster than this are jumps"
    )
    max_odom_turn_rate_deg_s: float = Field(
        180.0, gt=0.0, description="same, heading (degrees per second)"
    )
    cv_horizon_s: float = Field(
        1.0, gt=0.0, description="constant-velocity prediction reach without odometry"
    )
    odom_noise_m_per_m: float = Field(
        0.1, ge=0.0, description="prediction std growth per metre travelled (unmatched scans)"
    )
    odom_noise_rad_per_rad: float = Field(0.1, ge=0.0, description="same, heading per turn")
    prediction_floor_std_m: float = Field(
        0.05, ge=0.0, description="smallest position std of a prediction"
    )
    prediction_floor_std_deg: float = Field(
        2.0, ge=0.0, description="smallest heading std of a prediction"
    )
    insert_min_distance_m: float = Field(0.2, ge=0.0, description="motion filter: distance")
    insert_min_angle_deg: float = Field(10.0, ge=0.0, description="motion filter: heading")
    insert_max_interval_s: float = Field(
        5.0, gt=0.0, description="motion filter: insert anyway after this long"
    )
    prior_map: str = Field(
        "", description="localise on this map (.npz, or a map_server .yaml); '' = map from scratch"
    )
    initial_pose: Annotated[list[float], NoDecode] = Field(
        default_factory=list,
        description="the robot's start, 'x_m,y_m,yaw_deg' in the map frame; empty = unknown: "
        "searched over the whole prior map (the map's origin without one)",
    )
    update_map: bool = Field(
        True, description="insert accepted scans; false = localise only (needs a prior map)"
    )
    global_level: int = Field(
        1, ge=0, le=MAX_GLOBAL_LEVEL,
        description="map pyramid level of the whole-map search (cells x 2**level); a map too "
        "large for it is searched at the next coarser level that fits",
    )
    global_after_rejections: int = Field(
        3, ge=0, description="search the whole map after every this many rejected scans in a "
        "row (a kidnapped or lost robot); 0 = never"
    )

    _split = field_validator("initial_pose", mode="before")(_split_csv)
    _check_initial_pose = field_validator("initial_pose")(_check_pose)

    def start_pose(self) -> Pose2D | None:
        """`initial_pose` as a pose (yaw in radians), None when unknown."""
        return _pose_of(self.initial_pose)


class BackendSettings(Section):
    """Loop closure and pose-graph optimisation (SCANFLOW_BACKEND_*): `scanflow.backend`."""

    model_config = SettingsConfigDict(env_prefix="SCANFLOW_BACKEND_")

    loop_closure: bool = Field(
        False, description="close loops and optimise the keyframes' pose graph"
    )
    search_radius_m: float = Field(
        5.0, gt=0.0, description="earlier keyframes this near (by the estimates) are candidates"
    )
    min_travel_m: float = Field(
        10.0, gt=0.0, description="a candidate lies at least this far back along the path"
    )
    max_candidates: int = Field(2, ge=1, description="candidates searched per keyframe")
    submap_half_nodes: int = Field(
        5, ge=0, description="a candidate's submap: keyframes j-w .. j+w"
    )
    linear_m: float = Field(1.0, gt=0.0, description="search window half-width around the guess")
    angular_deg: float = Field(20.0, gt=0.0, description="search window half-angle")
    method: MatchMethod = Field("gn", description="refines the search's best pose on the submap")
    min_score: float = Field(0.5, description="lowest refined match score kept as a closure")
    max_position_std_m: float = Field(0.1, gt=0.0, description="largest sqrt(var x/y) kept")
    max_heading_std_deg: float = Field(2.0, gt=0.0, description="largest heading std kept")
    ambiguity_ratio: float = Field(
        0.9, gt=0.0, le=1.0, description="a distinct rival scoring this x the best: no closure"
    )
    rival_distance_m: float = Field(
        0.5, gt=0.0, le=1000.0, description="rivals lie this far from the best"
    )
    rival_angle_deg: float = Field(10.0, gt=0.0, le=360.0, description="or this far in heading")
    confirm_keyframes: int = Field(
        3, ge=0, description="a closure waits this many keyframes for another that implies the "
        "same correction before it enters the graph; 0 = every closure enters at once"
    )
    busy_search_every: int = Field(
        1, ge=1, description="while closures keep entering the graph (one entered within the "
        "last confirm_keyframes keyframes), search for closures at every n-th keyframe only; "
        "1 = at every keyframe"
    )
    confirm_m: float = Field(0.05, gt=0.0, description="two corrections agree within this")
    confirm_deg: float = Field(0.5, gt=0.0, description="and this")
    cull_m: float = Field(
        0.0, ge=0.0, description="an insert the front end tracked within this of a keyframe "
        "already drawn is not made a keyframe but hangs from that one: a parked robot, or one "
        "going over mapped ground, adds no keyframes; 0 = every insert is a keyframe"
    )
    cull_deg: float = Field(10.0, gt=0.0, description="and within this heading of it")
    keyframe_std_m: float = Field(
        0.02, gt=0.0, description="std of the front end's motion between keyframes, fixed part"
    )
    keyframe_std_per_m: float = Field(0.02, ge=0.0, description="and per metre moved")
    keyframe_std_deg: float = Field(0.3, gt=0.0, description="heading std, fixed part")
    keyframe_std_deg_per_deg: float = Field(0.02, ge=0.0, description="and per degree turned")
    loop_min_std_m: float = Field(0.03, gt=0.0, description="floor of a closure's position std")
    loop_min_std_deg: float = Field(0.5, gt=0.0, description="floor of its heading std")
    robust_scale: float = Field(
        2.0, gt=0.0, description="Cauchy kernel scale on closures, in standard deviations"
    )
    optimise_every: int = Field(
        10, ge=1, description="optimise after this many keyframes when a closure came meanwhile"
    )
    redraw_shift_m: float = Field(
        0.2, gt=0.0, description="redraw the tracking map when optimising moves a keyframe "
        "this far against it"
    )
    redraw_shift_deg: float = Field(2.0, gt=0.0, description="or turns one this much")
    relocated_std_m: float = Field(
        100.0, gt=0.0, description="std of the link across an operator's pose (unmeasured)"
    )
    relocated_std_deg: float = Field(90.0, gt=0.0, description="and its heading std")


# Every section, in the order a deployment meets them (docs/settings.md follows it).
SECTIONS: tuple[type[Section], ...] = (
    ZenohSettings,
    RouterSettings,
    IngestSettings,
    DeskewSettings,
    MatcherSettings,
    MapServerSettings,
    GatewaySettings,
    FrontendSettings,
    BackendSettings,
    LaunchSettings,
)
