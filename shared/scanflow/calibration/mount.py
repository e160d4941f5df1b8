"""The lidar's mount on the robot (T_base_laser) from paired motions: 2D hand-eye calibration.

Over the same interval the wheels measure the robot's motion A and scan matching the lidar's
motion B. The lidar rides on the robot, so A X = X B for the mount X (Censi, Franchi, Marchionni
and Oriolo 2013, without their odometry parameters). Rotations commute in 2D, so the rotation
part only says theta_A = theta_B (a check on each pair); the translation part
    (R_A - I) t_X - R(phi_X) t_B = -t_A
is linear in (t_X, cos phi_X, sin phi_X). R_A there is built from the scan match's turn: the
two agree in theory, and the match's is far more precise than the wheels' (on the simulator
with its 1 % odometry error, this cuts the mount's error from 1 cm / 0.7 deg to 0.3 cm /
0.03 deg). t_X is eliminated in closed form and phi_X found on the unit circle (dense search,
then refined), which is the exact constrained least squares.
Observability: t_X needs turning (R_A - I has singular values 2 |sin(theta_A / 2)|), phi_X
needs driving: lidar translation that no choice of t_X explains as turning (turns about one
point, on the spot or along arcs of one radius, move an offset lidar yet leave a whole family
of mounts, R(phi_X)^T (t_X - c) fixed). Pairs whose rotations disagree by more than
`max_rotation_gap_rad` are dropped (a failed match or an odometry glitch); then the fit
alternates with trimming the pairs whose residual exceeds 3x the median (and TRIM_FLOOR_M) until
the kept set settles.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from enum import StrEnum

import numpy as np
from numpy.typing import NDArray

from scanflow.geometry import Pose2D, normalize_angles

# Summed 4 sin^2(theta / 2) of the pairs' turns below this: t_X is not observable
# (e.g. one 5 deg turn gives 0.0076, twenty of them 0.15).
MIN_TURNING = 0.05
# Summed squared lidar translation not explained by turning below this (m^2): phi_X is not
# observable.
MIN_DRIVING_M2 = 0.05
MIN_PAIRS = 5
# A pair is trimmed when its residual exceeds 3x the median and this (the range noise of a
# planar lidar, so exact or nearly exact data keep every pair).
TRIM_FLOOR_M = 0.005


class MountStatus(StrEnum):
    OK = "ok"
    TOO_FEW_PAIRS = "too_few_pairs"
    NO_TURNING = "no_turning"  # the position on the robot cannot be told
    NO_DRIVING = "no_driving"  # the yaw on the robot cannot be told


@dataclass(frozen=True)
class MountEstimate:
    """The fitted mount, its uncertainty and what it rests on."""

    mount: Pose2D
    status: MountStatus
    pairs_used: int
    pairs_given: int
    residual_rms_m: float
    std_xy_m: tuple[float, float]
    std_yaw_rad: float
    message: str = ""

    @property
    def ok(self) -> bool:
        """True for status OK: enough pairs, with both the position and the yaw observable."""
        return self.status is MountStatus.OK


def _design(
    robot: NDArray[np.float64], sensor: NDArray[np.float64]
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """(A1, A2, b), (2n, 2) x2 and (2n,), of A1 t_X + A2 (cos, sin) = b for (n, 3) motions."""
    # The turn is the scan match's: the same as the odometry's in theory, far more precise.
    c, s = np.cos(sensor[:, 2]), np.sin(sensor[:, 2])
    a1 = np.zeros((len(robot), 2, 2))
    a1[:, 0, 0], a1[:, 0, 1], a1[:, 1, 0], a1[:, 1, 1] = c - 1.0, -s, s, c - 1.0
    bx, by = sensor[:, 0], sensor[:, 1]
    a2 = np.zeros((len(robot), 2, 2))
    a2[:, 0, 0], a2[:, 0, 1], a2[:, 1, 0], a2[:, 1, 1] = -bx, by, -by, -bx
    return a1.reshape(-1, 2), a2.reshape(-1, 2), -robot[:, :2].reshape(-1)


def _fit(
    robot: NDArray[np.float64], sensor: NDArray[np.float64]
) -> tuple[NDArray[np.float64], float]:
    """(t_X, phi_X) of the constrained least squares."""
    a1, a2, b = _design(robot, sensor)
    # t_X = N^-1 A1' (b - A2 u) with N = A1' A1 (2 x 2); what is left is quadratic in u.
    # Normal equations only: memory stays O(n), not the (2n)^2 projector.
    n_inv = np.linalg.pinv(a1.T @ a1)
    cross = a2.T @ a1
    m = a2.T @ a2 - cross @ n_inv @ cross.T
    g = a2.T @ b - cross @ n_inv @ (a1.T @ b)
    # f(phi) = u' M u - 2 g' u on the unit circle: coarse grid, then two finer ones.
    best, span = 0.0, math.pi
    for steps in (3600, 2001, 2001):
        phi = best + np.linspace(-span, span, steps)
        u = np.stack((np.cos(phi), np.sin(phi)))
        cost = np.einsum("in,ij,jn->n", u, m, u) - 2.0 * g @ u
        best = float(phi[np.argmin(cost)])
        span = 4.0 * (2.0 * span / (steps - 1))
    u = np.array([math.cos(best), math.sin(best)])
    return n_inv @ (a1.T @ (b - a2 @ u)), best


def _residuals(
    robot: NDArray[np.float64], sensor: NDArray[np.float64], t: NDArray[np.float64], phi: float
) -> NDArray[np.float64]:
    """Per-pair norm of A1 t_X + A2 (cos, sin) - b."""
    a1, a2, b = _design(robot, sensor)
    r = (a1 @ t + a2 @ np.array([math.cos(phi), math.sin(phi)]) - b).reshape(-1, 2)
    return np.hypot(r[:, 0], r[:, 1])


def _driving(robot: NDArray[np.float64], sensor: NDArray[np.float64]) -> float:
    """Information on phi_X with t_X unknown (m^2): the summed squared lidar translation left
    once turning about any one point explains what it can (the Schur complement; the same for
    every phi_X). Straight stretches keep theirs, turns about one point none."""
    a1, a2, _ = _design(robot, sensor)
    v = a2[:, 1]  # d/d phi of A2 (cos, sin) at phi = 0
    proj = a1.T @ v
    return float(v @ v - proj @ np.linalg.pinv(a1.T @ a1) @ proj)


def _std(robot: NDArray[np.float64], sensor: NDArray[np.float64], phi: float,
         rms: float) -> tuple[tuple[float, float], float]:
    """Linearised standard deviations of t_X and phi_X from the residual spread."""
    a1, a2, _ = _design(robot, sensor)
    u_perp = np.array([-math.sin(phi), math.cos(phi)])  # d(cos, sin) / d phi
    jac = np.column_stack((a1, a2 @ u_perp))
    dof = max(len(jac) - 3, 1)
    sigma2 = rms**2 * len(robot) / dof
    cov = sigma2 * np.linalg.pinv(jac.T @ jac)
    return (math.sqrt(cov[0, 0]), math.sqrt(cov[1, 1])), math.sqrt(cov[2, 2])


def estimate_mount(
    robot_motions: list[Pose2D],
    sensor_motions: list[Pose2D],
    max_rotation_gap_rad: float = math.radians(2.0),
) -> MountEstimate:
    """The mount X with A_i X = X B_i for robot motions A_i (odometry) and sensor motions B_i
    (scan matching) over the same intervals; see the module docstring."""
    if len(robot_motions) != len(sensor_motions):
        raise ValueError(
            f"robot_motions and sensor_motions differ in length: {len(robot_motions)} != "
            f"{len(sensor_motions)}"
        )
    given = len(robot_motions)
    robot = np.array([p.to_array() for p in robot_motions]).reshape(-1, 3)
    sensor = np.array([p.to_array() for p in sensor_motions]).reshape(-1, 3)
    if not (np.all(np.isfinite(robot)) and np.all(np.isfinite(sensor))):
        raise ValueError("motions must be finite")
    agree = np.abs(normalize_angles(robot[:, 2] - sensor[:, 2])) <= max_rotation_gap_rad
    robot, sensor = robot[agree], sensor[agree]

    def failed(status: MountStatus, message: str) -> MountEstimate:
        nan = math.nan
        return MountEstimate(Pose2D(), status, len(robot), given, nan, (nan, nan), nan, message)

    if len(robot) < MIN_PAIRS:
        return failed(MountStatus.TOO_FEW_PAIRS, (
            f"{len(robot)} of {given} pairs agree on their rotation within "
            f"{math.degrees(max_rotation_gap_rad):.1f} deg; need {MIN_PAIRS}"
        ))
    keep = np.ones(len(robot), dtype=bool)
    for _ in range(5):  # fit, trim against the fit, until the kept set settles
        t, phi = _fit(robot[keep], sensor[keep])
        residual = _residuals(robot, sensor, t, phi)
        trimmed = residual <= max(3.0 * float(np.median(residual[keep])), TRIM_FLOOR_M)
        if np.count_nonzero(trimmed) < MIN_PAIRS or np.array_equal(trimmed, keep):
            break
        keep = trimmed
    robot, sensor = robot[keep], sensor[keep]
    # Observability of the pairs kept: trimming can drop every turn (or every straight stretch).
    turning = float(np.sum(4.0 * np.sin(sensor[:, 2] / 2.0) ** 2))
    if turning < MIN_TURNING:
        return failed(MountStatus.NO_TURNING, (
            f"the robot hardly turned (sum of 4 sin^2(theta/2) = {turning:.4f} < {MIN_TURNING}):"
            " the mount's position cannot be told; drive turns"
        ))
    driving = _driving(robot, sensor)
    if driving < MIN_DRIVING_M2:
        return failed(MountStatus.NO_DRIVING, (
            f"the lidar hardly moved other than by turning about one point (sum of squared "
            f"translations left {driving:.4f} m^2 < {MIN_DRIVING_M2}): the mount's yaw cannot "
            "be told; drive straight stretches"
        ))
    t, phi = _fit(robot, sensor)
    rms = float(np.sqrt(np.mean(_residuals(robot, sensor, t, phi) ** 2)))
    std_xy, std_yaw = _std(robot, sensor, phi, rms)
    return MountEstimate(
        Pose2D(float(t[0]), float(t[1]), phi), MountStatus.OK, len(robot), given, rms,
        std_xy, std_yaw,
    )
