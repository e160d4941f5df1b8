"""The matching entry point: registration, input validation, statuses for bad input."""

import math

import numpy as np
import pytest
from scanflow.geometry import Pose2D
from scanflow.matching import DEFAULT_METHOD, MatchInputError, MatchStatus, available_methods, match
from scanflow.matching.api import as_points, target_points
from scanflow.matching.checks import analyse_hessian, line_hessian
from scanflow.scan import LaserScan
from scanflow.sim import cast_rays, get_world


def _square(n: int = 200) -> np.ndarray:
    t = np.linspace(0, 4, n // 4, endpoint=False)
    z = np.zeros_like(t)
    return np.vstack([np.c_[t, z], np.c_[z + 4, t], np.c_[4 - t, z + 4], np.c_[z, 4 - t]])


def test_default_and_own_methods_are_registered() -> None:
    assert DEFAULT_METHOD in available_methods()
    assert {"svd", "icp", "plicp", "csm+plicp"} <= set(available_methods())


def test_unknown_method_names_the_choices() -> None:
    with pytest.raises(MatchInputError, match=r"unknown method 'nope'.*plicp"):
        match(_square(), _square(), method="nope")


@pytest.mark.parametrize("guess", [(math.nan, 0.0, 0.0), (0.0, 0.0), "x"])
def test_bad_initial_guess_is_a_clear_error(guess: object) -> None:
    with pytest.raises(MatchInputError, match="initial_guess"):
        match(_square(), _square(), guess)


def test_wrong_shape_is_a_clear_error() -> None:
    with pytest.raises(MatchInputError, match=r"source must have shape \(N, 2\)"):
        match(np.zeros((5, 3)), _square())


@pytest.mark.parametrize("method", ["icp", "plicp", "csm+plicp"])
def test_empty_and_tiny_inputs_give_a_status(method: str) -> None:
    assert match(np.zeros((0, 2)), _square(), method=method).status is not MatchStatus.OK
    assert match(_square(), [], method=method).status is MatchStatus.EMPTY_MAP
    tiny = match(_square()[:2], _square(), method=method)
    assert tiny.status is MatchStatus.TOO_FEW_POINTS and np.all(np.isinf(np.diag(tiny.covariance)))


def test_nan_rows_are_dropped_not_propagated() -> None:
    src = _square()
    src[::7] = np.nan
    r = match(src, _square(), Pose2D(0.05, 0.0, 0.01))
    assert r.ok and r.pose.translation_norm() < 0.01


class _Map:
    def __init__(self, points: np.ndarray) -> None:
        self._points = points

    def likelihood_field(self, level: int = 0) -> object:
        raise AssertionError("point methods must use occupied_points()")

    def occupied_points(self) -> np.ndarray:
        return self._points


def test_map_target_uses_occupied_points() -> None:
    r = match(_square(), _Map(_square()), Pose2D(0.05, -0.05, 0.02), method="plicp")
    assert r.ok and r.pose.translation_norm() < 0.01
    assert match(_square(), _Map(np.zeros((0, 2))), method="icp").status is MatchStatus.EMPTY_MAP


def test_target_without_points_is_a_clear_error() -> None:
    with pytest.raises(MatchInputError, match="occupied_points"):
        target_points(object())


def test_corridor_hessian_weak_direction_is_along_the_walls() -> None:
    x = np.linspace(-5, 5, 50)
    pts = np.r_[np.c_[x, np.ones(50)], np.c_[x, -np.ones(50)]]
    normals = np.tile([0.0, 1.0], (100, 1))
    cond = analyse_hessian(line_hessian(pts, normals), 3.0)
    assert cond.degenerate
    assert np.allclose(cond.weak_direction, (1.0, 0.0, 0.0), atol=1e-6)


def test_as_points_gives_one_array_type_whatever_comes_in() -> None:
    """Read-only (decoded from the wire) and strided arrays come out C-contiguous, writable and
    equal, so numba compiles no second kernel for them; a fitting array is not copied."""
    fitting = np.arange(12.0).reshape(6, 2)
    assert as_points(fitting, "points") is fitting
    read_only = fitting.copy()
    read_only.flags.writeable = False
    strided = np.arange(24.0).reshape(6, 4)[:, ::2]
    for given in (read_only, strided, fitting.astype(np.float32)):
        points = as_points(given, "points")
        assert points.flags.c_contiguous and points.flags.writeable
        assert points.dtype == np.float64
        np.testing.assert_array_equal(points, given)


def _mounted_scan(robot: Pose2D, mount: Pose2D) -> LaserScan:
    """A zero-duration 270 deg scan of the rooms world by a lidar at `mount` on the robot."""
    sensor = robot * mount
    angles = np.linspace(-0.75 * math.pi, 0.75 * math.pi, 541)
    origin = np.tile([sensor.x, sensor.y], (angles.size, 1))
    ranges = cast_rays(origin, angles + sensor.theta, get_world("rooms").segments, 20.0)
    return LaserScan(ranges, float(angles[0]), float(angles[1] - angles[0]), range_max_m=20.0,
                     mount=mount)


@pytest.mark.parametrize("method", ["plicp", "icp", "csm+plicp"])
def test_mounted_scans_give_the_robots_motion(method: str) -> None:
    """Two scans from a lidar 0.5 m off the robot's centre: match() returns the robot's motion
    (not the sensor's), expressed through the target's sensor frame and back."""
    mount = Pose2D(0.5, -0.2, math.radians(30.0))
    a, b = Pose2D(7.3, 2.1, 0.2), Pose2D(7.6, 2.3, 0.45)
    truth = b.relative_to(a)
    source, target = _mounted_scan(b, mount), _mounted_scan(a, mount)
    result = match(source, target, truth * Pose2D(0.05, -0.04, 0.03), method=method)
    assert result.ok, result.message
    e = result.pose.relative_to(truth)
    assert e.translation_norm() < 0.01 and abs(e.theta) < math.radians(0.2)
    sensor_motion = mount.inverse() * truth * mount
    assert sensor_motion.relative_to(truth).translation_norm() > 0.1  # the mount matters here
    # The same match run by hand in the target's sensor frame, then carried to the robot's.
    by_hand = match(as_points(source, "source"), target.points(),
                    mount.inverse() * truth * Pose2D(0.05, -0.04, 0.03), method=method)
    assert (mount * by_hand.pose).relative_to(result.pose).translation_norm() < 1e-12
    rot = np.eye(3)
    rot[:2, :2] = mount.rotation_matrix()
    np.testing.assert_allclose(result.covariance, rot @ by_hand.covariance @ rot.T, atol=1e-15)
