"""The pose-graph optimiser against scipy's general sparse least squares on the same graphs.

`python -m bench.pose_graph [--laps 5] [--nodes-per-lap 400] [--repeats 3] [--json]`

Graphs: laps of a square, each node tied to the next by noisy odometry (1 cm, 0.17 deg) and to
the same corner of every earlier lap by a closure (exact). Both solvers start from dead
reckoning and minimise the same cost (every edge plain least squares: scipy's robust losses
apply to all residuals alike, ours to closures only), node 0 held. Baseline:
`scipy.optimize.least_squares(method="trf", x_scale="jac")` with the analytic Jacobian as a
sparse matrix (its `lsmr` trust region); ours: `PoseGraph.optimise` (sparse Levenberg-Marquardt
on the normal equations, SuperLU). Reported: final cost, RMS position error against the truth,
median wall time over the repeats.
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np
from numpy.typing import NDArray
from scanflow.backend import PoseGraph
from scanflow.backend.pose_graph import _residuals_and_jacobians
from scanflow.geometry import Pose2D, compose_arrays, relative_arrays
from scipy.optimize import least_squares
from scipy.sparse import coo_matrix

ODOMETRY_STD = np.array([0.01, 0.01, 0.003])
LOOP_STD = np.array([0.02, 0.02, 0.005])


def square_laps(laps: int, per_lap: int, side_m: float = 20.0) -> NDArray[np.float64]:
    """Poses evenly spaced round a square, `laps` times."""
    s = np.arange(laps * per_lap) % per_lap * (4 * side_m / per_lap)
    side = np.minimum((s // side_m).astype(int), 3)
    along = s - side * side_m
    corners = np.array([[0, 0], [side_m, 0], [side_m, side_m], [0, side_m]], dtype=float)
    heading = side * (np.pi / 2)
    xy = corners[side] + along[:, None] * np.column_stack((np.cos(heading), np.sin(heading)))
    return np.column_stack((xy, heading))


def build(laps: int, per_lap: int, seed: int) -> tuple[PoseGraph, NDArray[np.float64]]:
    """The graph (started from dead reckoning) and the true poses."""
    rng = np.random.default_rng(seed)
    truth = square_laps(laps, per_lap)
    noise = rng.normal(0, ODOMETRY_STD, (len(truth) - 1, 3))
    steps = relative_arrays(truth[:-1], truth[1:]) + noise
    start = [truth[0]]
    for step in steps:
        start.append(compose_arrays(start[-1], step)[0])
    graph = PoseGraph()
    for pose in start:
        graph.add_node(Pose2D.from_array(pose))
    for k, step in enumerate(steps):
        graph.add_edge(k, k + 1, Pose2D.from_array(step), np.diag(ODOMETRY_STD**-2))
    for lap in range(1, laps):
        for k in range(per_lap * (laps - lap)):
            j = k + per_lap * lap
            z = relative_arrays(truth[k : k + 1], truth[j : j + 1])[0]
            graph.add_edge(k, j, Pose2D.from_array(z), np.diag(LOOP_STD**-2))
    return graph, truth


def scipy_solve(graph: PoseGraph) -> NDArray[np.float64]:
    """The same cost through scipy.optimize.least_squares (whitened residuals, node 0 held)."""
    i, j, z, info, _ = graph.edges()
    root = np.linalg.cholesky(info).transpose(0, 2, 1)  # info = L L^T: whiten with L^T
    n, m = graph.node_count, len(z)
    x0 = graph.poses

    def unpack(v: NDArray[np.float64]) -> NDArray[np.float64]:
        return np.vstack((x0[:1], v.reshape(-1, 3)))

    def fun(v: NDArray[np.float64]) -> NDArray[np.float64]:
        x = unpack(v)
        e, _, _ = _residuals_and_jacobians(x[i], x[j], z)
        return np.einsum("mab,mb->ma", root, e).ravel()

    def jac(v: NDArray[np.float64]) -> coo_matrix:
        x = unpack(v)
        _, a, b = _residuals_and_jacobians(x[i], x[j], z)
        rows, cols, vals = [], [], []
        for node, block in ((i, root @ a), (j, root @ b)):
            keep = node > 0
            r = (3 * np.arange(m)[:, None, None] + np.arange(3)[None, :, None]).repeat(3, 2)
            c = (3 * (node - 1)[:, None, None] + np.arange(3)[None, None, :]).repeat(3, 1)
            rows.append(r[keep].ravel())
            cols.append(c[keep].ravel())
            vals.append(block[keep].ravel())
        return coo_matrix(
            (np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
            shape=(3 * m, 3 * (n - 1)),
        )

    result = least_squares(fun, x0[1:].ravel(), jac=jac, method="trf", x_scale="jac",
                           tr_solver="lsmr")
    return unpack(result.x)


def cost(graph: PoseGraph, poses: NDArray[np.float64]) -> float:
    """The graph's cost at `poses`: half the information-weighted squared edge residuals."""
    i, j, z, info, _ = graph.edges()
    e, _, _ = _residuals_and_jacobians(poses[i], poses[j], z)
    return 0.5 * float(np.einsum("mi,mij,mj->", e, info, e))


def rms_error_m(poses: NDArray[np.float64], truth: NDArray[np.float64]) -> float:
    """RMS position error (m) of (N, 3) poses against the truth, without alignment."""
    return float(np.sqrt(np.mean(np.sum((poses[:, :2] - truth[:, :2]) ** 2, axis=1))))


def run(laps: int, per_lap: int, repeats: int) -> dict:
    """Median wall time, final cost and RMS error of both solvers over `repeats` seeded graphs,
    with the graph's size."""
    rows: dict[str, dict[str, list[float]]] = {"scanflow": {}, "scipy_least_squares": {}}
    for seed in range(repeats):
        for name in rows:
            graph, truth = build(laps, per_lap, seed)
            t0 = time.perf_counter()
            poses = graph.optimise().poses if name == "scanflow" else scipy_solve(graph)
            elapsed = time.perf_counter() - t0
            for key, value in (("wall_s", elapsed), ("cost", cost(graph, poses)),
                               ("rms_error_m", rms_error_m(poses, truth))):
                rows[name].setdefault(key, []).append(value)
    graph, _ = build(laps, per_lap, 0)
    return {
        "nodes": graph.node_count, "edges": graph.edge_count, "repeats": repeats,
        **{name: {k: float(np.median(v)) for k, v in row.items()} for name, row in rows.items()},
    }


def main(argv: list[str] | None = None) -> None:
    """Run the benchmark and print its report as JSON (one line with --json)."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--laps", type=int, default=5)
    parser.add_argument("--nodes-per-lap", type=int, default=400)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args(argv)
    report = run(args.laps, args.nodes_per_lap, args.repeats)
    print(json.dumps(report, indent=None if args.json else 2))


if __name__ == "__main__":
    main()
