"""SE(2) properties: group laws, matrices, point transforms, interpolation, array helpers."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from scanflow.geometry import (
    Pose2D,
    angle_diff,
    compose_arrays,
    interpolate_arrays,
    normalize_angle,
    normalize_angles,
    transform_points_per_pose,
)

coords = st.floats(-100.0, 100.0, allow_nan=False)
angles = st.floats(-math.pi, math.pi, allow_nan=False)
poses = st.builds(Pose2D, coords, coords, angles)
fractions = st.floats(0.0, 1.0)
points = st.lists(st.tuples(coords, coords), min_size=1, max_size=20).map(np.array)


def assert_pose_close(a: Pose2D, b: Pose2D, atol: float = 1e-9) -> None:
    assert a.x == pytest.approx(b.x, abs=atol)
    assert a.y == pytest.approx(b.y, abs=atol)
    assert abs(angle_diff(a.theta, b.theta)) <= atol


@given(st.floats(-1e6, 1e6))
def test_normalize_angle_range_and_equivalence(angle: float) -> None:
    wrapped = normalize_angle(angle)
    assert -math.pi <= wrapped < math.pi
    assert math.cos(wrapped) == pytest.approx(math.cos(angle), abs=1e-6)
    assert math.sin(wrapped) == pytest.approx(math.sin(angle), abs=1e-6)
    assert normalize_angles(np.array([angle]))[0] == wrapped


def test_normalize_angle_at_the_seam() -> None:
    assert normalize_angle(math.pi) == -math.pi
    assert normalize_angle(-math.pi) == -math.pi
    just_below = math.nextafter(-math.pi, -4.0)  # the modulo rounds this one up to 2*pi
    assert -math.pi <= normalize_angle(just_below) < math.pi
    assert -math.pi <= normalize_angles(np.array([just_below]))[0] < math.pi


@given(poses)
def test_inverse_gives_identity(p: Pose2D) -> None:
    assert_pose_close(p * p.inverse(), Pose2D.identity())
    assert_pose_close(p.inverse() * p, Pose2D.identity())


@given(poses, poses, poses)
def test_composition_is_associative(a: Pose2D, b: Pose2D, c: Pose2D) -> None:
    assert_pose_close((a * b) * c, a * (b * c), atol=1e-7)


@given(poses, poses)
def test_relative_to(a: Pose2D, b: Pose2D) -> None:
    rel = a.relative_to(b)
    assert_pose_close(rel, b.inverse() * a)
    assert_pose_close(b * rel, a, atol=1e-7)


@given(poses, poses)
def test_matrix_round_trip_and_homomorphism(a: Pose2D, b: Pose2D) -> None:
    assert_pose_close(Pose2D.from_matrix(a.to_matrix()), a)
    np.testing.assert_allclose((a * b).to_matrix(), a.to_matrix() @ b.to_matrix(), atol=1e-9)
    assert_pose_close(Pose2D.from_matrix(a.to_matrix()[:2]), a)


@given(poses, points)
def test_transform_points_matches_the_matrix(p: Pose2D, pts: np.ndarray) -> None:
    homogeneous = np.column_stack((pts, np.ones(len(pts))))
    expected = (p.to_matrix() @ homogeneous.T).T[:, :2]
    np.testing.assert_allclose(p.transform_points(pts), expected, atol=1e-9)


@given(poses, poses, points)
def test_transform_points_composes(a: Pose2D, b: Pose2D, pts: np.ndarray) -> None:
    np.testing.assert_allclose(
        (a * b).transform_points(pts), a.transform_points(b.transform_points(pts)), atol=1e-7
    )


@given(poses, poses)
def test_interpolation_endpoints(a: Pose2D, b: Pose2D) -> None:
    assert_pose_close(a.interpolate(b, 0.0), a)
    assert_pose_close(a.interpolate(b, 1.0), b, atol=1e-7)


@given(poses, poses, fractions)
def test_interpolation_follows_the_shortest_arc(a: Pose2D, b: Pose2D, f: float) -> None:
    mid = a.interpolate(b, f)
    assert angle_diff(mid.theta, a.theta) == pytest.approx(
        f * angle_diff(b.theta, a.theta), abs=1e-9
    )
    assert mid.x == pytest.approx(a.x + f * (b.x - a.x))


def test_interpolation_is_continuous_across_pi() -> None:
    a, b = Pose2D(0, 0, math.radians(179)), Pose2D(0, 0, math.radians(-179))
    f = np.linspace(0.0, 1.0, 101)
    _, _, theta = interpolate_arrays(a, b, f)
    assert np.all(np.abs(theta) >= math.radians(179) - 1e-12)  # never swings through 0
    assert abs(a.interpolate(b, 0.5).theta) == pytest.approx(math.pi)
    steps = np.abs(normalize_angles(np.diff(theta)))
    assert np.all(steps == pytest.approx(math.radians(2) / 100))


@given(st.lists(st.tuples(poses, poses), min_size=1, max_size=10))
def test_compose_arrays_equals_scalar_compose(pairs: list[tuple[Pose2D, Pose2D]]) -> None:
    left = np.array([a.to_array() for a, _ in pairs])
    right = np.array([b.to_array() for _, b in pairs])
    got = compose_arrays(left, right)
    for row, (a, b) in zip(got, pairs, strict=True):
        assert_pose_close(Pose2D.from_array(row), a * b, atol=1e-9)
    broadcast = compose_arrays(left[0], right)
    for row, (_, b) in zip(broadcast, pairs, strict=True):
        assert_pose_close(Pose2D.from_array(row), pairs[0][0] * b, atol=1e-9)


@given(st.lists(st.tuples(poses, st.tuples(coords, coords)), min_size=1, max_size=10))
def test_transform_points_per_pose(items: list[tuple[Pose2D, tuple[float, float]]]) -> None:
    xyt = np.array([p.to_array() for p, _ in items])
    pts = np.array([pt for _, pt in items])
    got = transform_points_per_pose(xyt[:, 0], xyt[:, 1], xyt[:, 2], pts)
    expected = np.vstack([p.transform_points(np.array([pt])) for p, pt in items])
    np.testing.assert_allclose(got, expected, atol=1e-9)


@pytest.mark.parametrize("field", ["x", "y", "theta"])
@pytest.mark.parametrize("bad", [math.nan, math.inf])
def test_non_finite_pose_names_the_field(field: str, bad: float) -> None:
    with pytest.raises(ValueError, match=f"Pose2D.{field}"):
        Pose2D(**{field: bad})


def test_bad_shapes_are_rejected() -> None:
    with pytest.raises(ValueError, match="3x3"):
        Pose2D.from_matrix(np.eye(2))
    with pytest.raises(ValueError, match="3 values"):
        Pose2D.from_array([1.0, 2.0])
