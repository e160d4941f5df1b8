"""What every service process does first: one logging format, then its CPU affinity.

On a small machine the scheduler's wake-up preemption lets the light services (router, ingest,
deskew, map server), which wake for every message, keep interrupting the matcher, the one
CPU-bound stage: a local launch can give the matcher CPUs of its own (see `cpu_plan`), and put
its Zenoh runtime's threads (network I/O, routing; they take no GIL) on the shared CPUs
(`io_threads`). Its Python threads stay with the worker: one of them holding the GIL while
descheduled on a busy shared CPU would stall the worker.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field

from scanflow.config import ProcessSettings, Section, SettingsError, check_environment

_log = logging.getLogger("scanflow.process")


def configure_logging(level: str) -> None:
    """Timestamped, service-named lines on stderr."""
    logging.basicConfig(
        level=level, format="%(asctime)s %(levelname)s %(name)s: %(message)s", force=True
    )


def require_settings(service: str, *sections: type[Section]) -> None:
    """Exit at start, naming every bad SCANFLOW_* variable the service reads, rather than
    with a traceback for the first one (or, for a NaN limit, not at all)."""
    try:
        check_environment(*sections)
    except SettingsError as error:
        raise SystemExit(f"{service}: bad settings: {error}") from None


def init_process(settings: ProcessSettings) -> None:
    """Configure logging, then restrict this process (its threads, and every thread it starts
    later) to `settings.cpus`; empty leaves the affinity it inherited. Unknown CPUs (also among
    `settings.io_cpus`, used by `io_threads`) are a clear error."""
    configure_logging(settings.log_level)
    if not (settings.cpus or settings.io_cpus):
        return
    if not available_cpus():
        _log.warning(
            "CPU affinity is not supported here: ignoring cpus=%s, io_cpus=%s",
            list(settings.cpus), list(settings.io_cpus),
        )
        return
    prefix = str(settings.model_config.get("env_prefix", ""))
    if settings.io_cpus:  # the kernel refuses CPUs outside the cgroup's set: check them now
        with _named(f"{prefix}IO_CPUS"), io_threads(settings.io_cpus):
            pass
    if not settings.cpus:
        return
    with _named(f"{prefix}CPUS"):
        _pin_calling_thread(settings.cpus)
    for tid in _thread_ids():  # those started at import (numpy's BLAS pool) too
        try:
            os.sched_setaffinity(tid, settings.cpus)
        except ProcessLookupError:  # a thread that has just ended
            continue
    _log.info("running on CPUs %s", sorted(set(settings.cpus)))


@contextmanager
def _named(variable: str) -> Iterator[None]:
    """Turn an unavailable CPU into an exit at start naming the setting, not a traceback."""
    try:
        yield
    except ValueError as exc:
        raise SystemExit(
            f"bad settings: {variable}: {exc} (available: {available_cpus()})"
        ) from None


@contextmanager
def io_threads(cpus: Sequence[int]) -> Iterator[None]:
    """Threads started inside the block (the Zenoh runtime's, when the first session opens)
    run on `cpus`, not where the calling thread works; its own affinity is restored after.
    Empty, or affinity unsupported: nothing changes. Unknown CPUs are a clear error."""
    before = available_cpus()
    if not cpus or not before:
        yield
        return
    try:
        _pin_calling_thread(cpus)
        yield
    finally:
        os.sched_setaffinity(0, before)


def _thread_ids() -> list[int]:
    """Kernel ids of this process's threads (Linux /proc)."""
    try:
        return [int(tid) for tid in os.listdir("/proc/self/task")]
    except OSError:
        return []


def _pin_calling_thread(cpus: Sequence[int]) -> None:
    """Restrict the calling thread (and the threads it starts from now on) to `cpus`."""
    wanted = set(cpus)
    try:  # may widen what the process inherited; the kernel keeps only CPUs it may use
        os.sched_setaffinity(0, wanted)
    except OSError as exc:
        raise ValueError(f"cpus {sorted(wanted)} are not available to this process") from exc
    unknown = sorted(wanted - set(available_cpus()))
    if unknown:
        raise ValueError(f"cpus {unknown} are not available to this process")


def available_cpus() -> list[int]:
    """The CPUs this process may run on; empty where affinity is unsupported (not Linux)."""
    if not hasattr(os, "sched_getaffinity"):
        return []
    return sorted(os.sched_getaffinity(0))


@dataclass
class CpuPlan:
    """Which CPUs each locally launched service gets: matchers one of their own while at least
    one CPU is left for the rest; everything else (and later matchers) shares the others."""

    dedicated: list[int]
    shared: list[int]
    _given: dict[str, int] = field(default_factory=dict)

    def cpus_for(self, name: str, label: str) -> list[int]:
        """The CPUs of service `name` started as `label` (the same again on a restart)."""
        if name == "matcher":
            if label not in self._given and len(self._given) < len(self.dedicated):
                self._given[label] = self.dedicated[len(self._given)]
            if label in self._given:
                return [self._given[label]]
        return list(self.shared)

    def io_cpus_for(self, name: str, label: str) -> list[int]:
        """Where the Zenoh threads of `name` started as `label` go: the shared CPUs for a
        service with a CPU of its own, else nowhere special (empty: with the process)."""
        return list(self.shared) if self.cpus_for(name, label) != self.shared else []


def cpu_plan(available: Sequence[int], matchers: int) -> CpuPlan | None:
    """Dedicate the last `matchers` CPUs (CPU 0 takes most interrupts) to matchers, keeping at
    least one for the rest; None when there is nothing to separate (one CPU, no matcher)."""
    cpus = sorted(set(available))
    count = min(matchers, len(cpus) - 1)
    if count <= 0:
        return None
    return CpuPlan(dedicated=cpus[len(cpus) - count :], shared=cpus[: len(cpus) - count])
