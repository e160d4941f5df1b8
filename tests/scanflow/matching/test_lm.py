"""Levenberg-Marquardt specifics: it never accepts a step that raises the cost."""

import numpy as np
from scanflow.geometry import Pose2D
from scanflow.matching import MatchStatus, match
from scanflow.matching.field_cost import field_cost, points_field


def test_final_cost_never_exceeds_the_start(room, caster, room_map_points) -> None:
    rng = np.random.default_rng(5)
    field = points_field(room_map_points, 0.05, 0.1)
    for _ in range(10):
        true = Pose2D(rng.uniform(-2, 2), rng.uniform(-2, 1.5), rng.uniform(-3, 3))
        scan = caster(room, true, noise_m=0.02, rng=rng)
        guess = true * Pose2D(rng.normal(0, 0.05), rng.normal(0, 0.05), rng.normal(0, 0.03))
        r = match(scan, room_map_points, guess, method="lm", levels=1)
        if r.status is MatchStatus.OK:
            end = field_cost(field, scan, r.pose.to_array())
            assert end <= field_cost(field, scan, guess.to_array()) + 1e-9


def test_heavy_initial_damping_still_converges(room, caster, room_map_points) -> None:
    true = Pose2D(0.4, -0.3, 0.5)
    scan = caster(room, true)
    start = Pose2D(0.5, -0.2, 0.55)
    r = match(scan, room_map_points, start, method="lm", tau=1.0, max_iterations=60)
    gn = match(scan, room_map_points, start, method="gn")
    # Both land on the same cell-limited optimum (a few cm from the truth at 5 cm cells).
    assert r.ok and r.pose.relative_to(true).translation_norm() < 0.05
    assert r.pose.relative_to(gn.pose).translation_norm() < 0.01
