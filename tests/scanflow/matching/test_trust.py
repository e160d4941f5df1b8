import math

import numpy as np
import pytest
from scanflow.geometry import Pose2D
from scanflow.matching import MatchStatus, match

from .conftest import scan_points

LOCAL_METHODS = ("icp", "plicp", "gn", "lm", "ndt", "csm+plicp")


def wrong_basin() -> tuple[np.ndarray, np.ndarray, Pose2D, Pose2D]:
    """Two sweeps in the "rooms" world 17 cm apart and a guess 1 m / 30 deg off, from which ndt
    converges 1.25 m / 57 deg away from the truth."""
    base = Pose2D(2.94214, 2.68405, 1.89296)
    moved = Pose2D(3.08573, 2.76663, 1.88218)
    guess = Pose2D(-0.95701, -0.02042, -0.53438)
    source, target = scan_points("rooms", moved, 5), scan_points("rooms", base, 4)
    return source, target, moved.relative_to(base), guess


def test_a_wrong_basin_that_ndt_called_ok_is_a_poor_fit() -> None:
    source, target, truth, guess = wrong_basin()
    unchecked = match(source, target, guess, method="ndt", max_free_space_share=1.0)
    error = unchecked.pose.relative_to(truth)
    assert unchecked.ok and error.translation_norm() > 0.5  # what ndt said before the check
    checked = match(source, target, guess, method="ndt")
    assert checked.status is MatchStatus.POOR_FIT
    assert "max_free_space_share 0.1" in checked.message
    assert checked.extra["free_space_share"] > 0.1
    np.testing.assert_allclose(checked.pose.to_array(), unchecked.pose.to_array())


@pytest.mark.parametrize("method", LOCAL_METHODS)
def test_good_alignments_stay_ok(method: str) -> None:
    """Over seeded pairs in two simulated worlds, every local method from a guess near the
    truth converges near it with status OK and few free-space conflicts."""
    rng = np.random.default_rng(8)
    for trial, world in enumerate(("rooms", "loop") * 4):
        box = {"rooms": (2.0, 13.0, 1.5, 6.5), "loop": (1.5, 22.5, 1.0, 2.0)}[world]
        base = Pose2D(rng.uniform(*box[:2]), rng.uniform(*box[2:]), rng.uniform(-math.pi, math.pi))
        moved = base * Pose2D(rng.uniform(-0.2, 0.2), rng.uniform(-0.2, 0.2), rng.normal(0, 0.05))
        truth = moved.relative_to(base)
        source = scan_points(world, moved, 2 * trial + 1)
        target = scan_points(world, base, 2 * trial)
        r = match(source, target, truth * Pose2D(0.05, -0.05, 0.03), method=method)
        error = r.pose.relative_to(truth)
        assert r.ok, (world, trial, r.status, r.message)
        assert error.translation_norm() < 0.05 and abs(error.theta) < math.radians(1.0)
        assert r.extra["free_space_share"] <= 0.1


def test_a_map_target_is_not_tested(room, caster, room_map_points) -> None:
    class PointsMap:
        def likelihood_field(self) -> None: ...

        def occupied_points(self) -> np.ndarray:
            return room_map_points

    source = caster(room, Pose2D(0.2, 0.1, 0.05))
    r = match(source, PointsMap(), Pose2D(0.2, 0.1, 0.05), method="plicp")
    assert r.ok and "free_space_share" not in r.extra


def test_limits_out_of_range_are_refused(room, caster) -> None:
    scan = caster(room, Pose2D())
    with pytest.raises(ValueError, match=r"max_free_space_share must be in \[0, 1\], got 1.5"):
        match(scan, scan, method="plicp", max_free_space_share=1.5)
    with pytest.raises(ValueError, match=r"margin_m must be >= 0, got -0.2"):
        match(scan, scan, method="icp", free_space_margin_m=-0.2)
