"""The back end around the front end: keyframes, confirmed closures, optimisation, redraw."""

from __future__ import annotations

import itertools
import math
from dataclasses import replace

import numpy as np
import pytest
from scanflow.backend import LoopClosure, Mapper, SavedRun
from scanflow.backend.loops import draw_keyframes
from scanflow.config import BackendSettings
from scanflow.frontend import Frontend, default_settings
from scanflow.geometry import IDENTITY, Pose2D

from .conftest import Drive, output

SETTINGS = BackendSettings.model_construct(loop_closure=True)


def _position_errors(poses: np.ndarray, truth: np.ndarray) -> np.ndarray:
    return np.hypot(*(poses - truth)[:, :2].T)


def _feed(mapper: Mapper, drive: Drive) -> list[bool]:
    """The drifting estimates as a front end gives them: in the frame of its current map, which
    moves whenever the back end redraws it. Says, per scan, whether it was redrawn."""
    frame = IDENTITY  # T_current_drifted
    redrawn = []
    for seq, (pose, points) in enumerate(zip(drive.drifted, drive.scans, strict=True)):
        step = mapper.add(output(seq, (frame * Pose2D.from_array(pose)).to_array()), points)
        if step.correction is not None:
            frame = step.correction * frame
        redrawn.append(step.redrawn)
    mapper.finish()
    return redrawn


def _run(drive: Drive, settings: BackendSettings = SETTINGS) -> tuple[Mapper, Frontend]:
    frontend = Frontend(default_settings())
    mapper = Mapper(frontend, settings)
    _feed(mapper, drive)
    return mapper, frontend


def test_closing_the_ring_removes_the_drift(drive: Drive) -> None:
    """Round a ring with a heading drift (0.6 m off when back at the start): the closures at
    the revisit pull every keyframe most of the way back to the truth."""
    mapper, _ = _run(drive)
    before = _position_errors(drive.drifted, drive.truth)
    after = _position_errors(mapper.trajectory(), drive.truth)
    assert before.max() > 0.5
    # What is left peaks opposite the revisit (~0.1 m): a steady heading drift is not the
    # chain's noise model, so the closures spread it along the ring.
    assert after.max() < 0.25 * before.max()
    assert after.mean() < 0.2 * before.mean()
    assert mapper.closures
    # Each closure names an older keyframe at least min_travel_m back.
    assert all(c.older < c.newer for c in mapper.closures)


def test_the_front_end_map_is_redrawn_at_the_optimised_poses(drive: Drive) -> None:
    """The map the front end tracks on is replaced: its walls lie where the truth puts them,
    so a scan at a true pose late in the drive matches it there."""
    frontend = Frontend(default_settings())
    first_map = frontend.map
    mapper = Mapper(frontend, SETTINGS)
    assert any(_feed(mapper, drive))
    assert frontend.map is not first_map
    field = frontend.map.likelihood_field(0)

    def fit(poses: np.ndarray) -> float:
        """Mean map likelihood under every scan placed at `poses`."""
        return float(np.mean([
            field.sample(Pose2D.from_array(p).transform_points(s))[0].mean()
            for p, s in zip(poses, drive.scans, strict=True)
        ]))

    assert fit(drive.truth) > 0.6
    assert fit(drive.truth) > fit(drive.drifted) + 0.2


def test_without_confirmation_every_closure_enters(drive: Drive) -> None:
    confirmed, _ = _run(drive)
    eager, _ = _run(drive, SETTINGS.model_copy(update={"confirm_keyframes": 0}))
    assert len(eager.closures) >= len(confirmed.closures)


def test_while_closures_keep_entering_every_other_keyframe_is_searched(drive: Drive) -> None:
    """busy_search_every=2: every keyframe is searched until a closure enters, then every
    other one while they keep entering; the ring is still closed as well."""
    settings = SETTINGS.model_copy(update={"busy_search_every": 2})
    mapper = Mapper(Frontend(default_settings()), settings)
    verify = mapper.detector.verify
    searched: list[int] = []

    def counted(nodes, poses, j, k):  # type: ignore[no-untyped-def]
        if not searched or searched[-1] != k:
            searched.append(k)
        return verify(nodes, poses, j, k)

    mapper.detector.verify = counted  # type: ignore[method-assign]
    _feed(mapper, drive)
    every, _ = _run(drive)
    entered = sorted({c.newer for c in mapper.closures})
    assert entered and len(mapper.closures) < len(every.closures)
    steps = list(itertools.pairwise(searched))
    assert all(b - a == 1 for a, b in steps if b <= entered[0])
    busy = [(a, b) for a, b in steps
            if any(0 < a - e <= settings.confirm_keyframes for e in entered)]
    assert busy and all(b - a == 2 for a, b in busy)
    after = _position_errors(mapper.trajectory(), drive.truth)
    assert after.max() < 1.2 * _position_errors(every.trajectory(), drive.truth).max()


def test_a_single_wrong_closure_waits_and_is_dropped(drive: Drive) -> None:
    """The first closure found, turned 3 deg: no other closure agrees with it, so it never
    enters the graph, and the drive is still corrected by the others."""
    frontend = Frontend(default_settings())
    mapper = Mapper(frontend, SETTINGS)
    verify = mapper.detector.verify
    corrupted: list[LoopClosure] = []

    def first_one_wrong(nodes, poses, j, k):  # type: ignore[no-untyped-def]
        found = verify(nodes, poses, j, k)
        if isinstance(found, str) or corrupted:
            return found
        turned = replace(found, measurement=found.measurement * Pose2D(0, 0, math.radians(3)))
        corrupted.append(turned)
        return turned

    mapper.detector.verify = first_one_wrong  # type: ignore[method-assign]
    _feed(mapper, drive)
    assert corrupted
    assert all(c is not corrupted[0] for c in mapper.closures)
    assert _position_errors(mapper.trajectory(), drive.truth).max() < 0.15


def test_scans_between_keyframes_follow_their_keyframe(drive: Drive) -> None:
    """Scans not inserted hang from the last keyframe: each keeps its offset to it through
    every optimisation and redraw."""
    frontend = Frontend(default_settings())
    mapper = Mapper(frontend, SETTINGS)
    offset = Pose2D(0.05, 0.01, 0.02)
    frame = IDENTITY
    for seq, (pose, points) in enumerate(zip(drive.drifted, drive.scans, strict=True)):
        keyframe = frame * Pose2D.from_array(pose)
        step = mapper.add(output(2 * seq, keyframe.to_array()), points)
        if step.correction is not None:
            frame = step.correction * frame
            keyframe = step.correction * keyframe
        mapper.add(output(2 * seq + 1, (keyframe * offset).to_array(), inserted=False), points)
    mapper.finish()
    poses = mapper.trajectory()
    assert len(poses) == 2 * len(drive.truth)
    for keyframe, other in zip(poses[0::2], poses[1::2], strict=True):
        gap = Pose2D.from_array(other).relative_to(Pose2D.from_array(keyframe))
        assert gap.relative_to(offset).translation_norm() < 1e-9
        assert abs(gap.relative_to(offset).theta) < 1e-9
    assert mapper.graph.node_count == len(drive.truth)
    assert mapper.closures
    assert mapper.keyframe_seqs == list(range(0, 2 * len(drive.truth), 2))
    np.testing.assert_array_equal(mapper.stamps_s(), 0.1 * np.arange(2 * len(drive.truth)))


def test_scans_before_the_first_keyframe_hang_from_it() -> None:
    frontend = Frontend(default_settings())
    mapper = Mapper(frontend, SETTINGS)
    points = np.array([[1.0, 0.0], [0.0, 1.0], [1.0, 1.0]])
    mapper.add(output(0, np.array([0.1, 0.0, 0.0]), inserted=False), points)
    assert mapper.trajectory().tolist() == [[0.1, 0.0, 0.0]]
    mapper.add(output(1, np.array([0.3, 0.0, 0.0])), points)
    np.testing.assert_allclose(mapper.trajectory(), [[0.1, 0.0, 0.0], [0.3, 0.0, 0.0]])


def test_nothing_to_optimise_without_closures() -> None:
    frontend = Frontend(default_settings())
    mapper = Mapper(frontend, SETTINGS)
    assert mapper.finish().optimised is None
    assert mapper.trajectory().shape == (0, 3)


@pytest.mark.parametrize("mount", [IDENTITY, Pose2D(0.2, 0.0, 0.0)])
def test_keyframes_keep_their_mount(drive: Drive, mount: Pose2D) -> None:
    frontend = Frontend(default_settings())
    mapper = Mapper(frontend, SETTINGS)
    mapper.add(output(0, drive.truth[0]), drive.scans[0], None, mount)
    assert mapper.nodes[0].mount == mount
    assert mapper.nodes[0].no_return.shape == (0, 2)


def test_a_prior_map_is_refused(drive: Drive) -> None:
    """The back end redraws the map from its keyframes: a prior map would be lost."""
    frontend = Frontend(default_settings())
    frontend.process(drive.scans[0], 0.0)
    with pytest.raises(ValueError, match="prior map"):
        Mapper(frontend, SETTINGS)


def test_an_operators_pose_is_a_weak_link_that_the_closures_move(drive: Drive) -> None:
    """Halfway round the ring the front end is put 0.5 m / 4 deg off (an operator's pose
    that was wrong, or one that fixed a wrong track: either way the two halves disagree).
    As a weak link, the jump gives way to the closures at the revisit; as a measured motion
    it would be spread over the whole ring."""
    jump, k_jump = Pose2D(0.4, -0.3, math.radians(4.0)), len(drive.truth) // 2

    def errors(relocate: bool) -> np.ndarray:
        mapper = Mapper(Frontend(default_settings()), SETTINGS)
        frame = IDENTITY
        for seq, (pose, points) in enumerate(zip(drive.truth, drive.scans, strict=True)):
            if seq == k_jump:
                frame = jump * frame
                if relocate:
                    mapper.relocated()
            step = mapper.add(output(seq, (frame * Pose2D.from_array(pose)).to_array()), points)
            if step.correction is not None:
                frame = step.correction * frame
        mapper.finish()
        assert mapper.closures
        return _position_errors(mapper.trajectory(), drive.truth)

    weak, measured = errors(True), errors(False)
    assert weak.max() < 0.08  # 0.03 m here
    assert measured.max() > 0.3  # 0.70 m here


def test_a_run_carried_on_from_its_saved_keyframes_still_closes_the_loop(drive: Drive) -> None:
    """What a restarted matcher does: a new back end from the keyframes at the poses they are
    drawn at and the path so far (as the map server keeps them), on the map they draw. The
    revisit after the restart still closes the ring; the path covers every scan."""
    first = Mapper(Frontend(default_settings()), SETTINGS)
    cut = int(0.6 * len(drive.truth))
    frame, drawn, path = IDENTITY, [], []  # as the map server holds them
    for seq in range(cut):
        pose = frame * Pose2D.from_array(drive.drifted[seq])
        step = first.add(output(seq, pose.to_array()), drive.scans[seq])
        drawn.append(pose.to_array())
        path.append(pose.to_array())
        if step.correction is not None:
            frame = step.correction * frame
            drawn, path = list(first.graph.poses), list(first.trajectory())
    saved = SavedRun(first.nodes, first.keyframe_seqs, np.array(drawn), first.stamps_s(),
                     np.array(path))
    frontend = Frontend(default_settings(), grid=draw_keyframes(
        saved.nodes, saved.poses, first.params).grid)
    resumed = Mapper(frontend, SETTINGS, saved)
    assert resumed.keyframe_seqs == first.keyframe_seqs
    np.testing.assert_allclose(resumed.trajectory(), path, atol=1e-9)
    for seq in range(cut, len(drive.truth)):
        pose = frame * Pose2D.from_array(drive.drifted[seq])
        step = resumed.add(output(seq, pose.to_array()), drive.scans[seq])
        if step.correction is not None:
            frame = step.correction * frame
    resumed.finish()
    assert any(c.older < len(saved.nodes) for c in resumed.closures)  # to keyframes before
    after = _position_errors(resumed.trajectory(), drive.truth)
    before = _position_errors(drive.drifted, drive.truth)
    assert len(after) == len(drive.truth)
    assert after.max() < 0.25 * before.max()
