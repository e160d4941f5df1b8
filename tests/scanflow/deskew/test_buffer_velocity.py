import math

import numpy as np
import pytest
from scanflow.deskew import ConstantVelocityModel, DeskewError, OdometryBuffer
from scanflow.geometry import Pose2D, se2_exp, se2_log


def _circle_pose(t):
    return Pose2D(*se2_exp([[1.0 * t, 0.0, math.pi * t]])[0])


def test_se2_log_inverts_exp_including_small_angles():
    twists = np.array([[1.0, 0.2, 0.5], [0.3, -0.1, 1e-9], [0.0, 0.0, -3.0], [2.0, 0.0, 0.0]])
    np.testing.assert_allclose(se2_log(se2_exp(twists)), twists, atol=1e-12)


def test_out_of_order_and_duplicate_samples_give_the_same_buffer():
    stamps = np.arange(0.0, 1.0, 0.02)
    ordered, shuffled = OdometryBuffer(), OdometryBuffer()
    for t in stamps:
        ordered.add(t, _circle_pose(t))
    rng = np.random.default_rng(0)
    for t in rng.permutation(stamps):
        shuffled.add(t, Pose2D(9.0, 9.0, 1.0))  # wrong pose first ...
    for t in rng.permutation(stamps):
        assert shuffled.add(t, _circle_pose(t))  # ... replaced by the later arrival
    assert shuffled.replaced_count == stamps.size
    np.testing.assert_array_equal(shuffled.stamps_s, ordered.stamps_s)
    times = np.linspace(0.05, 0.9, 50)
    for a, b in zip(ordered.poses_at(times), shuffled.poses_at(times), strict=True):
        np.testing.assert_allclose(a, b, atol=1e-12)


def test_interpolation_is_shortest_arc_across_pi():
    buffer = OdometryBuffer()
    buffer.add(0.0, Pose2D(0.0, 0.0, math.pi - 0.1))
    buffer.add(0.1, Pose2D(1.0, 0.0, -math.pi + 0.1))
    x, _, theta = buffer.poses_at(np.array([0.05]))
    assert x[0] == pytest.approx(0.5)
    assert abs(abs(theta[0]) - math.pi) < 1e-9


def test_bounded_by_age_and_old_samples_dropped():
    buffer = OdometryBuffer(max_age_s=1.0)
    for t in np.arange(0.0, 5.0, 0.01):
        buffer.add(t, Pose2D(t, 0.0, 0.0))
    assert buffer.stamps_s[0] >= 4.99 - 1.0 - 1e-9
    assert not buffer.add(1.0, Pose2D())
    assert buffer.dropped_count == 1


def test_extrapolation_limited_by_margin_and_gaps_refused():
    buffer = OdometryBuffer(extrapolation_margin_s=0.02, max_gap_s=0.2)
    for t in (0.0, 0.1, 0.2, 0.6, 0.7):
        buffer.add(t, Pose2D(t, 0.0, 0.0))
    assert buffer.coverage_gap(-0.01, 0.15) is None
    for t in (-0.01, 0.71):  # extrapolated along the end segments
        np.testing.assert_allclose(buffer.poses_at(np.array([t]))[0], [t])
    assert "before the oldest" in buffer.coverage_gap(-0.05, 0.1)
    assert "after the newest" in buffer.coverage_gap(0.6, 0.75)
    assert "gap of 0.4000 s" in buffer.coverage_gap(0.15, 0.65)
    with pytest.raises(DeskewError, match="after the newest"):
        buffer.poses_at(np.array([0.8]))
    assert "at least two" in OdometryBuffer().coverage_gap(0.0, 0.1)


def test_buffer_keeps_growing_correctly_past_its_initial_capacity():
    buffer = OdometryBuffer(max_age_s=100.0)
    stamps = np.arange(0.0, 20.0, 0.01)
    for t in stamps[::-1][:50]:  # some arrive late
        buffer.add(t, _circle_pose(t))
    for t in stamps:
        buffer.add(t, _circle_pose(t))
    assert len(buffer) == stamps.size
    x, y, theta = buffer.poses_at(stamps[::97])
    truth = np.array([_circle_pose(t).to_array() for t in stamps[::97]])
    np.testing.assert_allclose(np.column_stack((x, y, theta)), truth, atol=1e-9)


def test_bad_settings_and_stamps_name_the_field():
    with pytest.raises(DeskewError, match="max_age_s"):
        OdometryBuffer(max_age_s=0.0)
    with pytest.raises(DeskewError, match="stamp_s"):
        OdometryBuffer().add(math.nan, Pose2D())
    with pytest.raises(DeskewError, match="max_horizon_s"):
        ConstantVelocityModel(max_horizon_s=-1.0)


def test_constant_velocity_model_predicts_arcs_exactly():
    model = ConstantVelocityModel()
    assert "has 0" in model.coverage_gap(0.0, 0.1)
    model.update(0.0, _circle_pose(0.0))
    assert "has 1" in model.coverage_gap(0.0, 0.1)
    model.update(0.1, _circle_pose(0.1))
    np.testing.assert_allclose(model.twist, [1.0, 0.0, math.pi], atol=1e-12)
    times = np.linspace(0.1, 0.2, 11)
    predicted = np.column_stack(model.poses_at(times))
    truth = np.array([_circle_pose(t).to_array() for t in times])
    np.testing.assert_allclose(predicted, truth, atol=1e-12)
    assert "max_horizon_s" in model.coverage_gap(0.1, 0.9)


def test_constant_velocity_model_resets_when_time_goes_backwards():
    model = ConstantVelocityModel()
    model.update(1.0, Pose2D())
    model.update(1.1, Pose2D(0.1, 0.0, 0.0))
    model.update(0.5, Pose2D())
    gap = model.coverage_gap(0.5, 0.6)
    assert "time went backwards" in gap
    model.update(0.6, Pose2D(0.1, 0.0, 0.0))
    assert model.coverage_gap(0.6, 0.7) is None


def test_constant_velocity_model_skips_a_pose_too_close_in_time():
    """Two estimates a microsecond and 5 cm apart are not 50 km/s of motion."""
    model = ConstantVelocityModel()
    model.update(1.0, Pose2D())
    model.update(1.1, Pose2D(0.1, 0.0, 0.0))
    model.update(1.100001, Pose2D(0.15, 0.0, 0.0))
    np.testing.assert_allclose(model.twist, [1.0, 0.0, 0.0], atol=1e-9)
    model.update(1.2, Pose2D(0.25, 0.0, 0.0))  # the baseline is the last kept pose, 1.1 s
    np.testing.assert_allclose(model.twist, [1.5, 0.0, 0.0], atol=1e-9)


@pytest.mark.parametrize(("step", "named"), [(Pose2D(6.0, 0.0, 0.0), "60 m/s"),
                                            (Pose2D(0.0, 0.0, 1.5), "15 rad/s")])
def test_constant_velocity_model_refuses_an_implausible_twist(step, named):
    model = ConstantVelocityModel()
    model.update(0.0, Pose2D())
    model.update(0.1, step)
    assert model.twist is None
    assert named in model.coverage_gap(0.1, 0.2)
    with pytest.raises(DeskewError, match="max_speed_mps"):
        model.poses_at([0.15])
    model.update(0.2, step * Pose2D(0.1, 0.0, 0.0))  # plausible again: predicts again
    assert model.coverage_gap(0.2, 0.25) is None


def test_constant_velocity_model_settings_are_checked():
    for bad in ({"min_interval_s": 0.0}, {"max_speed_mps": math.nan},
                {"max_turn_rate_rads": -1.0}):
        with pytest.raises(DeskewError, match=next(iter(bad))):
            ConstantVelocityModel(**bad)
