"""checks.py: removing the unobserved (weak) direction from a pose correction."""

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from scanflow.geometry import Pose2D
from scanflow.matching.checks import analyse_hessian, line_hessian, without_weak_direction

finite = st.floats(-1.0, 1.0, allow_nan=False)
# Fine steps are within the agreement window (0.1 m, 1 deg) by far: no heading wraps around.
small = st.floats(-0.2, 0.2, allow_nan=False)


@given(st.tuples(small, small, small), st.tuples(finite, finite, finite),
       st.floats(0.5, 20.0))
def test_the_weak_component_is_removed_and_the_rest_kept(
    correction: tuple, weak: tuple, length_m: float
) -> None:
    """Orthogonal to the weak direction in analyse_hessian's metric; projecting twice changes
    nothing; a correction already across it is unchanged."""
    scale = np.array([1.0, 1.0, length_m])
    w = np.array(weak)
    if np.linalg.norm(w * scale) < 1e-3:
        return
    out = without_weak_direction(Pose2D(*correction), weak, length_m)
    ws = w * scale / np.linalg.norm(w * scale)
    assert abs(np.dot(out.to_array() * scale, ws)) < 1e-9
    again = without_weak_direction(out, weak, length_m)
    assert np.allclose(again.to_array(), out.to_array(), atol=1e-12)


def test_a_corridor_s_weak_direction_is_where_the_projection_acts() -> None:
    """The weak direction of a corridor's point-to-line Hessian is along it: a correction
    along the corridor is removed, one across it kept."""
    normals = np.tile([0.0, 1.0], (200, 1))
    points = np.column_stack((np.linspace(-5, 5, 200), np.where(np.arange(200) % 2, 1.0, -1.0)))
    weak = analyse_hessian(line_hessian(points, normals), 3.0).weak_direction
    along = without_weak_direction(Pose2D(0.05, 0.0, 0.0), weak, 3.0)
    across = without_weak_direction(Pose2D(0.0, 0.02, 0.0), weak, 3.0)
    assert along.translation_norm() < 1e-9
    assert across.to_array() == pytest.approx([0.0, 0.02, 0.0], abs=1e-9)
