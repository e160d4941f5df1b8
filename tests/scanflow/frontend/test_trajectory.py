"""TrajectoryStore and TUM export: growth, round trips and the yaw quaternion."""

from __future__ import annotations

import math
import warnings
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from scanflow.frontend import TrajectoryStore, load_tum, tum_text
from scanflow.geometry import Pose2D

angle = st.floats(-math.pi, math.pi, allow_nan=False, exclude_max=True)


def test_trajectory_store_grows_and_round_trips_tum(tmp_path: Path) -> None:
    store = TrajectoryStore()
    rng = np.random.default_rng(0)
    rows = rng.uniform(-3, 3, size=(600, 3))
    for i, (x, y, th) in enumerate(rows):
        store.append(1.7e9 + 0.1 * i, Pose2D(x, y, th))
    assert len(store) == 600 and store.poses.shape == (600, 3)
    stamps, loaded = load_tum(store.save_tum(tmp_path / "traj.tum"))
    np.testing.assert_allclose(stamps, store.stamps_s, atol=1e-6)
    np.testing.assert_allclose(loaded[:, :2], rows[:, :2], atol=1e-7)
    np.testing.assert_allclose(np.cos(loaded[:, 2] - store.poses[:, 2]), 1.0, atol=1e-12)


@given(angle)
def test_tum_quaternion_is_a_yaw_rotation(theta: float) -> None:
    fields = [float(v) for v in tum_text(np.array([0.0]), np.array([[1.0, 2.0, theta]])).split()]
    assert fields[3:6] == [0.0, 0.0, 0.0]
    assert math.isclose(fields[6] ** 2 + fields[7] ** 2, 1.0, rel_tol=1e-7)
    assert math.isclose(math.cos(2 * math.atan2(fields[6], fields[7]) - theta), 1.0, abs_tol=1e-9)


def test_tum_shape_error_names_the_field() -> None:
    with pytest.raises(ValueError, match="poses must have shape"):
        tum_text(np.zeros(2), np.zeros((3, 3)))


def test_an_empty_trajectory_round_trips(tmp_path: Path) -> None:
    """A run that tracked no scan writes an empty TUM file (`scanflow run` on a log that broke
    off at once): it reads back as no poses, not as a file of 1 column, and without a warning."""
    path = TrajectoryStore().save_tum(tmp_path / "empty.tum")
    commented = tmp_path / "commented.tum"
    commented.write_text("# timestamp tx ty tz qx qy qz qw\n")
    for tum in (path, commented):
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            stamps, poses = load_tum(tum)
        assert stamps.shape == (0,) and poses.shape == (0, 3)
