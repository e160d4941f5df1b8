"""Conditioning of a 2D match: is the pose observable from these points, and if not, which way?

The Hessian mixes metres and radians, so the rotation axis is scaled by a characteristic length
(the RMS radius of the points) before the eigen-analysis; the weak direction is reported back in
(x, y, theta) as a unit 3-vector. Corridors show up as one tiny translational eigenvalue.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

# Ratio of smallest to largest scaled eigenvalue below which a direction counts as unconstrained.
DEGENERATE_RATIO = 2e-3


@dataclass(frozen=True)
class Conditioning:
    """Eigen-analysis of a scaled 3x3 Hessian."""

    eigenvalues: NDArray[np.float64]
    weak_direction: tuple[float, float, float]
    ratio: float

    @property
    def degenerate(self) -> bool:
        return not self.ratio > DEGENERATE_RATIO


def characteristic_length_m(points: NDArray[np.float64]) -> float:
    """RMS distance of the points from their centroid (>= 1 cm), the scale for rotations."""
    if len(points) == 0:
        return 1.0
    c = points - points.mean(axis=0)
    return max(float(np.sqrt(np.mean(np.sum(c * c, axis=1)))), 0.01)


def analyse_hessian(hessian: NDArray[np.float64], length_m: float) -> Conditioning:
    """Eigenvalues and weakest direction of H with theta scaled by `length_m`."""
    h = np.asarray(hessian, dtype=np.float64)
    if h.shape != (3, 3) or not np.all(np.isfinite(h)):
        return Conditioning(np.zeros(3), (1.0, 0.0, 0.0), 0.0)
    scale = np.array([1.0, 1.0, 1.0 / length_m])
    hs = h * np.outer(scale, scale)
    vals, vecs = np.linalg.eigh(0.5 * (hs + hs.T))
    top = float(vals[-1])
    ratio = float(vals[0]) / top if top > 0.0 else 0.0
    weak = vecs[:, 0] * scale
    weak /= np.linalg.norm(weak)
    if weak[np.argmax(np.abs(weak))] < 0.0:
        weak = -weak
    return Conditioning(vals, (float(weak[0]), float(weak[1]), float(weak[2])), ratio)


def line_hessian(points: NDArray[np.float64], normals: NDArray[np.float64]) -> NDArray[np.float64]:
    """Point-to-line Hessian sum_i J_i^T J_i, J_i = [n_x, n_y, p x n] (unit residual weights)."""
    cross = points[:, 0] * normals[:, 1] - points[:, 1] * normals[:, 0]
    j = np.column_stack((normals, cross))
    return j.T @ j

