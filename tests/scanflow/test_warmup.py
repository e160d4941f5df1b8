"""warm_up runs the kernels a service needs for its first scan (checked in a fresh process)."""

from __future__ import annotations

import json
import subprocess
import sys

KERNELS = {
    "scanflow.deskew.kernels": ["beams_in_reference", "coverage", "interpolate_poses"],
    "scanflow.maps.occupancy_kernels": ["update_cells"],
    "scanflow.maps.field": ["_splat_means"],
    "scanflow.matching.field_cost": ["_solve_kernel"],  # the front end's scan-to-map step
}
METHOD_KERNELS = {
    "scanflow.matching.plicp": ["_plicp_kernel"],
    "scanflow.matching.covariance": ["_censi_terms"],
    "scanflow.matching.icp": ["_icp_kernel"],
    "scanflow.matching.ndt": ["_ndt_accumulate"],
    "scanflow.matching.csm_search": ["_branch_and_bound", "_exhaustive"],
    "scanflow.matching.correspondence": ["grid_within_any"],  # a scan target's surfaces
}

# Kernels called from Python that a full warm-up compiles exactly once: every caller passes
# the same array types (numba compiles each type apart, 0.1-0.5 s each). A scan target's NDT
# cells are read-only like a map's. (Kernels called only from other kernels are not counted
# here: loaded from numba's cache, their callers bring them compiled.) The map's float32
# fields and stack views next to a scan target's float64 and whole arrays still compile
# twice, by design (`_splat_means`, `field_cost._accumulate`, the csm search kernels).
ONCE = {"scanflow.matching.ndt": ["_ndt_accumulate"]}

SCRIPT = """
import importlib, json, sys
from scanflow.warmup import warm_up
kernels = json.loads(sys.argv[1])
def compiled():
    return {f"{m}.{k}": len(getattr(importlib.import_module(m), k).signatures)
            for m, names in kernels.items() for k in names}
before = compiled()
scans = warm_up(methods=sys.argv[2] == "1")
print(json.dumps({"before": before, "after": compiled(), "scans": scans}))
"""


def _run(kernels: dict[str, list[str]], methods: bool) -> dict:
    out = subprocess.run(
        [sys.executable, "-c", SCRIPT, json.dumps(kernels), "1" if methods else "0"],
        capture_output=True, text=True, check=True, timeout=300,
    )
    return json.loads(out.stdout.strip().splitlines()[-1])


def test_warm_up_compiles_the_per_scan_kernels_and_with_methods_every_matcher():
    everything = {**KERNELS, **METHOD_KERNELS}
    plain = _run(everything, methods=False)
    assert plain["scans"] > 2
    assert not any(plain["before"].values())  # a fresh process: nothing compiled yet
    assert all(plain["after"][f"{m}.{k}"] for m, names in KERNELS.items() for k in names)
    full = _run({**everything, **ONCE}, methods=True)
    assert all(full["after"].values()), full["after"]
    once = {f"{m}.{k}": full["after"][f"{m}.{k}"] for m, names in ONCE.items() for k in names}
    assert once == dict.fromkeys(once, 1)


NOTHING_LEFT_SCRIPT = """
import importlib, json, pkgutil
from numba.core.registry import CPUDispatcher
import scanflow
import numpy as np
from scanflow.frontend import (Frontend, FrontendStatus, default_settings, insert_scan,
                               occupancy_params)
from scanflow.backend.loops import ScanNode, draw_keyframes
from scanflow.config import BackendSettings
from scanflow.geometry import IDENTITY, Pose2D
from scanflow.maps.matching_map import MatchingMap
from scanflow.maps.occupancy import OccupancyGrid
from scanflow.matching import MatchInputError, available_methods, match
from scanflow.pipeline import DeskewStage, Pipeline
from scanflow.sim import SimConfig, simulate
from scanflow.warmup import warm_up
from scanflow.wire import DeskewedScanMessage, MapInsertMessage, OdometryMessage, ScanMessage

kernels = {}
for info in pkgutil.walk_packages(scanflow.__path__, "scanflow."):
    if info.name.endswith("__main__"):
        continue
    for name, value in vars(importlib.import_module(info.name)).items():
        if isinstance(value, CPUDispatcher):
            kernels[f"{value.__module__}.{name}"] = value
warm_up(methods=True)
before = {name: len(kernel.signatures) for name, kernel in kernels.items()}

# A robot out of reach for 15 s (a network cut): back, it needs the fallback search (twice).
pipeline, statuses, scans, outputs = Pipeline(), [], [], []
for frame in simulate(SimConfig(duration_s=25.0, seed=7, robot_id="gap")):
    if 1.6 <= frame.scan.stamp_s < 16.6:
        continue
    for odom in frame.odometry:
        pipeline.add_odometry(odom)
    outputs.append(pipeline.process(frame.scan))
    statuses.append(outputs[-1].estimate.status)
    scans.append(frame.scan)

# The matcher's back end: keyframes, loop closures (the search on a keyframe's drawn submap,
# whose stack is a whole array, not a view into a followed map's), optimisation, redraws.
looped, closures = Pipeline(backend=BackendSettings(loop_closure=True)), 0
for frame in simulate(SimConfig(duration_s=25.0, seed=1, robot_id="loop")):
    for odom in frame.odometry:
        looped.add_odometry(odom)
    closures += len(looped.process(frame.scan).backend.closures)

# The services' path: arrays decoded from the wire (read-only) into a matcher's front end and
# the map server's map, and point operands of a match request.
def wire(message):
    return type(message).decode(message.encode())

stage = DeskewStage()  # the deskew service: raw scans and odometry decoded from the wire
for frame in simulate(SimConfig(duration_s=1.0, seed=5, robot_id="wire")):
    for odom in frame.odometry:
        stage.add_odometry(wire(OdometryMessage(odom)).odom)
    stage.process(wire(ScanMessage(frame.scan)).scan)

tracker = Frontend()
served = MatchingMap(OccupancyGrid(occupancy_params(default_settings())))
for out in outputs[-30:]:
    r = out.deskew
    scan = wire(DeskewedScanMessage(
        robot_id="gap", seq=out.estimate.seq, stamp_s=r.reference_stamp_s, points=r.points,
        source_used=r.source_used, times_assumed=r.times_assumed, beam_count=r.beam_count,
        dropped_count=r.beam_count - r.valid_count, no_return_points=r.no_return_points,
        odom_pose=out.estimate.pose))
    est = tracker.process(scan.points, scan.stamp_s, scan.odom_pose, scan.seq,
                          scan.no_return_points)
    if est.inserted:
        ins = wire(MapInsertMessage("gap", est.seq, est.stamp_s, est.pose, scan.points,
                                    scan.no_return_points))
        insert_scan(served, ins.points, ins.pose, ins.no_return_points)
# A scan with one return and one no-return beam: one-ray broadcasts (read-only) in the insert.
insert_scan(served, np.array([[1.5, 0.5]]), tracker.pose, np.array([[20.0, -3.0]]))
# The back end's redraw and a loop-closure submap of the map server's keyframes (from the wire).
draw_keyframes([ScanNode(ins.stamp_s, ins.points, ins.no_return_points, IDENTITY),
                ScanNode(ins.stamp_s, ins.points[:1], np.zeros((0, 2)), Pose2D(0.1, 0, 0))],
               np.array([ins.pose.to_array(), tracker.pose.to_array()]),
               occupancy_params(default_settings()))
tracker.relocalise(scan.points, tracker.pose * Pose2D(0.5, 0.3, 0.35))
source = scan.points
target = wire(MapInsertMessage("gap", 0, 0.0, Pose2D(), Pose2D(-0.1, 0.05, 0.03)
                               .transform_points(source), np.zeros((0, 2)))).points
for method in available_methods():
    on_map = (scans[-1], pipeline.frontend.map, pipeline.frontend.pose)
    for operand, goal, guess in ((source, target, None), on_map):
        try:
            match(operand, goal, guess, method=method)
        except MatchInputError:  # svd takes no map, global no points
            pass
compiled = sorted(n for n, k in kernels.items() if len(k.signatures) > before[n])
print(json.dumps({"kernels": len(kernels), "compiled": compiled,
                  "recovered": statuses.count(FrontendStatus.RECOVERED),
                  "closures": closures}))
"""


def test_after_warm_up_a_recovery_and_every_method_on_a_map_compile_nothing():
    """What a service does after its health token compiles no kernel: the first scan after a
    gap (the fallback search on the map, then the refinement) once compiled for seconds while
    the robot's scans queued behind it, so did a matcher's first loop-closure search (1.9 s
    idle: a drawn submap's stack, a numba type of its own), and arrays decoded from the wire
    (read-only, another type) compiled on a service's first real scan."""
    out = subprocess.run(
        [sys.executable, "-c", NOTHING_LEFT_SCRIPT],
        capture_output=True, text=True, check=False, timeout=600,
    )
    assert out.returncode == 0, out.stderr[-4000:]
    report = json.loads(out.stdout.strip().splitlines()[-1])
    assert report["kernels"] >= 10  # the search found the package's kernels
    assert report["recovered"] >= 1  # the gap took the fallback path
    assert report["closures"] >= 1  # the back end searched a submap and closed a loop
    assert report["compiled"] == []
