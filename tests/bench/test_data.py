"""bench.data: real logs in $SCANFLOW_DATA_DIR, else in shared/data beside the checkout."""

from __future__ import annotations

import importlib.util
from pathlib import Path
from types import ModuleType

import pytest

import bench.data


def fresh_data_module() -> ModuleType:
    """A new copy of bench.data, reading the environment as it is now (bench.data stays as is)."""
    spec = importlib.util.spec_from_file_location("bench_data_copy", bench.data.__file__)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_without_the_variable_the_logs_are_in_shared_data_beside_the_checkout(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.delenv("SCANFLOW_DATA_DIR", raising=False)
    data = fresh_data_module()
    checkout = Path(data.__file__).resolve().parents[1]  # the folder bench/ is in
    assert data.DATA_DIR.resolve() == (checkout.parent / "shared" / "data").resolve()
    assert data.corrected_log("intel") == data.DATA_DIR / "intel-corrected.log.gz"


def test_the_variable_names_the_data_directory(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    monkeypatch.setenv("SCANFLOW_DATA_DIR", str(tmp_path))
    data = fresh_data_module()
    assert tmp_path == data.DATA_DIR
    assert data.corrected_log("freiburg-079") == tmp_path / "freiburg-079-corrected.log.gz"


@pytest.mark.skipif(not bench.data.DATA_DIR.is_dir(),
                    reason=f"data directory {bench.data.DATA_DIR} not available")
def test_the_three_named_logs_are_found_in_the_data_directory() -> None:
    for name in ("intel", "aces", "freiburg-079"):
        log = bench.data.corrected_log(name)
        assert log.is_file(), log
        with log.open("rb") as f:
            assert f.read(2) == b"\x1f\x8b"  # gzip
