"""warm_up runs the kernels a service needs for its first scan (checked in a fresh process)."""

from __future__ import annotations

import json
import subprocess
import sys

KERNELS = {
    "scanflow.deskew.kernels": ["beams_in_reference", "coverage", "interpolate_poses"],
    "scanflow.maps.raycast": ["_mark"],
    "scanflow.maps.field": ["_splat_means"],
    "scanflow.matching.field_cost": ["_solve_kernel"],  # the front end's scan-to-map step
}
METHOD_KERNELS = {
    "scanflow.matching.plicp": ["_plicp_kernel"],
    "scanflow.matching.covariance": ["_censi_terms"],
    "scanflow.matching.icp": ["_icp_kernel"],
    "scanflow.matching.ndt": ["_ndt_accumulate"],
    "scanflow.matching.csm": ["_branch_and_bound", "_exhaustive"],
}

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
    full = _run(everything, methods=True)
    assert all(full["after"].values()), full["after"]
