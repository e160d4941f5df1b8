"""A smooth likelihood field over a grid, sampled bilinearly with its gradient (Hector-style).

Each cell holds M = exp(-d^2 / (2 sigma^2)), d the distance from the cell centre to the nearest
occupied cell centre: 1 on obstacles, falling smoothly to 0. Scan-to-map Gauss-Newton and LM
minimise sum_i (1 - M(T p_i))^2, so the field must be continuous with a usable gradient; a raw
binary occupancy grid is not.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy import ndimage

from scanflow.maps.grid import GridSpec


def field_values(
    occupied: NDArray[np.bool_],
    resolution_m: float,
    sigma_m: float,
    cutoff_m: float | None = None,
) -> NDArray[np.float64]:
    """exp(-d^2 / (2 sigma^2)) per cell, d the distance to the nearest occupied cell centre.

    With `cutoff_m`, cells farther than the cut-off get exactly 0: a cell's value then depends
    only on obstacles within the cut-off, which is what lets maps refresh the field locally.
    """
    if not (np.isfinite(sigma_m) and sigma_m > 0):
        raise ValueError(f"sigma_m must be positive and finite, got {sigma_m}")
    if cutoff_m is not None and not cutoff_m >= 0:
        raise ValueError(f"cutoff_m must be >= 0, got {cutoff_m}")
    if not occupied.any():
        return np.zeros(occupied.shape)
    d = ndimage.distance_transform_edt(~occupied) * resolution_m
    values = np.exp(-0.5 * (d / sigma_m) ** 2)
    if cutoff_m is not None:
        values[d > cutoff_m] = 0.0
    return values


@dataclass(frozen=True, eq=False)
class LikelihoodField:
    """Field values on a grid (cell centres) with bilinear value + gradient lookup."""

    spec: GridSpec
    values: NDArray[np.float64]
    sigma_m: float

    def __post_init__(self) -> None:
        if self.values.shape != self.spec.shape:
            raise ValueError(f"values shape {self.values.shape} != grid shape {self.spec.shape}")

    @staticmethod
    def from_occupied(
        spec: GridSpec,
        occupied: NDArray[np.bool_],
        sigma_m: float,
        cutoff_m: float | None = None,
    ) -> LikelihoodField:
        """Build from a boolean occupancy mask (True = obstacle); see `field_values`."""
        if occupied.shape != spec.shape:
            raise ValueError(f"occupied shape {occupied.shape} != grid shape {spec.shape}")
        return LikelihoodField(
            spec, field_values(occupied, spec.resolution_m, sigma_m, cutoff_m), sigma_m
        )

    @staticmethod
    def from_points(
        points: NDArray[np.float64], resolution_m: float, sigma_m: float, margin_m: float = 1.0
    ) -> LikelihoodField:
        """Rasterise points into a grid covering them (plus a margin) and build the field."""
        spec = GridSpec.covering(points, resolution_m, margin_m)
        occupied = np.zeros(spec.shape, dtype=bool)
        cells = spec.world_to_cell(points)
        cells = cells[spec.contains(cells)]
        occupied[cells[:, 0], cells[:, 1]] = True
        return LikelihoodField.from_occupied(spec, occupied, sigma_m)

    @property
    def is_empty(self) -> bool:
        return not bool(np.any(self.values > 0))

    def sample(
        self, points: NDArray[np.float64]
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Bilinear value and world-frame gradient (dM/dx, dM/dy) at each point.

        Points whose interpolation square leaves the grid get value 0 and gradient 0.
        """
        rows, cols = self.spec.shape
        if rows < 2 or cols < 2:  # no interpolation square fits: nothing is inside
            n = np.asarray(points).reshape(-1, 2).shape[0]
            return np.zeros(n), np.zeros((n, 2))
        rc = self.spec.world_to_continuous(points)
        r0 = np.floor(rc[:, 0]).astype(np.int64)
        c0 = np.floor(rc[:, 1]).astype(np.int64)
        fr = rc[:, 0] - r0
        fc = rc[:, 1] - c0
        inside = (r0 >= 0) & (c0 >= 0) & (r0 < rows - 1) & (c0 < cols - 1)
        r0 = np.where(inside, r0, 0)
        c0 = np.where(inside, c0, 0)
        v = self.values
        v00 = v[r0, c0]
        v01 = v[r0, c0 + 1]
        v10 = v[r0 + 1, c0]
        v11 = v[r0 + 1, c0 + 1]
        value = (1 - fr) * ((1 - fc) * v00 + fc * v01) + fr * ((1 - fc) * v10 + fc * v11)
        inv_res = 1.0 / self.spec.resolution_m
        dx = ((1 - fr) * (v01 - v00) + fr * (v11 - v10)) * inv_res
        dy = ((1 - fc) * (v10 - v00) + fc * (v11 - v01)) * inv_res
        value = np.where(inside, value, 0.0)
        grad = np.column_stack((np.where(inside, dx, 0.0), np.where(inside, dy, 0.0)))
        return value, grad
