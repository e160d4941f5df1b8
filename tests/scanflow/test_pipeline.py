"""The in-process pipeline: deskew stage + front end on the simulator and on keyframe scans."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from scanflow.config import BackendSettings
from scanflow.frontend import PredictionSource
from scanflow.geometry import Pose2D
from scanflow.pipeline import DeskewStage, Pipeline
from scanflow.scan import LaserScan, Odometry
from scanflow.sim import SimConfig, cast_rays, get_world, simulate

FAST = SimConfig(duration_s=3.0, seed=4, max_speed_mps=1.5, max_yaw_rate_dps=180.0)
# The map frame is turned against the world so walls do not lie on grid cell boundaries.
MAP_FROM_WORLD = Pose2D(0.013, -0.021, 0.3)


def track_errors_m(
    deskew_enabled: bool, config: SimConfig = FAST, declared_mount: Pose2D | None = None
) -> tuple[list[float], list[str]]:
    """Translation errors of the robot's tracked poses; `declared_mount` overrides the mount
    the scans carry (what a user who mis-declares the sensor's place would get)."""
    frames = list(simulate(config))
    pipeline = Pipeline(
        deskew_enabled=deskew_enabled, initial_pose=MAP_FROM_WORLD * frames[0].true_pose
    )
    errors, sources = [], []
    for frame in frames:
        for sample in frame.odometry:
            pipeline.add_odometry(sample)
        scan = frame.scan
        if declared_mount is not None:
            scan = dataclasses.replace(scan, mount=declared_mount)
        out = pipeline.process(scan)
        assert out.estimate.stamp_s == frame.scan.stamp_s  # reference "start"
        truth = MAP_FROM_WORLD * frame.true_pose
        errors.append(out.estimate.pose.relative_to(truth).translation_norm())
        sources.append(out.deskew.source_used)
    return errors, sources


@pytest.mark.slow
def test_deskewing_helps_tracking_at_speed() -> None:
    with_deskew, sources = track_errors_m(True)
    without, raw = track_errors_m(False)
    assert set(sources[1:]) == {"odometry"} and set(raw) == {"none"}
    assert max(with_deskew) < 0.15
    assert np.sqrt(np.mean(np.square(with_deskew))) < np.sqrt(np.mean(np.square(without)))


@pytest.mark.slow
def test_a_mounted_lidar_tracks_the_robot() -> None:
    """The lidar 40 cm ahead of the turning axis and turned 20 deg: the poses are the robot's,
    as good as with the lidar at the origin; declaring it at the origin instead is far off."""
    mounted = dataclasses.replace(FAST, mount=Pose2D(0.4, 0.05, math.radians(20.0)))
    errors, _ = track_errors_m(True, mounted)
    assert max(errors) < 0.15
    ignored, _ = track_errors_m(True, mounted, declared_mount=Pose2D())
    assert np.median(ignored) > 0.3


def keyframe(ranges_m: np.ndarray, stamp_s: float, seq: int) -> LaserScan:
    """A CARMEN-like scan: no per-beam times, zero duration."""
    return LaserScan(ranges_m, -math.pi / 2, math.pi / 180, range_max_m=50.0, stamp_s=stamp_s,
                     seq=seq)


def test_keyframes_use_the_given_odometry_and_skip_deskewing() -> None:
    angles = -math.pi / 2 + np.arange(181) * math.pi / 180
    origin = np.tile([7.32, 2.07], (181, 1))
    ranges = cast_rays(origin, angles + 0.3, get_world("rooms").segments, 20.0)
    pipeline = Pipeline()
    first = pipeline.process(keyframe(ranges, 10.0, 0), Pose2D(5.0, 5.0, 0.0))
    second = pipeline.process(keyframe(ranges, 11.0, 1), Pose2D(5.0, 5.0, 0.0))
    assert first.deskew.source_used == "none" and "zero duration" in first.deskew.message
    assert first.estimate.status == "initialised" and first.estimate.seq == 0
    assert second.estimate.accepted and second.estimate.seq == 1
    assert second.estimate.prediction_source == PredictionSource.ODOMETRY
    assert second.estimate.pose.translation_norm() < 0.02


def test_no_return_beams_reach_the_map_through_the_pipeline() -> None:
    angles = -math.pi / 2 + np.arange(181) * math.pi / 180
    ranges = cast_rays(np.tile([7.32, 2.07], (181, 1)), angles + 0.3, get_world("rooms").segments,
                       20.0)
    gone = (np.arange(181) % 9 == 0) | np.isinf(ranges)  # and the beams out of the door
    maps, misses = {}, {}
    for name, lost in (("no_return", np.inf), ("error", np.nan)):
        pipeline = Pipeline()
        out = pipeline.process(keyframe(np.where(gone, lost, ranges), 10.0, 0), Pose2D())
        assert out.estimate.inserted
        maps[name], misses[name] = pipeline.frontend.map.grid, out.deskew.no_return_points
    assert (len(misses["no_return"]), len(misses["error"])) == (np.count_nonzero(gone), 0)
    grid, other = maps["no_return"], maps["error"]
    # Cells the no-return beams cleared: free, within no_return_clear_m of the sensor.
    observed = np.zeros(grid.extent.shape, dtype=bool)
    observed[other.extent.slices_in(grid.extent)] = other.observed
    extra = grid.observed & ~observed
    assert np.count_nonzero(extra) > 100
    assert (grid.log_odds[extra] < 0).all()
    rows, cols = np.nonzero(extra)
    spec = grid.spec
    x = spec.origin_x_m + (cols + 0.5) * spec.resolution_m
    y = spec.origin_y_m + (rows + 0.5) * spec.resolution_m
    assert np.hypot(x, y).max() <= grid.params.no_return_clear_m + spec.resolution_m


def test_deskew_stage_odometry_pose_at() -> None:
    stage = DeskewStage()
    assert stage.odometry_pose_at(1.0) is None
    stage.add_odometry(Odometry(1.0, Pose2D(0.0, 0.0, 0.0)))
    stage.add_odometry(Odometry(1.1, Pose2D(0.2, 0.0, 0.2)))
    pose = stage.odometry_pose_at(1.05)
    assert pose is not None
    assert math.isclose(pose.x, 0.1) and math.isclose(pose.theta, 0.1)
    assert stage.odometry_pose_at(2.0) is None


def test_deskew_stage_gives_the_measured_odometry_at_its_exact_stamp() -> None:
    stage = DeskewStage()
    measured = Pose2D(1.0, 2.0, 3.0)
    stage.add_odometry(Odometry(5.0, measured))
    assert stage.odometry_pose_at(5.0) is measured  # one sample: no interpolation possible
    stage.add_odometry(Odometry(5.2, Pose2D(1.2, 2.0, -3.0)))
    assert stage.odometry_pose_at(5.0) is measured
    assert stage.odometry_pose_at(5.1) is not None and stage.odometry_pose_at(4.0) is None


@pytest.mark.second_lane  # 10-18 s: beside the container tests, whose wait on Zenoh leaves a core
def test_loop_closure_corrects_a_drifting_lap() -> None:
    """A lap of the simulator's ring corridor with poor wheel odometry (3 % scale error, 5 %
    yaw noise): the front end alone drifts; with the back end the closures at the revisit bring
    the keyframes back, and the pipeline's outputs report what it did. (With 1 % yaw noise the
    front end's error, 0.12 m rms, is along the corridors, where its scans are degenerate and
    the odometry's scale error leads: it cancels out over the lap, so a revisit finds nothing
    to correct.)"""
    config = SimConfig(world="loop", duration_s=100.0, seed=1, odom_scale_error=0.03,
                       odom_yaw_noise=0.05)
    frames = list(simulate(config))
    truth = np.array([(MAP_FROM_WORLD * f.true_pose).to_array() for f in frames])

    def errors_m(backend: BackendSettings | None) -> tuple[np.ndarray, Pipeline, list]:
        pipeline = Pipeline(initial_pose=Pose2D.from_array(truth[0]), backend=backend)
        outs = []
        for frame in frames:
            for sample in frame.odometry:
                pipeline.add_odometry(sample)
            outs.append(pipeline.process(frame.scan))
        pipeline.finish()
        if pipeline.mapper is not None:
            poses = pipeline.mapper.trajectory()
        else:
            poses = np.array([o.estimate.pose.to_array() for o in outs])
        return np.hypot(*(poses - truth)[:, :2].T), pipeline, outs

    alone, plain, plain_outs = errors_m(None)
    closed, pipeline, outs = errors_m(BackendSettings.model_construct(loop_closure=True))
    assert plain.mapper is None and all(o.backend is None for o in plain_outs)
    assert pipeline.mapper is not None and pipeline.mapper.closures
    assert any(o.backend is not None and o.backend.optimised is not None for o in outs)
    assert np.sqrt(np.mean(closed**2)) < 0.6 * np.sqrt(np.mean(alone**2))
    assert pipeline.finish() is not None and plain.finish() is None
