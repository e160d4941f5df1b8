"""SE(2) rigid motions: compose, invert, interpolate, exp/log, and apply them to points.

`Pose2D` is the scalar type used at API boundaries; the `*_arrays` helpers work on
many poses at once (columns x, y, theta) so hot loops stay vectorised.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

TWO_PI = 2.0 * math.pi


def normalize_angle(angle_rad: float) -> float:
    """Wrap an angle to [-pi, pi)."""
    wrapped = (angle_rad + math.pi) % TWO_PI - math.pi
    # The modulo can round up to 2*pi for inputs just below -pi; keep the interval half-open.
    return wrapped - TWO_PI if wrapped >= math.pi else wrapped


def normalize_angles(angles_rad: ArrayLike) -> NDArray[np.float64]:
    """Vectorised `normalize_angle`."""
    a = np.asarray(angles_rad, dtype=np.float64)
    wrapped = (a + np.pi) % TWO_PI - np.pi
    return np.where(wrapped >= np.pi, wrapped - TWO_PI, wrapped)


def angle_diff(a_rad: float, b_rad: float) -> float:
    """Signed shortest rotation from b to a, in [-pi, pi)."""
    return normalize_angle(a_rad - b_rad)


@dataclass(frozen=True, slots=True)
class Pose2D:
    """A rigid motion in the plane: rotate by `theta` then translate by (x, y).

    As a frame pose `T_a_b` it maps points from frame b into frame a, so
    `T_a_c = T_a_b * T_b_c`.
    """

    x: float = 0.0
    y: float = 0.0
    theta: float = 0.0

    def __post_init__(self) -> None:
        for name in ("x", "y", "theta"):
            value = getattr(self, name)
            if not math.isfinite(value):
                raise ValueError(f"Pose2D.{name} must be finite, got {value!r}")
        object.__setattr__(self, "x", float(self.x))
        object.__setattr__(self, "y", float(self.y))
        object.__setattr__(self, "theta", normalize_angle(float(self.theta)))

    @staticmethod
    def identity() -> Pose2D:
        """The identity motion (a new instance; `IDENTITY` is the shared one)."""
        return Pose2D()

    def __mul__(self, other: Pose2D) -> Pose2D:
        """Composition `self ∘ other`."""
        if not isinstance(other, Pose2D):
            return NotImplemented
        c, s = math.cos(self.theta), math.sin(self.theta)
        return Pose2D(
            self.x + c * other.x - s * other.y,
            self.y + s * other.x + c * other.y,
            self.theta + other.theta,
        )

    def inverse(self) -> Pose2D:
        """The inverse motion, so `self * self.inverse()` is the identity."""
        c, s = math.cos(self.theta), math.sin(self.theta)
        return Pose2D(-c * self.x - s * self.y, s * self.x - c * self.y, -self.theta)

    def relative_to(self, other: Pose2D) -> Pose2D:
        """The motion from `other` to `self`: `other.inverse() * self`."""
        return other.inverse() * self

    def transform_points(self, points: ArrayLike) -> NDArray[np.float64]:
        """Apply this motion to an (N, 2) array of points."""
        p = np.asarray(points, dtype=np.float64).reshape(-1, 2)
        c, s = math.cos(self.theta), math.sin(self.theta)
        out = np.empty_like(p)
        out[:, 0] = c * p[:, 0] - s * p[:, 1] + self.x
        out[:, 1] = s * p[:, 0] + c * p[:, 1] + self.y
        return out

    def rotation_matrix(self) -> NDArray[np.float64]:
        """The 2x2 rotation matrix of `theta`."""
        c, s = math.cos(self.theta), math.sin(self.theta)
        return np.array([[c, -s], [s, c]])

    def frame_jacobian(self) -> NDArray[np.float64]:
        """diag(R, 1): how a pose's (x, y, theta) error turns when the pose is re-expressed
        through this frame (a covariance C becomes J C J^T)."""
        jacobian = np.eye(3)
        jacobian[:2, :2] = self.rotation_matrix()
        return jacobian

    def to_matrix(self) -> NDArray[np.float64]:
        """Homogeneous 3x3 matrix."""
        m = np.eye(3)
        m[:2, :2] = self.rotation_matrix()
        m[:2, 2] = (self.x, self.y)
        return m

    @staticmethod
    def from_matrix(matrix: ArrayLike) -> Pose2D:
        """From a homogeneous 3x3 (or 2x3) matrix; the rotation part is re-orthogonalised."""
        m = np.asarray(matrix, dtype=np.float64)
        if m.shape not in ((3, 3), (2, 3)):
            raise ValueError(f"matrix must be 3x3 or 2x3, got shape {m.shape}")
        return Pose2D(m[0, 2], m[1, 2], math.atan2(m[1, 0] - m[0, 1], m[0, 0] + m[1, 1]))

    def to_array(self) -> NDArray[np.float64]:
        """(x, y, theta) as a float64 array of shape (3,)."""
        return np.array([self.x, self.y, self.theta])

    @staticmethod
    def from_array(values: ArrayLike) -> Pose2D:
        """From 3 values (x, y, theta) in any shape; ValueError for any other count."""
        v = np.asarray(values, dtype=np.float64).reshape(-1)
        if v.shape != (3,):
            raise ValueError(f"pose array must have 3 values (x, y, theta), got {v.shape}")
        return Pose2D(v[0], v[1], v[2])

    def translation_norm(self) -> float:
        """Length of the translation (x, y)."""
        return math.hypot(self.x, self.y)

    def interpolate(self, other: Pose2D, fraction: float) -> Pose2D:
        """Pose a `fraction` of the way to `other`: lerp in translation, shortest arc in heading."""
        x, y, th = interpolate_arrays(self, other, np.asarray([fraction], dtype=np.float64))
        return Pose2D(x[0], y[0], th[0])


IDENTITY = Pose2D()
"""The identity pose (immutable, so one shared instance serves as a default everywhere)."""


def interpolate_arrays(
    a: Pose2D, b: Pose2D, fractions: ArrayLike
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """Many poses between `a` and `b` at once (the 2D slerp: linear in the shortest heading arc)."""
    f = np.asarray(fractions, dtype=np.float64)
    dtheta = angle_diff(b.theta, a.theta)
    x = a.x + f * (b.x - a.x)
    y = a.y + f * (b.y - a.y)
    theta = normalize_angles(a.theta + f * dtheta)
    return x, y, theta


def compose_arrays(
    poses_xyt: NDArray[np.float64], other_xyt: NDArray[np.float64]
) -> NDArray[np.float64]:
    """Row-wise composition of (N, 3) pose arrays (broadcasts a single row)."""
    a = np.atleast_2d(poses_xyt)
    b = np.atleast_2d(other_xyt)
    c, s = np.cos(a[:, 2]), np.sin(a[:, 2])
    out = np.empty(np.broadcast_shapes(a.shape, b.shape))
    out[:, 0] = a[:, 0] + c * b[:, 0] - s * b[:, 1]
    out[:, 1] = a[:, 1] + s * b[:, 0] + c * b[:, 1]
    out[:, 2] = normalize_angles(a[:, 2] + b[:, 2])
    return out


def transform_points_per_pose(
    x: NDArray[np.float64],
    y: NDArray[np.float64],
    theta: NDArray[np.float64],
    points: NDArray[np.float64],
) -> NDArray[np.float64]:
    """Apply pose i (x[i], y[i], theta[i]) to point i; used to move each beam by its own pose."""
    c, s = np.cos(theta), np.sin(theta)
    out = np.empty((points.shape[0], 2))
    out[:, 0] = c * points[:, 0] - s * points[:, 1] + x
    out[:, 1] = s * points[:, 0] + c * points[:, 1] + y
    return out


def relative_arrays(
    a_xyt: NDArray[np.float64], b_xyt: NDArray[np.float64]
) -> NDArray[np.float64]:
    """Row-wise a^-1 * b for (N, 3) pose arrays (heading not wrapped: exact differences)."""
    c, s = np.cos(a_xyt[:, 2]), np.sin(a_xyt[:, 2])
    dx, dy = b_xyt[:, 0] - a_xyt[:, 0], b_xyt[:, 1] - a_xyt[:, 1]
    return np.column_stack((c * dx + s * dy, -s * dx + c * dy, b_xyt[:, 2] - a_xyt[:, 2]))


# SE(2) exponential and logarithm: motion under a constant body-frame twist. A robot moving with
# constant forward/lateral speed and yaw rate follows a circular arc, not a chord; `se2_exp`
# gives that arc exactly (the constant-velocity model, the simulator's odometry).
_SMALL_ANGLE_RAD = 1e-6


def _arc_coefficients(
    phi_rad: NDArray[np.float64],
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """sin(phi)/phi and (1 - cos(phi))/phi, with their Taylor series near zero."""
    small = np.abs(phi_rad) < _SMALL_ANGLE_RAD
    safe = np.where(small, 1.0, phi_rad)
    a = np.where(small, 1.0 - phi_rad**2 / 6.0, np.sin(safe) / safe)
    b = np.where(small, phi_rad / 2.0, (1.0 - np.cos(safe)) / safe)
    return a, b


def se2_exp(twist: ArrayLike) -> NDArray[np.float64]:
    """Relative poses (N, 3) reached by integrating twists (N, 3) = (dx, dy, dtheta) over unit time.

    Row i is the pose after moving with body velocity (dx, dy) and yaw rate dtheta for one unit.
    """
    xi = np.atleast_2d(np.asarray(twist, dtype=np.float64))
    if xi.shape[-1] != 3:
        raise ValueError(f"twist must have 3 columns (dx, dy, dtheta), got shape {xi.shape}")
    a, b = _arc_coefficients(xi[:, 2])
    out = np.empty_like(xi)
    out[:, 0] = a * xi[:, 0] - b * xi[:, 1]
    out[:, 1] = b * xi[:, 0] + a * xi[:, 1]
    out[:, 2] = normalize_angles(xi[:, 2])
    return out


def se2_log(poses_xyt: ArrayLike) -> NDArray[np.float64]:
    """Twists (N, 3) whose `se2_exp` gives the relative poses (N, 3), heading on the short arc."""
    p = np.atleast_2d(np.asarray(poses_xyt, dtype=np.float64))
    if p.shape[-1] != 3:
        raise ValueError(f"poses must have 3 columns (x, y, theta), got shape {p.shape}")
    phi = normalize_angles(p[:, 2])
    a, b = _arc_coefficients(phi)
    det = a * a + b * b
    out = np.empty_like(p)
    out[:, 0] = (a * p[:, 0] + b * p[:, 1]) / det
    out[:, 1] = (-b * p[:, 0] + a * p[:, 1]) / det
    out[:, 2] = phi
    return out
