"""Run the compiled kernels once so that a fresh process handles its first scan at full speed.

numba compiles each kernel at its first call, or loads it from its cache; even from the cache
the first load sets up numba's compiler context, about 0.9 s of CPU measured here, which the
first scan of a service would otherwise wait for (an ingest-to-pose latency of ~0.9 s, then a
backlog of the scans behind it). Services call `warm_up` before they announce themselves
healthy; container builds call it to fill NUMBA_CACHE_DIR.
"""

from __future__ import annotations

from scanflow.matching import available_methods, match
from scanflow.pipeline import Pipeline
from scanflow.scan import LaserScan
from scanflow.sim import SimConfig, simulate

WARM_UP_SIM_S = 2.0


def warm_up(methods: bool = False) -> int:
    """Track a short simulated run (deskew, matching, fallback search, map updates) and, with
    `methods`, match two of its scans with every registered method; returns the scan count."""
    pipeline = Pipeline()
    scans: list[LaserScan] = []
    for frame in simulate(SimConfig(duration_s=WARM_UP_SIM_S, seed=0, robot_id="warmup")):
        for odom in frame.odometry:
            pipeline.add_odometry(odom)
        pipeline.process(frame.scan)
        scans.append(frame.scan)
    if methods:
        for method in available_methods():
            match(scans[1], scans[0], None, method=method)
    return len(scans)
