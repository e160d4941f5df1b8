"""Process set-up: the settings check at start, the CPU plan, a service pinning itself to CPUs."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys

import pytest
from hypothesis import given
from hypothesis import strategies as st

from services.common.process import available_cpus, cpu_plan

needs_two_cpus = pytest.mark.skipif(len(available_cpus()) < 2, reason="needs 2 CPUs")


@given(
    cpus=st.sets(st.integers(0, 63), min_size=1, max_size=16),
    matchers=st.integers(0, 20),
)
def test_cpu_plan_splits_the_cpus_and_always_leaves_one_to_share(cpus, matchers):
    plan = cpu_plan(sorted(cpus), matchers)
    if len(cpus) == 1 or matchers == 0:
        assert plan is None
        return
    assert plan is not None
    assert set(plan.dedicated).isdisjoint(plan.shared)
    assert set(plan.dedicated) | set(plan.shared) == cpus
    assert len(plan.dedicated) == min(matchers, len(cpus) - 1)
    assert plan.shared  # the light services always have somewhere to run


def test_cpu_plan_gives_matchers_the_last_cpus_each_its_own_and_keeps_it_on_restart():
    plan = cpu_plan([0, 1, 2, 3], 2)
    assert plan is not None
    assert plan.cpus_for("router", "router") == [0, 1]
    assert plan.cpus_for("matcher", "matcher-a") == [2]
    assert plan.cpus_for("matcher", "matcher-b") == [3]
    assert plan.cpus_for("matcher", "matcher-c") == [0, 1]  # no dedicated CPU left: share
    assert plan.cpus_for("matcher", "matcher-a") == [2]  # a restart keeps its CPU
    assert plan.cpus_for("deskew", "deskew") == [0, 1]
    # Zenoh's threads of a matcher with a CPU of its own go to the shared ones; others stay put
    assert plan.io_cpus_for("matcher", "matcher-a") == [0, 1]
    assert plan.io_cpus_for("matcher", "matcher-c") == []
    assert plan.io_cpus_for("router", "router") == []


def _affinity_after_init(cpus: str, field: str = "cpus") -> subprocess.CompletedProcess[str]:
    """A fresh interpreter that runs `init_process` with `cpus` (as deskew's `field`), then
    reports the affinity of itself and of a thread started afterwards."""
    code = (
        "import os, threading\n"
        "from scanflow.config import DeskewSettings\n"
        "from services.common.process import init_process\n"
        f"init_process(DeskewSettings(log_level='INFO', {field}=[{cpus}]))\n"
        "seen = []\n"
        "t = threading.Thread(target=lambda: seen.append(sorted(os.sched_getaffinity(0))))\n"
        "t.start(); t.join()\n"
        "print(sorted(os.sched_getaffinity(0)), seen[0])\n"
    )
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=False)


@needs_two_cpus
def test_init_process_pins_the_process_and_the_threads_it_starts_later():
    last = available_cpus()[-1]
    result = _affinity_after_init(str(last))
    assert result.returncode == 0, result.stderr
    assert result.stdout.split("] [") == [f"[{last}", f"{last}]\n"]


@pytest.mark.parametrize("field", ["cpus", "io_cpus"])
def test_init_process_names_cpus_the_process_cannot_have(field: str):
    """An exit at start naming the variable and the CPUs there are, not a traceback."""
    missing = max(available_cpus() or [0]) + 1000
    result = _affinity_after_init(str(missing), field)
    assert result.returncode == 1
    assert result.stderr.startswith(f"bad settings: SCANFLOW_DESKEW_{field.upper()}: cpus "
                                    f"[{missing}] are not available"), result.stderr
    assert "Traceback" not in result.stderr


@needs_two_cpus
@pytest.mark.skipif(shutil.which("taskset") is None, reason="needs taskset (util-linux)")
def test_init_process_may_widen_the_affinity_it_inherited():
    first, last = available_cpus()[0], available_cpus()[-1]
    code = (
        "import os\n"
        "from scanflow.config import ProcessSettings\n"
        "from services.common.process import init_process\n"
        f"init_process(ProcessSettings(log_level='INFO', cpus=[{first}, {last}]))\n"
        "print(sorted(os.sched_getaffinity(0)))\n"
    )
    result = subprocess.run(
        ["taskset", "-c", str(first), sys.executable, "-c", code],
        capture_output=True, text=True, check=False,
    )
    assert result.returncode == 0, result.stderr
    assert result.stdout.strip() == f"[{first}, {last}]"


@needs_two_cpus
def test_a_service_shell_puts_zenohs_threads_on_its_io_cpus_and_python_threads_with_it():
    """The worker's CPU keeps the process's Python threads (they share the GIL with it); the
    Zenoh runtime's threads, started when the session opens, run on the I/O CPUs."""
    first, last = available_cpus()[0], available_cpus()[-1]
    code = (
        "import os, threading\n"
        "from scanflow.config import ServiceSettings, ZenohSettings\n"
        "from services.common.process import init_process\n"
        "from services.common.shell import ServiceShell\n"
        f"settings = ServiceSettings(cpus=[{last}], io_cpus=[{first}])\n"
        "init_process(settings)\n"
        "zenoh = ZenohSettings(mode='peer', connect=[], listen=[], multicast_scouting=False)\n"
        "tasks = lambda: {int(t) for t in os.listdir('/proc/self/task')}\n"
        "before = tasks()\n"
        "shell = ServiceShell('probe', settings, zenoh)\n"
        "shell.subscribe('probe/in', 'x', bytes)\n"
        "shell.start(install_signals=False)\n"
        "python = {t.native_id for t in threading.enumerate()}\n"
        "for tid in sorted(tasks()):\n"
        "    kind = 'python' if tid in python else 'zenoh' if tid not in before else 'import'\n"
        "    print(kind, sorted(os.sched_getaffinity(tid)))\n"
        "shell.close(flush_s=0.0)\n"
    )
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert result.returncode == 0, result.stderr
    seen = {tuple(line.split(" ", 1)) for line in result.stdout.splitlines()}
    assert ("python", f"[{last}]") in seen and ("zenoh", f"[{first}]") in seen, seen
    # threads started before init_process (numpy's BLAS pool) are pinned with the process
    allowed = {("python", f"[{last}]"), ("zenoh", f"[{first}]"), ("import", f"[{last}]")}
    assert seen <= allowed, seen


def test_io_cpus_the_process_cannot_have_are_named():
    missing = max(available_cpus() or [0]) + 1000
    code = (
        "from scanflow.config import ProcessSettings\n"
        "from services.common.process import init_process\n"
        f"init_process(ProcessSettings(io_cpus=[{missing}]))\n"
    )
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert result.returncode != 0
    assert f"cpus [{missing}] are not available" in result.stderr


@pytest.mark.parametrize(("service", "name", "value"), [
    ("router", "SCANFLOW_ROUTER_QUEUE_SIZE", "0"),
    ("ingest", "SCANFLOW_INGEST_RATE", "fast"),
    ("deskew", "SCANFLOW_DESKEW_ODOM_WAIT_S", "-1"),
    ("matcher", "SCANFLOW_FRONTEND_MIN_SCORE", "nan"),
    ("mapserver", "SCANFLOW_BACKEND_LOOP_CLOSURE", "perhaps"),
    ("gateway", "SCANFLOW_ZENOH_MODE", "satellite"),
])
def test_a_service_with_a_bad_setting_stops_at_start_naming_it(service, name, value):
    """One line naming the variable, before any session is opened (no router runs here)."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("SCANFLOW_")}
    done = subprocess.run([sys.executable, "-m", f"services.{service}"], env={**env, name: value},
                          capture_output=True, text=True, timeout=60)
    assert done.returncode == 1
    assert f"{service}: bad settings: {name}={value!r}" in done.stderr
    assert "Traceback" not in done.stderr
