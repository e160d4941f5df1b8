"""Settings: every section reads its own SCANFLOW_<SECTION>_ variables; list parsing; defaults."""

from __future__ import annotations

import inspect
import math

import pytest
from pydantic import ValidationError
from pydantic_settings import BaseSettings
from scanflow import config
from scanflow.geometry import Pose2D


@pytest.fixture(autouse=True)
def clean_env(monkeypatch: pytest.MonkeyPatch) -> pytest.MonkeyPatch:
    import os

    for name in list(os.environ):
        if name.startswith("SCANFLOW_"):
            monkeypatch.delenv(name)
    return monkeypatch


def _sections() -> list[type[BaseSettings]]:
    """Every settings class the module defines that is used directly (bases are skipped)."""
    return [c for c in _classes() if c.model_config.get("env_prefix")]


def _classes() -> list[type[BaseSettings]]:
    return [
        c
        for _, c in inspect.getmembers(config, inspect.isclass)
        if issubclass(c, BaseSettings) and c.__module__ == config.__name__
    ]


def _bases() -> list[type[BaseSettings]]:
    """Settings classes without an env prefix: shared bases for the sections."""
    return [c for c in _classes() if not c.model_config.get("env_prefix")]


def test_every_section_has_its_own_scanflow_prefix() -> None:
    sections = _sections()
    assert config.ZenohSettings in sections
    prefixes = [c.model_config["env_prefix"] for c in sections]
    assert all(p.startswith("SCANFLOW_") and p.endswith("_") for p in prefixes), prefixes
    assert len(set(prefixes)) == len(prefixes), prefixes


def test_sections_lists_every_section() -> None:
    assert set(config.SECTIONS) == set(_sections())
    assert len(config.SECTIONS) == len(set(config.SECTIONS))


def _float_fields() -> list[tuple[type[BaseSettings], str]]:
    return [(c, name) for c in _sections() for name, f in c.model_fields.items()
            if f.annotation is float]


@pytest.mark.parametrize(("section", "field"), _float_fields(),
                         ids=lambda v: v if isinstance(v, str) else v.__name__)
@pytest.mark.parametrize("value", ["nan", "inf", "-inf"])
def test_no_number_setting_takes_nan_or_infinity(clean_env, section, field, value) -> None:
    """A NaN limit turns its check off without a word (score < nan is never true)."""
    name = f"{section.model_config['env_prefix']}{field}".upper()
    clean_env.setenv(name, value)
    with pytest.raises(config.SettingsError, match=f"{name}='{value}': Input should be a finite"):
        config.load_settings(section)


def test_load_settings_names_each_bad_variable_and_its_value(clean_env) -> None:
    clean_env.setenv("SCANFLOW_GATEWAY_PORT", "eighty")
    clean_env.setenv("SCANFLOW_GATEWAY_MAX_BEAMS", "0")
    clean_env.setenv("SCANFLOW_GATEWAY_HOST", "x" * 500)  # any text is a host: not an error
    with pytest.raises(config.SettingsError) as error:
        config.load_settings(config.GatewaySettings)
    message = str(error.value)
    assert "SCANFLOW_GATEWAY_PORT='eighty': Input should be a valid integer" in message
    assert "SCANFLOW_GATEWAY_MAX_BEAMS='0': Input should be greater than or equal to 1" in message
    assert isinstance(error.value, ValueError)


def test_a_long_bad_value_is_shortened_in_the_message(clean_env) -> None:
    clean_env.setenv("SCANFLOW_GATEWAY_PORT", "9" * 300)
    with pytest.raises(config.SettingsError) as error:
        config.load_settings(config.GatewaySettings)
    assert len(str(error.value)) < 200 and "..." in str(error.value)


def test_check_environment_names_the_bad_variables_of_every_section(clean_env) -> None:
    clean_env.setenv("SCANFLOW_ZENOH_MODE", "satellite")
    clean_env.setenv("SCANFLOW_BACKEND_OPTIMISE_EVERY", "0")
    config.check_environment(config.GatewaySettings)  # neither is its business
    with pytest.raises(config.SettingsError) as error:
        config.check_environment(*config.SECTIONS)
    assert "SCANFLOW_ZENOH_MODE='satellite'" in str(error.value)
    assert "SCANFLOW_BACKEND_OPTIMISE_EVERY='0'" in str(error.value)


@pytest.mark.parametrize("section", _sections(), ids=lambda c: c.__name__)
def test_every_section_builds_from_defaults(section: type[BaseSettings]) -> None:
    section()


def test_zenoh_defaults() -> None:
    s = config.ZenohSettings()
    assert (s.mode, s.connect, s.listen, s.prefix) == (
        "client",
        ["tcp/127.0.0.1:7447"],
        [],
        "scanflow",
    )


@pytest.mark.parametrize(
    ("raw", "expected"),
    [
        ("tcp/10.0.0.2:7447", ["tcp/10.0.0.2:7447"]),
        ("tcp/a:1, tcp/b:2 ,", ["tcp/a:1", "tcp/b:2"]),
        ('["tcp/a:1", "udp/b:2"]', ["tcp/a:1", "udp/b:2"]),
        ("", []),
    ],
)
def test_zenoh_lists_take_csv_or_json(clean_env, raw: str, expected: list[str]) -> None:
    clean_env.setenv("SCANFLOW_ZENOH_CONNECT", raw)
    clean_env.setenv("SCANFLOW_ZENOH_LISTEN", raw)
    s = config.ZenohSettings()
    assert s.connect == expected
    assert s.listen == expected


@pytest.mark.parametrize(
    ("name", "value", "field"),
    [
        ("SCANFLOW_ZENOH_MODE", "satellite", "mode"),
        ("SCANFLOW_ZENOH_CONNECT", "[not json", "connect"),
        ("SCANFLOW_ZENOH_MULTICAST_SCOUTING", "maybe", "multicast_scouting"),
    ],
)
def test_bad_values_name_the_field(clean_env, name: str, value: str, field: str) -> None:
    clean_env.setenv(name, value)
    with pytest.raises(ValidationError, match=field):
        config.ZenohSettings()


@pytest.mark.parametrize("section", _sections(), ids=lambda c: c.__name__)
def test_inherited_fields_read_only_the_sections_prefix(clean_env, section) -> None:
    """Fields from a prefix-less base class must not pick up bare variables like INSTANCE."""
    prefix = section.model_config["env_prefix"]
    bases = [b for b in section.__mro__[1:] if b in _bases()]
    inherited = {n for b in bases for n, i in b.model_fields.items() if i.annotation is str}
    for name in sorted(inherited):
        clean_env.setenv(name.upper(), "from-bare-variable")
        clean_env.setenv(f"{prefix}{name.upper()}", "from-section")
        assert getattr(section(), name) == "from-section"
        clean_env.delenv(f"{prefix}{name.upper()}")
        assert getattr(section(), name) != "from-bare-variable"


@pytest.mark.parametrize(
    "section", [c for c in _sections() if "cpus" in c.model_fields], ids=lambda c: c.__name__
)
def test_every_process_takes_its_cpus_as_csv_or_json(clean_env, section) -> None:
    name = f"{section.model_config['env_prefix']}CPUS"
    assert section().cpus == []
    clean_env.setenv(name, "1, 3")
    assert section().cpus == [1, 3]
    clean_env.setenv(name, "[0, 2]")
    assert section().cpus == [0, 2]
    clean_env.setenv(name, "one")
    with pytest.raises(ValidationError, match="cpus"):
        section()


@pytest.mark.parametrize("field", ["CPUS", "IO_CPUS"])
def test_a_negative_cpu_id_is_refused_when_settings_load(clean_env, field: str) -> None:
    """Named at start, not by a traceback from pinning the process ('negative CPU number')."""
    clean_env.setenv(f"SCANFLOW_DESKEW_{field}", "0,-1")
    with pytest.raises(config.SettingsError, match=f"SCANFLOW_DESKEW_{field}='-1'"):
        config.check_environment(config.DeskewSettings)


def test_launch_pins_one_matcher_by_default_and_refuses_a_negative_count(clean_env) -> None:
    assert config.LaunchSettings().matcher_cpus == 1
    clean_env.setenv("SCANFLOW_LAUNCH_MATCHER_CPUS", "-1")
    with pytest.raises(ValidationError, match="matcher_cpus"):
        config.LaunchSettings()


def test_ingest_mount_is_x_y_and_yaw_in_degrees(clean_env) -> None:
    assert config.IngestSettings().mount_pose() is None
    clean_env.setenv("SCANFLOW_INGEST_MOUNT", "0.3,-0.1,90")
    assert config.IngestSettings().mount_pose() == Pose2D(0.3, -0.1, math.pi / 2)
    for bad in ("0.3,-0.1", "1,2,nan", "[1, 2, 3, 4]", "250,0,0"):
        clean_env.setenv("SCANFLOW_INGEST_MOUNT", bad)
        with pytest.raises(ValidationError, match="mount"):
            config.IngestSettings()


def test_an_ingest_log_that_is_not_there_is_refused_when_settings_load(clean_env, tmp_path) -> None:
    """Named at start-up, not by a traceback from the first read (and, under compose's
    restart: on-failure, again at every restart)."""
    missing = tmp_path / "nope.log.gz"
    clean_env.setenv("SCANFLOW_INGEST_LOG", str(missing))
    with pytest.raises(config.SettingsError, match=f"SCANFLOW_INGEST_LOG.*no log at '{missing}'"):
        config.check_environment(config.IngestSettings)
    missing.write_text("")
    assert config.IngestSettings().log == str(missing)


def test_an_empty_ingest_log_or_a_directory_that_is_no_bag_is_refused(clean_env, tmp_path) -> None:
    """'' named the current directory, and any directory passed as a log: both were taken,
    and ingest failed on its first read; a ROS 2 bag's directory is still a log."""
    for bad in ("", str(tmp_path)):
        clean_env.setenv("SCANFLOW_INGEST_LOG", bad)
        with pytest.raises(config.SettingsError, match=r"SCANFLOW_INGEST_LOG='.*no log at"):
            config.check_environment(config.IngestSettings)
    (tmp_path / "metadata.yaml").write_text("")
    assert config.IngestSettings().log == str(tmp_path)


def test_frontend_initial_pose_is_x_y_and_yaw_in_degrees_or_unknown(clean_env) -> None:
    assert config.FrontendSettings().start_pose() is None
    clean_env.setenv("SCANFLOW_FRONTEND_INITIAL_POSE", "1.5,-2,180")
    assert config.FrontendSettings().start_pose() == Pose2D(1.5, -2.0, math.pi)
    for bad in ("1,2", "1,2,inf"):
        clean_env.setenv("SCANFLOW_FRONTEND_INITIAL_POSE", bad)
        with pytest.raises(ValidationError, match="initial_pose"):
            config.FrontendSettings()


def test_backend_settings_read_the_environment_and_name_bad_values(clean_env) -> None:
    assert config.BackendSettings().loop_closure is False
    clean_env.setenv("SCANFLOW_BACKEND_LOOP_CLOSURE", "true")
    clean_env.setenv("SCANFLOW_BACKEND_SEARCH_RADIUS_M", "8")
    clean_env.setenv("SCANFLOW_BACKEND_CONFIRM_KEYFRAMES", "0")
    assert config.BackendSettings().cull_m == 0.0  # culling is opt-in
    clean_env.setenv("SCANFLOW_BACKEND_CULL_M", "0.3")
    settings = config.BackendSettings()
    assert settings.loop_closure and settings.search_radius_m == 8.0
    assert settings.confirm_keyframes == 0 and settings.cull_m == 0.3
    for name, bad in (("AMBIGUITY_RATIO", "1.5"), ("LOOP_MIN_STD_M", "0"),
                      ("OPTIMISE_EVERY", "0"), ("CULL_M", "-0.1"), ("CULL_DEG", "0")):
        clean_env.setenv(f"SCANFLOW_BACKEND_{name}", bad)
        with pytest.raises(ValidationError, match=name.lower()):
            config.BackendSettings()
        clean_env.delenv(f"SCANFLOW_BACKEND_{name}")


def test_the_ingest_simulator_offers_every_built_in_world() -> None:
    """The setting's choices are the simulator's worlds (config stays free of the sim's imports,
    so the list is written out there)."""
    from typing import get_args

    from scanflow.sim import WORLDS

    choices = get_args(config.IngestSettings.model_fields["sim_world"].annotation)
    assert sorted(choices) == sorted(WORLDS)


def test_the_method_settings_offer_every_matching_method() -> None:
    """The written-out list is `scanflow.matching`'s registry (config stays free of its imports)."""
    from typing import get_args

    from scanflow.matching import available_methods

    assert sorted(get_args(config.MatchMethod)) == available_methods()


def test_a_misspelt_method_is_refused_when_settings_load(monkeypatch) -> None:
    """Named at start-up, not by the first scan the front end matches (or the first fallback,
    or the first loop closure)."""
    monkeypatch.setenv("SCANFLOW_FRONTEND_METHOD", "gn_plicp")
    monkeypatch.setenv("SCANFLOW_FRONTEND_FALLBACK_METHOD", "cms")
    monkeypatch.setenv("SCANFLOW_BACKEND_METHOD", "nd")
    with pytest.raises(config.SettingsError) as error:
        config.check_environment(config.FrontendSettings, config.BackendSettings)
    for name in ("FRONTEND_METHOD='gn_plicp'", "FALLBACK_METHOD='cms'", "BACKEND_METHOD='nd'"):
        assert name in str(error.value)
    monkeypatch.setenv("SCANFLOW_FRONTEND_FALLBACK_METHOD", "")
    monkeypatch.setenv("SCANFLOW_FRONTEND_METHOD", "gn+plicp")
    monkeypatch.setenv("SCANFLOW_BACKEND_METHOD", "ndt")
    loaded = config.check_environment(config.FrontendSettings, config.BackendSettings)
    assert loaded[config.FrontendSettings].fallback_method == ""


def test_a_negative_simulator_seed_is_refused_when_settings_load(monkeypatch) -> None:
    """numpy takes no negative seed: named at start-up, not by the first simulated frame."""
    monkeypatch.setenv("SCANFLOW_INGEST_SIM_SEED", "-1")
    with pytest.raises(config.SettingsError, match="SCANFLOW_INGEST_SIM_SEED='-1'"):
        config.check_environment(config.IngestSettings)


def test_a_simulator_run_longer_than_the_simulator_lays_out_is_refused_when_settings_load(
    monkeypatch,
) -> None:
    """The simulator's tour is built in advance (an hour at most): named at start-up, not a
    MemoryError in ingest."""
    monkeypatch.setenv("SCANFLOW_INGEST_SIM_DURATION_S", "86400")
    with pytest.raises(config.SettingsError, match="SCANFLOW_INGEST_SIM_DURATION_S='86400'"):
        config.check_environment(config.IngestSettings)
