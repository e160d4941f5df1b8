"""Pose covariances: sigma^2 H^-1 and Censi's line-fit covariance against finite differences and
the spread of simulated least-squares fits."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from numpy.typing import NDArray
from scanflow.geometry import Pose2D
from scanflow.matching.correspondence import MAD_TO_SIGMA, GridIndex, target_lines
from scanflow.matching.covariance import (
    least_squares_covariance,
    line_fit_covariance,
    pose_parameter_jacobian,
    residual_variance,
    unknown_covariance,
)

# Three straight walls, none parallel to another: every pose direction is constrained.
WALLS = [((0.0, 0.0), (0.0, 3.0)), ((0.3, 0.0), (3.0, 0.0)), ((3.0, 0.5), (1.5, 3.0))]


def _on_walls(fractions: NDArray[np.float64]) -> NDArray[np.float64]:
    """Points at the given fractions along each of WALLS."""
    return np.vstack([np.asarray(a) + fractions[:, None] * (np.subtract(b, a)) for a, b in WALLS])


def _line_fit(
    target: NDArray[np.float64], neighbours: NDArray[np.int64], like: NDArray[np.float64]
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """(normals, centroids) of a total-least-squares fit through each row's neighbours (numpy's
    eigh of the scatter), each normal on the side of the same row of `like`."""
    valid = neighbours >= 0
    pts = np.where(valid[..., None], target[np.maximum(neighbours, 0)], 0.0)
    centres = pts.sum(axis=1) / valid.sum(axis=1)[:, None]
    centred = np.where(valid[..., None], pts - centres[:, None], 0.0)
    normals = np.linalg.eigh(np.einsum("mki,mkj->mij", centred, centred))[1][:, :, 0]
    return normals * np.sign(np.sum(normals * like, axis=1))[:, None], centres


def _point_to_line_increment(
    moved: NDArray[np.float64],
    weights: NDArray[np.float64],
    normals: NDArray[np.float64],
    centres: NDArray[np.float64],
) -> NDArray[np.float64]:
    """The left increment d (T <- Exp(d) T) minimising sum w (n . (Exp(d) p - c))^2, by
    Gauss-Newton on the exact rotation."""
    d = np.zeros(3)
    for _ in range(5):
        c, s = math.cos(d[2]), math.sin(d[2])
        p = moved @ np.array([[c, s], [-s, c]]) + d[:2]
        dp = moved @ np.array([[-s, c], [-c, -s]])  # d p / d theta
        r = np.sum(normals * (p - centres), axis=1)
        jac = np.column_stack((normals, np.sum(normals * dp, axis=1)))
        d -= np.linalg.solve(jac.T @ (weights[:, None] * jac), jac.T @ (weights * r))
    return d


def test_covariance_unknown_when_not_estimable() -> None:
    assert np.all(np.isinf(np.diag(least_squares_covariance(np.eye(3), 1.0, 3))))
    assert np.all(np.isinf(np.diag(least_squares_covariance(np.zeros((3, 3)), 1.0, 100))))
    cov = least_squares_covariance(np.diag([4.0, 4.0, 1.0]), 9.7, 100)
    assert np.allclose(cov, np.diag([0.025, 0.025, 0.1]))


def test_unknown_covariance_is_infinite_on_the_diagonal_only() -> None:
    cov = unknown_covariance()
    assert cov.shape == (3, 3) and np.all(np.isinf(np.diag(cov)))
    assert np.all(cov[~np.eye(3, dtype=bool)] == 0.0)


@settings(max_examples=50, deadline=None)
@given(ssr=st.floats(0.0, 1e6), n=st.integers(4, 10_000))
def test_residual_variance_is_the_ssr_over_n_minus_three(ssr: float, n: int) -> None:
    assert residual_variance(ssr, n) == pytest.approx(ssr / (n - 3), rel=1e-12)
    for too_few in range(4):  # no degree of freedom left for the noise
        assert residual_variance(ssr, too_few) == math.inf


@pytest.mark.parametrize(
    "hessian",
    [np.full((3, 3), np.nan), np.diag([1.0, np.inf, 1.0]), -np.eye(3)],
    ids=["nan", "inf", "negative-definite"],
)
def test_covariance_is_unknown_for_a_non_finite_or_negative_hessian(hessian: np.ndarray) -> None:
    np.testing.assert_array_equal(least_squares_covariance(hessian, 1.0, 100), unknown_covariance())


@pytest.mark.parametrize("shape", [(2, 2), (3,), (3, 4)])
def test_covariance_refuses_a_hessian_that_is_not_3x3(shape: tuple[int, ...]) -> None:
    with pytest.raises(ValueError, match=r"hessian must be 3x3"):
        least_squares_covariance(np.ones(shape), 1.0, 100)


def test_least_squares_covariance_matches_the_spread_of_simulated_linear_fits() -> None:
    """y = J x + noise with 8 residuals, 20,000 draws: the mean of sigma^2 H^-1 (SSR / (n - 3),
    so unbiased) equals the covariance of the least-squares estimates, as does the truth; an
    SSR / n estimate would be 37 % too small here."""
    rng = np.random.default_rng(4)
    jac = rng.normal(size=(8, 3)) * [1.0, 2.0, 0.5]
    noise_sigma = 0.1
    hessian = jac.T @ jac
    truth = noise_sigma**2 * np.linalg.inv(hessian)
    y = rng.normal(0.0, noise_sigma, (20_000, 8))  # x = 0: y is the noise
    estimates = np.linalg.solve(hessian, jac.T @ y.T).T
    ssr = np.sum((y - estimates @ jac.T) ** 2, axis=1)
    mean_cov = np.mean([least_squares_covariance(hessian, s, 8) for s in ssr[:2000]], axis=0)
    # Whitened by the truth, both must be the identity (2,000 and 20,000 draws: within ~5 %).
    w = np.linalg.inv(np.linalg.cholesky(truth))
    np.testing.assert_allclose(w @ np.cov(estimates.T) @ w.T, np.eye(3), atol=0.05)
    np.testing.assert_allclose(w @ mean_cov @ w.T, np.eye(3), atol=0.06)


@settings(max_examples=50, deadline=None)
@given(x=st.floats(-50, 50), y=st.floats(-50, 50), theta=st.floats(-3.0, 3.0))
def test_pose_parameter_jacobian_matches_finite_differences_of_a_left_increment(
    x: float, y: float, theta: float
) -> None:
    """d(x, y, theta of Exp(d) * T) / dd at d = 0, by central differences over Pose2D."""
    pose = Pose2D(x, y, theta)
    h = 1e-6
    columns = [
        ((Pose2D(*(h * e)) * pose).to_array() - (Pose2D(*(-h * e)) * pose).to_array()) / (2 * h)
        for e in np.eye(3)
    ]
    np.testing.assert_allclose(
        pose_parameter_jacobian(np.array([x, y])), np.column_stack(columns), atol=1e-6
    )


def test_line_fit_covariance_is_unknown_with_three_residuals_or_fewer() -> None:
    target = _on_walls(np.linspace(0.0, 1.0, 31))
    lines = target_lines(GridIndex.build(target))
    rows = np.array([3, 40, 70])
    cov = line_fit_covariance(
        target[rows], np.ones(3), np.full(3, 0.01), lines.normals[rows], lines.centres[rows],
        lines.neighbours[rows], lines.spread_m2[rows], target, np.zeros(2),
    )
    np.testing.assert_array_equal(cov, unknown_covariance())


def test_line_fit_covariance_equals_finite_difference_noise_propagation() -> None:
    """Censi's closed form against brute force on noise-free walls (zero residuals, where it is
    exact to first order): sigma^2 sum_z (dpose/dz)(dpose/dz)^T over every coordinate z of every
    source and target point, dpose/dz by central differences of the weighted point-to-line
    optimum with each line refitted (numpy) through its perturbed neighbours; sigma^2 from
    residuals r_i = u_i sqrt(s_i), s_i = 1 + |dr_i/d(target)|^2 by central differences too, so
    their MAD-based sigma^2 is known: (MAD_TO_SIGMA median(u))^2 m / (m - 3)."""
    target = _on_walls(np.linspace(0.0, 1.0, 31))
    moved = _on_walls(np.arange(0.1, 0.9, 0.05))
    lines = target_lines(GridIndex.build(target))
    d2 = np.sum((moved[:, None, :] - target[None, :, :]) ** 2, axis=2)
    d2[:, ~lines.ok] = np.inf
    row = np.argmin(d2, axis=1)
    neighbours, line_normals = lines.neighbours[row], lines.normals[row]
    rng = np.random.default_rng(0)
    weights = rng.uniform(0.3, 1.0, len(moved))  # Cauchy weights, held fixed
    pose_xy = np.array([0.4, -0.3])
    to_params = pose_parameter_jacobian(pose_xy)

    def optimum(src: NDArray[np.float64], tgt: NDArray[np.float64]) -> NDArray[np.float64]:
        return _point_to_line_increment(src, weights, *_line_fit(tgt, neighbours, line_normals))

    h = 1e-6
    gain = np.zeros((3, 3))
    s = np.ones(len(moved))
    for which, points in (("source", moved), ("target", target)):
        for index in np.ndindex(points.shape):
            e = np.zeros(points.shape)
            e[index] = h
            if which == "source":
                plus, minus = optimum(moved + e, target), optimum(moved - e, target)
            else:
                plus, minus = optimum(moved, target + e), optimum(moved, target - e)
                (n_plus, c_plus), (n_minus, c_minus) = (
                    _line_fit(target + e, neighbours, line_normals),
                    _line_fit(target - e, neighbours, line_normals),
                )
                dr = (np.sum(n_plus * (moved - c_plus), axis=1)
                      - np.sum(n_minus * (moved - c_minus), axis=1)) / (2 * h)
                s += dr**2
            dpose = to_params @ (plus - minus) / (2 * h)
            gain += np.outer(dpose, dpose)
    u = rng.uniform(0.5, 2.0, len(moved))
    m = len(moved)
    expected = (MAD_TO_SIGMA * np.median(u)) ** 2 * m / (m - 3) * gain
    got = line_fit_covariance(
        moved, weights, u * np.sqrt(s), line_normals, lines.centres[row], neighbours,
        lines.spread_m2[row], target, pose_xy,
    )
    np.testing.assert_allclose(got, expected, rtol=1e-6, atol=1e-9 * np.abs(expected).max())


def test_line_fit_covariance_matches_the_spread_of_simulated_point_to_line_fits() -> None:
    """1 cm isotropic noise on source and target points, target lines refitted per draw: the
    mean NEES of the point-to-line optimum against Censi's covariance is near 3 (sigma^2 H^-1,
    which ignores the target's noise, gives ~4.6 on these draws)."""
    rng = np.random.default_rng(1)
    target0 = _on_walls(np.linspace(0.0, 1.0, 31))
    source0 = _on_walls(np.arange(0.1, 0.9, 0.03))
    nees = []
    for _ in range(300):
        target = target0 + rng.normal(0.0, 0.01, target0.shape)
        source = source0 + rng.normal(0.0, 0.01, source0.shape)
        lines = target_lines(GridIndex.build(target))
        d2 = np.sum((source[:, None, :] - target[None, :, :]) ** 2, axis=2)
        d2[:, ~lines.ok] = np.inf
        row = np.argmin(d2, axis=1)
        normals, centres = lines.normals[row], lines.centres[row]
        ones = np.ones(len(source))
        d = _point_to_line_increment(source, ones, normals, centres)
        moved = Pose2D(*d).transform_points(source)  # the truth is the identity: error = d
        residuals = np.sum(normals * (moved - centres), axis=1)
        cov = line_fit_covariance(moved, ones, residuals, normals, centres,
                                  lines.neighbours[row], lines.spread_m2[row], target, d[:2])
        nees.append(d @ np.linalg.solve(cov, d))
    assert 2.25 < np.mean(nees) < 3.9
