"""What every service process does first: one logging format, then its CPU affinity.

On a small machine the scheduler's wake-up preemption lets the light services (router, ingest,
deskew, map server), which wake for every message, keep interrupting the matcher, the one
CPU-bound stage: a local launch can give the matcher CPUs of its own (see `cpu_plan`).
"""

from __future__ import annotations

import logging
import os
from collections.abc import Sequence
from dataclasses import dataclass, field

from scanflow.config import ProcessSettings

_log = logging.getLogger("scanflow.process")


def configure_logging(level: str) -> None:
    """Timestamped, service-named lines on stderr."""
    logging.basicConfig(
        level=level, format="%(asctime)s %(levelname)s %(name)s: %(message)s", force=True
    )


def init_process(settings: ProcessSettings) -> None:
    """Configure logging, then restrict this process (and every thread it starts later) to
    `settings.cpus`; empty leaves the affinity it inherited. Unknown CPUs are a clear error."""
    configure_logging(settings.log_level)
    cpus = settings.cpus
    if not cpus:
        return
    if not available_cpus():
        _log.warning("CPU affinity is not supported here: ignoring cpus=%s", list(cpus))
        return
    wanted = set(cpus)
    try:  # may widen what the process inherited; the kernel keeps only CPUs it may use
        os.sched_setaffinity(0, wanted)
    except OSError as exc:
        raise ValueError(f"cpus {sorted(wanted)} are not available to this process") from exc
    unknown = sorted(wanted - set(available_cpus()))
    if unknown:
        raise ValueError(f"cpus {unknown} are not available to this process")
    _log.info("running on CPUs %s", sorted(wanted))


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


def cpu_plan(available: Sequence[int], matchers: int) -> CpuPlan | None:
    """Dedicate the last `matchers` CPUs (CPU 0 takes most interrupts) to matchers, keeping at
    least one for the rest; None when there is nothing to separate (one CPU, no matcher)."""
    cpus = sorted(set(available))
    count = min(matchers, len(cpus) - 1)
    if count <= 0:
        return None
    return CpuPlan(dedicated=cpus[len(cpus) - count :], shared=cpus[: len(cpus) - count])
