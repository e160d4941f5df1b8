"""2D NDT: analytic derivatives vs finite differences, convergence, statuses."""

import math

import numpy as np
import pytest
from scanflow.geometry import Pose2D
from scanflow.maps.ndt_cells import OverlappingCells
from scanflow.matching import MatchStatus, match
from scanflow.matching.ndt import ndt_cost, ndt_evaluate, positive_definite


@pytest.fixture
def problem(room, caster):
    rng = np.random.default_rng(0)
    grids = OverlappingCells.from_points(caster(room, Pose2D(), noise_m=0.01, rng=rng), 0.5)
    source = caster(room, Pose2D(0.1, 0.05, 0.05), noise_m=0.01, rng=rng)
    return grids, source


def test_gradient_and_hessian_match_finite_differences(problem) -> None:
    grids, source = problem
    eps = 1e-6
    for pose in (np.array([0.12, 0.03, 0.06]), np.array([0.05, 0.1, 0.02])):
        ev = ndt_evaluate(grids, source, pose)
        assert ev.cost == pytest.approx(ndt_cost(grids, source, pose))
        grad = [
            (ndt_cost(grids, source, pose + eps * e) - ndt_cost(grids, source, pose - eps * e))
            / (2 * eps)
            for e in np.eye(3)
        ]
        hess = [
            (
                ndt_evaluate(grids, source, pose + eps * e).gradient
                - ndt_evaluate(grids, source, pose - eps * e).gradient
            )
            / (2 * eps)
            for e in np.eye(3)
        ]
        np.testing.assert_allclose(ev.gradient, grad, rtol=1e-5, atol=1e-3)
        np.testing.assert_allclose(ev.hessian, np.array(hess), rtol=1e-5, atol=1e-2)


def test_positive_definite_floors_negative_eigenvalues() -> None:
    h = positive_definite(np.diag([4.0, -1.0, 2.0]))
    assert np.all(np.linalg.eigvalsh(h) > 0)
    assert positive_definite(np.zeros((3, 3))) is None


def test_converges_scan_to_scan(room, caster) -> None:
    rng = np.random.default_rng(4)
    for _ in range(5):
        a = Pose2D(rng.uniform(-1, 1), rng.uniform(-1, 1), rng.uniform(-3, 3))
        b = a * Pose2D(rng.normal(0, 0.15), rng.normal(0, 0.15), rng.normal(0, 0.08))
        target = caster(room, a, noise_m=0.01, rng=rng)
        source = caster(room, b, noise_m=0.01, rng=rng)
        truth = b.relative_to(a)
        r = match(source, target, Pose2D(), method="ndt")
        err = r.pose.relative_to(truth)
        assert r.ok, r.message
        assert err.translation_norm() < 0.05 and abs(err.theta) < math.radians(1.0)


def test_statuses(room, caster, corridor, corridor_map_points) -> None:
    scan = caster(room, Pose2D())
    assert match(scan, np.zeros((0, 2)), method="ndt").status is MatchStatus.EMPTY_MAP
    assert match(scan[:4], scan, method="ndt").status is MatchStatus.TOO_FEW_POINTS
    assert match(scan, scan + 500.0, method="ndt").status is MatchStatus.NO_OVERLAP
    source = caster(corridor, Pose2D(0.3, 0.05, 0.03), max_range_m=8.0)
    r = match(source, corridor_map_points, Pose2D(0.3, 0.0, 0.0), method="ndt")
    assert r.status is MatchStatus.DEGENERATE and abs(r.weak_direction[0]) > 0.95
