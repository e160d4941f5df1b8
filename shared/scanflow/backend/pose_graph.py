"""2D pose-graph optimisation: the least-squares core of the SLAM back end.

Nodes are poses T_map_node (x, y, theta); an edge (i, j, z, info) says T_i^-1 T_j = z, with
information `info` over the relative pose's (x, y, theta). Following Grisetti et al., "A tutorial
on graph-based SLAM" (g2o's EdgeSE2), the residual is
    e = [R_z^T (R_i^T (t_j - t_i) - t_z); wrap(theta_j - theta_i - theta_z)]
and the cost 0.5 sum_k rho_k(e_k^T info_k e_k), minimised by Levenberg-Marquardt (Marquardt's
lambda * diag(H) damping) on the sparse normal equations, assembled for all edges at once. The
`fixed` node's variables are left out (the gauge freedom). Robust edges (loop closures, which
can be wrong) use the Cauchy kernel rho(s) = c^2 log(1 + s / c^2) by iteratively reweighted
least squares, weight 1 / (1 + s / c^2) with c = robust_scale (in standard deviations); the
others rho(s) = s. A node not tied to the fixed one through edges would make the normal
equations singular, so that is an error.
"""

from __future__ import annotations

import operator
from dataclasses import dataclass
from typing import cast

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.sparse import coo_matrix, csc_matrix, diags
from scipy.sparse.csgraph import connected_components
from scipy.sparse.linalg import splu

from scanflow.geometry import Pose2D, normalize_angles

SYMMETRY_TOLERANCE = 1e-6  # |info - info^T| allowed, relative to info's largest entry
INITIAL_DAMPING = 1e-4  # lambda of the first step: close to Gauss-Newton

# i (M,), j (M,), z (M, 3), information (M, 3, 3), robust (M,)
_Edges = tuple[NDArray[np.int64], NDArray[np.int64], NDArray[np.float64], NDArray[np.float64],
               NDArray[np.bool_]]


@dataclass(frozen=True, eq=False)
class OptimiseReport:
    """The outcome of `PoseGraph.optimise`; costs are 0.5 sum_k rho_k(s_k)."""

    poses: NDArray[np.float64]  # (N, 3) optimised x, y, theta (theta in [-pi, pi))
    iterations: int  # linear solves, the rejected LM steps included
    initial_cost: float
    final_cost: float
    converged: bool  # a tolerance was met before max_iterations
    loop_weights: NDArray[np.float64]  # (M,) final IRLS weight per edge, 1.0 when not robust


def _residuals(
    xi: NDArray[np.float64], xj: NDArray[np.float64], z: NDArray[np.float64]
) -> NDArray[np.float64]:
    """(M, 3) residuals of edges from poses xi to xj (M, 3) measured as z (M, 3)."""
    dx, dy = xj[:, 0] - xi[:, 0], xj[:, 1] - xi[:, 1]
    # R_z^T R_i^T is the rotation by -(theta_i + theta_z).
    c, s = np.cos(xi[:, 2] + z[:, 2]), np.sin(xi[:, 2] + z[:, 2])
    cz, sz = np.cos(z[:, 2]), np.sin(z[:, 2])
    e = np.empty_like(z)
    e[:, 0] = c * dx + s * dy - (cz * z[:, 0] + sz * z[:, 1])
    e[:, 1] = -s * dx + c * dy - (-sz * z[:, 0] + cz * z[:, 1])
    e[:, 2] = normalize_angles(xj[:, 2] - xi[:, 2] - z[:, 2])
    return e


def _residuals_and_jacobians(
    xi: NDArray[np.float64], xj: NDArray[np.float64], z: NDArray[np.float64]
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """Residuals (M, 3) and their Jacobians A = de/dx_i, B = de/dx_j, each (M, 3, 3)."""
    e = _residuals(xi, xj, z)
    dx, dy = xj[:, 0] - xi[:, 0], xj[:, 1] - xi[:, 1]
    c, s = np.cos(xi[:, 2] + z[:, 2]), np.sin(xi[:, 2] + z[:, 2])
    b = np.zeros((len(z), 3, 3))
    b[:, 0, 0], b[:, 0, 1], b[:, 1, 0], b[:, 1, 1] = c, s, -s, c  # R_z^T R_i^T
    b[:, 2, 2] = 1.0
    a = -b
    # R_z^T dR_i^T/dtheta_i (t_j - t_i) = d(R_z^T R_i^T)/dtheta_i (t_j - t_i).
    a[:, 0, 2] = -s * dx + c * dy
    a[:, 1, 2] = -c * dx - s * dy
    return e, a, b


def _evaluate(
    x: NDArray[np.float64], edges: _Edges, scale2: float
) -> tuple[float, NDArray[np.float64]]:
    """Robust cost and IRLS weights at poses x (N, 3)."""
    i, j, z, info, robust = edges
    e = _residuals(x[i], x[j], z)
    s = np.einsum("mi,mij,mj->m", e, info, e)
    rho = np.where(robust, scale2 * np.log1p(s / scale2), s)
    return 0.5 * float(np.sum(rho)), np.where(robust, 1.0 / (1.0 + s / scale2), 1.0)


def _normal_equations(
    x: NDArray[np.float64], edges: _Edges, weights: NDArray[np.float64], fixed: int
) -> tuple[csc_matrix, NDArray[np.float64]]:
    """H (CSC) and b of H dx = -b over every node's (x, y, theta) but the fixed node's."""
    i, j, z, info, _ = edges
    n, m = len(x), len(z)
    e, a, b = _residuals_and_jacobians(x[i], x[j], z)
    jac = np.concatenate((a, b), axis=2)  # (M, 3, 6): d e / d (x_i, x_j)
    jt_omega = np.swapaxes(jac, 1, 2) @ (info * weights[:, None, None])
    h_blocks = jt_omega @ jac  # (M, 6, 6)
    g_blocks = (jt_omega @ e[:, :, None])[:, :, 0]  # (M, 6)
    block = np.arange(n) - (np.arange(n) > fixed)  # node -> block of the reduced system
    block[fixed] = -1
    nodes = block[np.column_stack((i, j))]  # (M, 2)
    var = np.where(nodes[:, :, None] >= 0, 3 * nodes[:, :, None] + np.arange(3), -1).reshape(m, 6)
    rows = np.broadcast_to(var[:, :, None], (m, 6, 6))
    cols = np.broadcast_to(var[:, None, :], (m, 6, 6))
    keep = (rows >= 0) & (cols >= 0)
    size = 3 * (n - 1)
    h = coo_matrix((h_blocks[keep], (rows[keep], cols[keep])), shape=(size, size)).tocsc()
    free = var >= 0
    # With weights bincount sums float64s (numpy's stub says integers).
    g = cast(NDArray[np.float64], np.bincount(var[free], weights=g_blocks[free], minlength=size))
    return h, g


def grown(buffer: NDArray, count: int) -> NDArray:
    """`buffer` with room for row `count` (capacity doubled when full): arrays that grow by
    a row at a time, amortised."""
    if count < len(buffer):
        return buffer
    bigger = np.zeros((max(16, 2 * len(buffer)), *buffer.shape[1:]), dtype=buffer.dtype)
    bigger[:count] = buffer[:count]
    return bigger


class PoseGraph:
    """Nodes are poses T_map_node; an edge (i, j, z, info) says T_i^-1 T_j = z with information
    matrix info (3x3, symmetric positive definite, in the order x, y, theta of the relative
    pose)."""

    def __init__(self) -> None:
        self._poses = np.zeros((0, 3))
        self._ij = np.zeros((0, 2), dtype=np.int64)
        self._z = np.zeros((0, 3))
        self._info = np.zeros((0, 3, 3))
        self._robust = np.zeros(0, dtype=np.bool_)
        self._n = 0
        self._m = 0

    @property
    def node_count(self) -> int:
        """Number of nodes (poses) added so far."""
        return self._n

    @property
    def edge_count(self) -> int:
        """Number of edges added so far."""
        return self._m

    @property
    def poses(self) -> NDArray[np.float64]:
        """(N, 3) copy of the node poses (x, y, theta)."""
        return self._poses[: self._n].copy()

    def pose(self, i: int) -> Pose2D:
        """Node `i`'s pose T_map_node; ValueError unless 0 <= i < node_count."""
        return Pose2D.from_array(self._poses[self._index("i", i)])

    def _index(self, name: str, value: int) -> int:
        index = operator.index(value)
        if not 0 <= index < self._n:
            raise ValueError(f"{name} must be a node index in [0, {self._n}), got {value!r}")
        return index

    def add_node(self, pose: Pose2D) -> int:
        """Add a node at `pose`; returns its index (0, 1, ...)."""
        values = pose.to_array()
        if not np.all(np.isfinite(values)):
            raise ValueError(f"pose must be finite, got {pose!r}")
        self._poses = grown(self._poses, self._n)
        self._poses[self._n] = values
        self._n += 1
        return self._n - 1

    def add_edge(
        self, i: int, j: int, measurement: Pose2D, information: ArrayLike, robust: bool = False
    ) -> int:
        """Add the constraint T_i^-1 T_j = measurement; returns the edge's index."""
        i, j = self._index("i", i), self._index("j", j)
        if i == j:
            raise ValueError(f"i and j must differ, got i = j = {i}")
        z = measurement.to_array()
        if not np.all(np.isfinite(z)):
            raise ValueError(f"measurement must be finite, got {measurement!r}")
        info = np.asarray(information, dtype=np.float64)
        if info.shape != (3, 3):
            raise ValueError(f"information must be 3x3, got shape {info.shape}")
        if not np.all(np.isfinite(info)):
            raise ValueError(f"information must be finite, got {info.tolist()}")
        if np.max(np.abs(info - info.T)) > SYMMETRY_TOLERANCE * np.max(np.abs(info)):
            raise ValueError(f"information must be symmetric, got {info.tolist()}")
        info = 0.5 * (info + info.T)
        if float(np.linalg.eigvalsh(info)[0]) <= 0.0:
            raise ValueError(f"information must be positive definite, got {info.tolist()}")
        self._ij, self._z = grown(self._ij, self._m), grown(self._z, self._m)
        self._info, self._robust = grown(self._info, self._m), grown(self._robust, self._m)
        self._ij[self._m], self._z[self._m] = (i, j), z
        self._info[self._m], self._robust[self._m] = info, bool(robust)
        self._m += 1
        return self._m - 1

    def set_poses(self, poses: ArrayLike) -> None:
        """Replace every node's pose with the rows of an (N, 3) array."""
        p = np.asarray(poses, dtype=np.float64)
        if p.shape != (self._n, 3):
            raise ValueError(f"poses must have shape ({self._n}, 3), got {p.shape}")
        if not np.all(np.isfinite(p)):
            raise ValueError("poses must be finite")
        self._poses = np.column_stack((p[:, :2], normalize_angles(p[:, 2])))

    def edges(self) -> _Edges:
        """Copies of every edge's i, j (M,), measurement z (M, 3), information (M, 3, 3) and
        robust flag (M,)."""
        m = self._m
        return (self._ij[:m, 0].copy(), self._ij[:m, 1].copy(), self._z[:m].copy(),
                self._info[:m].copy(), self._robust[:m].copy())

    def optimise(
        self, *, fixed: int = 0, max_iterations: int = 30, robust_scale: float = 1.0,
        tolerance: float = 1e-6,
    ) -> OptimiseReport:
        """Minimise the graph's cost with node `fixed` held; the result becomes the graph's
        poses. Stops when a step's max |dx| or an accepted step's relative cost decrease falls
        below `tolerance`. An empty graph gives an empty, converged report."""
        if not robust_scale > 0.0 or not np.isfinite(robust_scale):
            raise ValueError(f"robust_scale must be positive and finite, got {robust_scale!r}")
        if max_iterations < 0:
            raise ValueError(f"max_iterations must be >= 0, got {max_iterations!r}")
        if not tolerance >= 0.0:
            raise ValueError(f"tolerance must be >= 0, got {tolerance!r}")
        if self._n == 0:
            return OptimiseReport(np.zeros((0, 3)), 0, 0.0, 0.0, True, np.zeros(0))
        fixed = self._index("fixed", fixed)
        edges = self.edges()
        graph = coo_matrix((np.ones(self._m), (edges[0], edges[1])), shape=(self._n, self._n))
        labels = connected_components(graph, directed=False)[1]
        apart = int(np.count_nonzero(labels != labels[fixed]))
        if apart:
            raise ValueError(
                f"{apart} of {self._n} nodes are not connected to the fixed node {fixed} "
                "through edges: their poses are undetermined"
            )
        scale2 = float(robust_scale) ** 2
        x = self.poses
        cost, weights = _evaluate(x, edges, scale2)
        initial_cost = cost
        iterations, converged = 0, self._n == 1
        damping, growth, system = INITIAL_DAMPING, 2.0, None
        while not converged and iterations < max_iterations:
            if system is None:
                system = _normal_equations(x, edges, weights, fixed)
            h, g = system
            iterations += 1
            # H + lambda diag(H) is symmetric positive definite: a symmetric ordering and no
            # pivoting (SuperLU as a Cholesky), several times faster than spsolve's defaults.
            damped = (h + damping * diags(h.diagonal())).tocsc()
            try:
                step = splu(damped, permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0,
                            options={"SymmetricMode": True}).solve(-g)
            except RuntimeError:  # numerically singular: a failed step, damped harder next
                step = np.full(len(g), np.nan)
            candidate = x + np.insert(step.reshape(-1, 3), fixed, 0.0, axis=0)
            candidate[:, 2] = normalize_angles(candidate[:, 2])
            trial_cost, trial_weights = _evaluate(candidate, edges, scale2)
            small = float(np.max(np.abs(step), initial=0.0)) < tolerance
            if trial_cost < cost:  # the gain ratio is positive
                decrease = (cost - trial_cost) / cost
                x, cost, weights, system = candidate, trial_cost, trial_weights, None
                damping, growth = damping / 3.0, 2.0
                converged = small or decrease < tolerance
            else:
                damping, growth = damping * growth, growth * 2.0
                converged = small
        self._poses = x
        return OptimiseReport(x.copy(), iterations, initial_cost, cost, converged, weights)
