"""Run the compiled kernels once so that a fresh process handles its first scan at full speed.

numba compiles each kernel at its first call, or loads it from its cache; even from the cache
the first load sets up numba's compiler context, about 0.9 s of CPU measured here, which the
first scan of a service would otherwise wait for (an ingest-to-pose latency of ~0.9 s, then a
backlog of the scans behind it). A path left out is paid for later, at the worst time: the
front end's recovery search (csm on the map, then the local refinement) first ran on the scan
after a robot came back from a network cut, and compiled for 3 s idle, 7 s in a container and
over 30 s on a loaded machine while that robot's scans queued. (Arrays decoded from the wire
are read-only, a type numba compiles apart: `matching.as_points` copies them, so the writable
arrays here cover them.) Services call `warm_up` before they announce themselves healthy;
container builds call it to fill NUMBA_CACHE_DIR.
"""

from __future__ import annotations

import math

import numpy as np

from scanflow.backend.loops import ScanNode, draw_keyframes
from scanflow.frontend import occupancy_params
from scanflow.geometry import Pose2D
from scanflow.matching import MatchInputError, available_methods, match
from scanflow.matching.checks import ScanSurfaces, surfaces_agree
from scanflow.pipeline import Pipeline, PipelineOutput
from scanflow.sim import SimConfig, simulate

WARM_UP_SIM_S = 2.0
# Where the warm-up searches from: off the true pose, inside the default search window.
KIDNAP = Pose2D(0.5, 0.3, math.radians(20.0))
# Scan-to-scan target: the source moved by this, so every method (svd too) has a case.
MOTION = Pose2D(0.05, -0.03, math.radians(1.0))


def warm_up(methods: bool = False) -> int:
    """Track a short simulated run (deskew, matching, map updates), draw its last scan as the
    back end draws keyframes (redraws, loop-closure submaps), then relocalise off its last pose
    (the front end's fallback search on the map, refined); with `methods`, match its last scan
    with every registered method against itself moved and against the run's map, and let a
    scan target judge two of its lines as it judges isolated pairs. Returns the number of
    scans tracked."""
    pipeline = Pipeline()
    count = 0
    last: PipelineOutput | None = None
    for frame in simulate(SimConfig(duration_s=WARM_UP_SIM_S, seed=0, robot_id="warmup")):
        for odom in frame.odometry:
            pipeline.add_odometry(odom)
        last = pipeline.process(frame.scan)
        count += 1
    if last is None:
        raise RuntimeError("the warm-up run produced no scan")
    frontend = pipeline.frontend
    points, pose = last.deskew.points, frontend.pose or Pose2D()
    node = ScanNode(last.deskew.reference_stamp_s, points, last.deskew.no_return_points,
                    last.deskew.mount)
    draw_keyframes([node], pose.to_array()[None, :], occupancy_params(frontend.settings))
    if frontend.settings.fallback_method:
        frontend.relocalise(points, pose * KIDNAP)
    if methods:
        target = MOTION.transform_points(points)
        for method in available_methods():
            for goal, guess in ((target, None), (frontend.map, pose)):
                try:
                    match(points, goal, guess, method=method)
                except MatchInputError:  # svd takes no map, global no points
                    continue
        # A scan target judging a source's isolated two-point lines (`surface_conditioning`):
        # the simulated room's scans hold none, real far walls and trunks do.
        surfaces_agree(ScanSurfaces(target), points[:2], np.array([[1.0, 0.0], [0.0, 1.0]]),
                       unseen_agrees=True)
    return count
