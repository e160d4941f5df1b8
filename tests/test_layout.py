"""The tests mirror the code: every module of the core library, the services and the benches has
a test file at the mirrored path, so a newcomer finds a module's tests without searching."""

from __future__ import annotations

from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

# Code folder -> the tests folder that mirrors it.
MIRRORS = {
    ROOT / "shared" / "scanflow": ROOT / "tests" / "scanflow",
    ROOT / "services": ROOT / "tests" / "services",
    ROOT / "bench": ROOT / "tests" / "bench",
}


def mirrored_test(module: Path, code: Path, tests: Path) -> Path:
    """tests/<same folders>/test_<module>.py for code/<folders>/<module>.py."""
    relative = module.relative_to(code)
    return tests / relative.parent / f"test_{relative.name}"


def untested_modules() -> list[str]:
    """Modules without a mirrored test file. `__init__.py` (re-exports) and `__main__.py`
    (`python -m` entry points that call a tested `main`) are not modules of their own here."""
    missing = []
    for code, tests in MIRRORS.items():
        for module in sorted(code.rglob("*.py")):
            if module.name in ("__init__.py", "__main__.py"):
                continue
            if not mirrored_test(module, code, tests).is_file():
                missing.append(str(module.relative_to(ROOT)))
    return missing


def test_every_module_has_its_mirrored_test_file() -> None:
    assert untested_modules() == []


def test_the_mirror_rule_names_the_path_a_module_is_tested_at(tmp_path: Path) -> None:
    code, tests = tmp_path / "shared" / "scanflow", tmp_path / "tests" / "scanflow"
    module = code / "maps" / "grid.py"
    assert mirrored_test(module, code, tests) == tests / "maps" / "test_grid.py"
