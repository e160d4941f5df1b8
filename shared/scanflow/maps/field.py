"""A smooth likelihood field over a grid, sampled bilinearly with its gradient (Hector-style).

Each cell holds M = exp(-d^2 / (2 sigma^2)), d the distance from the cell centre to the nearest
obstacle: 1 on obstacles, falling smoothly to 0. Scan-to-map Gauss-Newton and LM minimise
sum_i (1 - M(T p_i))^2, so the field must be continuous with a usable gradient; a raw binary
occupancy grid is not. Obstacles are either occupied cell centres (`field_values`) or each
occupied cell's mean hit point (`field_from_means`), which keeps walls at sub-cell accuracy.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numba import njit
from numpy.typing import NDArray
from scipy import ndimage

from scanflow.maps.grid import GridSpec


def _check_sigma_cutoff(sigma_m: float, cutoff_m: float | None) -> None:
    if not (np.isfinite(sigma_m) and sigma_m > 0):
        raise ValueError(f"sigma_m must be positive and finite, got {sigma_m}")
    if cutoff_m is not None and not cutoff_m >= 0:
        raise ValueError(f"cutoff_m must be >= 0, got {cutoff_m}")


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
    _check_sigma_cutoff(sigma_m, cutoff_m)
    if not occupied.any():
        return np.zeros(occupied.shape)
    d = ndimage.distance_transform_edt(~occupied) * resolution_m
    values = np.exp(-0.5 * (d / sigma_m) ** 2)
    if cutoff_m is not None:
        values[d > cutoff_m] = 0.0
    return values


@njit(cache=True)
def _splat_means(values, mean_rc, resolution_m, sigma_m, cutoff_m):  # type: ignore[no-untyped-def]
    """values[r, c] = max over means within the cut-off of exp(-d^2 / 2 sigma^2), in place.

    The Gaussian factorises into a row and a column term: 2 (2 reach + 1) exponentials per
    mean instead of one per cell of its neighbourhood.
    """
    rows, cols = values.shape
    reach = math.ceil(cutoff_m / resolution_m) + 1
    k_cells = -0.5 * (resolution_m / sigma_m) ** 2
    limit2 = (cutoff_m / resolution_m) ** 2
    row_term = np.empty(2 * reach + 1)
    col_term = np.empty(2 * reach + 1)
    for k in range(mean_rc.shape[0]):
        mr, mc = mean_rc[k, 0], mean_rc[k, 1]
        r0, c0 = math.floor(mr + 0.5) - reach, math.floor(mc + 0.5) - reach
        for j in range(2 * reach + 1):
            row_term[j] = math.exp(k_cells * (r0 + j - mr) ** 2)
            col_term[j] = math.exp(k_cells * (c0 + j - mc) ** 2)
        for r in range(max(r0, 0), min(r0 + 2 * reach + 1, rows)):
            dr = r - mr
            # The columns inside the cut-off circle on this row.
            if dr * dr > limit2:
                continue
            half = math.sqrt(limit2 - dr * dr)
            c_lo = max(math.ceil(mc - half), 0)
            c_hi = min(math.floor(mc + half), cols - 1) + 1
            if c_hi <= c_lo:
                continue
            # Unsigned indices: no negative-index wrap-around check, so the loop vectorises.
            row, rt = values[r], row_term[r - r0]
            first, offset = np.uint64(c_lo), np.uint64(c_lo - c0)
            for i in range(np.uint64(c_hi - c_lo)):
                c = first + i
                row[c] = max(row[c], rt * col_term[offset + i])


def field_from_means(
    shape: tuple[int, int],
    mean_rc: NDArray[np.float64],
    resolution_m: float,
    sigma_m: float,
    cutoff_m: float,
    dtype: type[np.floating] = np.float64,
) -> NDArray[np.floating]:
    """exp(-d^2 / (2 sigma^2)) per cell, d the distance to the nearest of the `mean_rc` points.

    `mean_rc` (K, 2) are fractional (row, col) with cell centres at integers (one per occupied
    cell: its mean hit point, or its centre). Only cells within `cutoff_m` of a point are
    written, so the cost is K * (cut-off in cells)^2, whatever the grid's size; with integer
    `mean_rc` the result equals `field_values` of those cells (to rounding). Maps keep their
    fields as float32 (`dtype`): half the memory, and ample precision for values in [0, 1].
    """
    _check_sigma_cutoff(sigma_m, cutoff_m)
    values = np.zeros(shape, dtype=dtype)
    means = np.ascontiguousarray(mean_rc, dtype=np.float64).reshape(-1, 2)
    if means.shape[0] and values.size:
        _splat_means(values, means, float(resolution_m), float(sigma_m), float(cutoff_m))
    return values


@dataclass(frozen=True, eq=False)
class LikelihoodField:
    """Field values on a grid (cell centres) with bilinear value + gradient lookup."""

    spec: GridSpec
    values: NDArray[np.floating]  # float64, or float32 for a map's fields
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
        """True when no value is above 0: no obstacle within reach, nothing to match against."""
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
