"""The launcher's exit codes: its own SIGTERM counts as a clean stop."""

from __future__ import annotations

import subprocess
import sys

from services.common.launch import Launcher


def _python(code: str) -> subprocess.Popen[bytes]:
    """A child that prints "ready" once `code` (its signal setup) ran, then sleeps."""
    script = f"import signal, sys, time\n{code}\nprint('ready', flush=True)\ntime.sleep(60)"
    proc = subprocess.Popen([sys.executable, "-c", script], stdout=subprocess.PIPE)
    assert proc.stdout is not None and proc.stdout.readline() == b"ready\n"
    return proc


def test_launcher_counts_death_by_its_own_sigterm_as_a_clean_stop(tmp_path):
    launcher = Launcher({}, tmp_path)
    launcher.processes["reraises"] = _python("")  # SIGTERM's default action, as uvicorn's re-raise
    launcher.processes["fails"] = _python(
        "signal.signal(signal.SIGTERM, lambda *_: sys.exit(3))"
    )
    launcher.processes["done"] = subprocess.Popen([sys.executable, "-c", "raise SystemExit(4)"])
    launcher.processes["done"].wait()
    assert launcher.stop_all() == {"done": 4, "fails": 3, "reraises": 0}


def test_stop_all_stops_the_named_services_first_in_order_then_the_rest_newest_first(tmp_path):
    """`scanflow up` stops with the data (ingest, gateway, deskew, matcher, map server), one
    at a time, so what a stage flushes at its stop reaches the next one still running."""
    stopped = tmp_path / "stopped"
    launcher = Launcher({}, tmp_path)
    for name in ("router", "deskew", "matcher", "mapserver", "ingest"):
        launcher.processes[name] = _python(
            f"signal.signal(signal.SIGTERM, lambda *_: (open({str(stopped)!r}, 'a')"
            f".write('{name}\\n'), sys.exit(0)))"
        )
    codes = launcher.stop_all(("ingest", "gateway", "deskew", "matcher", "mapserver"))
    assert list(codes) == ["ingest", "deskew", "matcher", "mapserver", "router"]
    assert set(codes.values()) == {0}
    assert stopped.read_text().split() == ["ingest", "deskew", "matcher", "mapserver", "router"]
