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


def test_stop_together_signals_every_service_at_once_then_the_last_ones(tmp_path):
    """Each service here exits only once all three have had their SIGTERM: one at a time they
    would be killed at the timeout; together they all stop cleanly, the router after them."""
    log = tmp_path / "stopped"
    launcher = Launcher({}, tmp_path)
    launcher.processes["router"] = _python(
        f"signal.signal(signal.SIGTERM, lambda *_: (open({str(log)!r}, 'a')"
        ".write('router\\n'), sys.exit(0)))"
    )
    for name in ("deskew", "matcher", "mapserver"):
        launcher.processes[name] = _python(
            "def stop(*_):\n"
            f"    open({str(log)!r}, 'a').write('{name}\\n')\n"
            f"    while len(open({str(log)!r}).read().split()) < 3:\n"
            "        time.sleep(0.01)\n"
            "    sys.exit(0)\n"
            "signal.signal(signal.SIGTERM, stop)"
        )
    launcher.processes["fails"] = _python("signal.signal(signal.SIGTERM, lambda *_: sys.exit(3))")
    launcher.processes["done"] = subprocess.Popen([sys.executable, "-c", "raise SystemExit(4)"])
    launcher.processes["done"].wait()
    codes = launcher.stop_together(last=("router",), timeout_s=20.0)
    assert codes == {"deskew": 0, "matcher": 0, "mapserver": 0, "fails": 3, "done": 4,
                     "router": 0}
    assert list(codes)[-1] == "router"
    assert sorted(log.read_text().split()[:3]) == ["deskew", "mapserver", "matcher"]
    assert log.read_text().split()[3:] == ["router"]
