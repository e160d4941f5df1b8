"""bench.matching: keyframe pairs, the ground-truth-free closure figure, simulated pairs with
exact truth, and the CLI end to end."""

import json
import math

import numpy as np
import pytest
from scanflow.geometry import Pose2D
from scanflow.matching import MatchResult, MatchStatus
from scanflow.sim import SimConfig, simulate

from bench.data import corrected_log
from bench.matching import (
    Frame,
    closure,
    keyframe_pairs,
    main,
    odometry_matcher,
    run_matcher,
    sim_frames,
)

from .conftest import run_bench, usage_error

LOG = corrected_log("intel")


def frames_along(poses: list[Pose2D]) -> list[Frame]:
    """Keyframes at the given poses, odometry equal to the truth, distinct small scans."""
    return [Frame(np.full((8, 2), 1.0 + k), pose, pose) for k, pose in enumerate(poses)]


def same(a: Pose2D, b: Pose2D) -> bool:
    return np.allclose((a.x, a.y, a.theta), (b.x, b.y, b.theta), atol=1e-12)


def tour(n: int) -> list[Pose2D]:
    poses = [Pose2D.identity()]
    for k in range(n - 1):
        poses.append(poses[-1] * Pose2D(0.3, 0.05 * (k % 3), math.radians(7.0 + k)))
    return poses


def test_keyframe_pairs_index_truth_and_guess() -> None:
    poses = tour(10)
    frames = frames_along(poses)
    pairs = keyframe_pairs(frames, gap=3, stride=1, limit=None)
    assert [p.first for p in pairs] == [0, 3, 6]
    for p in pairs:
        want = poses[p.first + 3].relative_to(poses[p.first])
        assert same(p.truth, want) and same(p.guess, want)
        assert p.target is frames[p.first].points
        assert p.source is frames[p.first + 3].points
    assert [p.first for p in keyframe_pairs(frames, 3, 2, None)] == [0, 6]
    assert [p.first for p in keyframe_pairs(frames, 1, 1, 4)] == [0, 1, 2, 3]
    overlapping = keyframe_pairs(frames, 3, 1, None, start_step=1)
    assert [p.first for p in overlapping] == list(range(7))
    assert same(overlapping[1].truth, poses[4].relative_to(poses[1]))


def test_closure_of_a_consistent_matcher_is_exact() -> None:
    frames = frames_along(tour(13))
    pairs = keyframe_pairs(frames, 3, 1, None)
    direct = run_matcher("odometry", odometry_matcher, pairs, [p.guess for p in pairs]).poses
    c = closure("odometry", odometry_matcher, pairs, direct, frames, 3)
    assert c["agree_5cm_0.5deg"] == c["agree_10cm_1deg"] == 1.0
    assert c["trans_p50_m"] < 1e-9 and c["rot_p50_deg"] < 1e-9
    assert c["closure_sigma_xy_m"] < 1e-9 and c["truth_sigma_deg"] < 1e-9


def test_closure_sees_a_bias_that_accumulates_along_the_chain() -> None:
    """Every match off by the same 0.3 deg: a chain of 3 is 0.6 deg further off than the direct."""
    bias = math.radians(0.3)

    def biased(src, tgt, guess: Pose2D) -> Pose2D:
        return guess * Pose2D(0.0, 0.0, bias)

    frames = frames_along(tour(13))
    pairs = keyframe_pairs(frames, 3, 1, None)
    summary, direct, _ = run_matcher("biased", biased, pairs, [p.guess for p in pairs])
    assert summary["rot_p50_deg"] == pytest.approx(0.3)
    c = closure("biased", biased, pairs, direct, frames, 3)
    assert c["rot_p50_deg"] == pytest.approx(0.6)
    assert c["agree_5cm_0.5deg"] == 0.0 and c["agree_10cm_1deg"] == 1.0
    # A constant offset has no spread, against the chains or against the truth.
    assert c["closure_sigma_deg"] < 1e-9 and c["truth_sigma_deg"] < 1e-9


def test_the_chain_splits_the_silently_wrong_share() -> None:
    """The corrected pose of keyframe 6 is 0.3 m off (the real motion is the odometry's): the
    two pairs through it are silently wrong, but their chains agree with them. The direct match
    of pair 9 -> 12 is 0.5 m off while its chain is right: confirmed."""
    poses = tour(13)
    frames = [Frame(f.points, f.true_pose * Pose2D(0.3, 0.0, 0.0) if k == 6 else f.true_pose,
                    f.odom_pose) for k, f in enumerate(frames_along(poses))]

    def at_guess(src: np.ndarray, tgt: np.ndarray, guess: Pose2D) -> MatchResult:
        first, last = int(tgt[0, 0]) - 1, int(src[0, 0]) - 1  # frames_along's scan markers
        wrong = (first, last) == (9, 12)
        pose = guess * Pose2D(0.5, 0.0, 0.0) if wrong else guess
        return MatchResult(pose, np.eye(3), 1.0, 1, True, MatchStatus.OK, "at_guess")

    pairs = keyframe_pairs(frames, 3, 1, None)
    assert [p.first for p in pairs] == [0, 3, 6, 9]
    run = run_matcher("at_guess", at_guess, pairs, [p.guess for p in pairs])
    assert run.summary["silently_wrong"] == 0.75 and run.trusted.all()
    c = closure("at_guess", at_guess, pairs, run.poses, frames, 3, run.trusted)
    assert c["silently_wrong_confirmed"] == 0.25
    assert c["silently_wrong_chain_agrees"] == 0.5
    untrusted = closure("at_guess", at_guess, pairs, run.poses, frames, 3, np.zeros(4, bool))
    assert untrusted["silently_wrong_confirmed"] == untrusted["silently_wrong_chain_agrees"] == 0
    assert "silently_wrong_confirmed" not in closure("at_guess", at_guess, pairs, run.poses,
                                                     frames, 3)


def test_repeats_pass_over_the_pairs_that_often_and_keep_the_first_passes_pose() -> None:
    """`repeats` passes over the pairs (after one untimed warm-up call); the times are each
    pair's least, the pose the first pass's."""
    poses = tour(7)
    pairs = keyframe_pairs(frames_along(poses), 2, 1, None)
    calls: list[int] = []

    def drifting(src: np.ndarray, tgt: np.ndarray, guess: Pose2D) -> Pose2D:
        calls.append(1)
        return guess * Pose2D(0.01 * len(calls), 0.0, 0.0)

    run = run_matcher("drifting", drifting, pairs, [p.guess for p in pairs], repeats=3)
    assert len(calls) == 1 + 3 * len(pairs)
    firsts = [2 + k for k in range(len(pairs))]  # call numbers of the first pass
    for pose, pair, n in zip(run.poses, pairs, firsts, strict=True):
        assert same(pose, pair.guess * Pose2D(0.01 * n, 0.0, 0.0))


def test_repeats_must_be_positive(capsys: pytest.CaptureFixture[str]) -> None:
    err = usage_error(main, capsys, "--data", str(LOG), "--repeats", "0")
    assert "--repeats must be >= 1, got 0" in err


def test_simulated_keyframes_carry_exact_truth_and_the_wheel_odometry() -> None:
    config = SimConfig(world="campus", duration_s=3.0, seed=2, beams=181, fov_deg=180.0,
                       range_max_m=80.0)
    sweeps = list(simulate(config))
    frames = sim_frames(config, every=5)
    assert len(frames) == 6
    for frame, sweep in zip(frames, sweeps[::5], strict=True):
        assert np.array_equal(frame.points, sweep.true_points)
        assert same(frame.true_pose, sweep.true_pose)
        # The simulated wheel odometry: near the truth, not equal to it (1 % scale error).
        assert frame.odom_pose.relative_to(frame.true_pose).translation_norm() < 0.05
    assert frames[0].odom_pose.relative_to(frames[0].true_pose).translation_norm() < 1e-9
    assert frames[-1].odom_pose.relative_to(frames[-1].true_pose).translation_norm() > 1e-4


def test_closure_needs_a_gap_of_two_or_more(capsys: pytest.CaptureFixture[str]) -> None:
    err = usage_error(main, capsys, "--data", str(LOG), "--gap", "1", "--closure")
    assert "--closure needs --gap >= 2" in err


def test_start_step_must_be_positive(capsys: pytest.CaptureFixture[str]) -> None:
    err = usage_error(main, capsys, "--data", str(LOG), "--gap", "3", "--start-step", "0")
    assert "--start-step must be >= 1" in err


@pytest.mark.skipif(not LOG.exists(), reason=f"real log {LOG} not available")
def test_bench_matching_json_with_closure_on_real_pairs() -> None:
    out = run_bench("matching", "--data", str(LOG), "--gap", "3", "--start-step", "1",
                    "--limit", "4", "--methods", "odometry", "plicp", "--peers",
                    "--robust-pairs", "0", "--closure", "--repeats", "2", "--json")
    assert out.returncode == 0, out.stderr
    report = json.loads(out.stdout)
    assert report["pairs"] == 4 and report["start_step"] == 1 and report["repeats"] == 2
    assert set(report["results"]) == {"odometry", "plicp"}
    assert set(report["closure"]) == {"plicp"}  # odometry's chain is its guess
    assert isinstance(report["peer_libraries_not_loaded"], dict)
    c = report["closure"]["plicp"]
    assert 0.0 <= c["agree_5cm_0.5deg"] <= c["agree_10cm_1deg"] <= 1.0
    assert all(math.isfinite(c[k]) and c[k] >= 0 for k in
               ("closure_sigma_xy_m", "closure_sigma_deg", "truth_sigma_xy_m", "truth_sigma_deg"))
    split = c["silently_wrong_confirmed"] + c["silently_wrong_chain_agrees"]
    assert 0.0 <= split <= report["results"]["plicp"]["silently_wrong"]


def test_bench_matching_json_on_simulated_campus_pairs() -> None:
    out = run_bench("matching", "--sim", "campus", "--sim-duration-s", "12", "--lidar",
                    "181,180,80", "--methods", "odometry", "plicp", "--peers", "--robust-pairs",
                    "0", "--json")
    assert out.returncode == 0, out.stderr
    report = json.loads(out.stdout)
    assert report["data"] == "sim:campus" and report["pairs"] == 23
    assert report["sim"]["lidar"] == {"beams": 181, "fov_deg": 180.0, "range_max_m": 80.0,
                                     "rate_hz": 10.0, "bearing_noise_deg": 0.0}
    plicp = report["results"]["plicp"]
    # Exact truth: the matcher's own error, a few mm on every pair.
    assert plicp["ok_5cm_0.5deg"] == 1.0 and plicp["trans_p95_m"] < 0.02


def test_data_and_sim_are_one_or_the_other(capsys: pytest.CaptureFixture[str]) -> None:
    err = usage_error(main, capsys, "--data", str(LOG), "--sim", "rooms")
    assert "not allowed with argument" in err
    assert "range_max_m" in usage_error(main, capsys, "--sim", "campus", "--lidar", "181,180,-1")
    err = usage_error(main, capsys, "--sim", "campus", "--lidar", "181,180")
    assert "BEAMS,FOV_DEG,RANGE_M" in err
