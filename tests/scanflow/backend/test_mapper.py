"""The back end around the front end: keyframes, confirmed closures, optimisation, redraw."""

from __future__ import annotations

import copy
import itertools
import math
from dataclasses import replace

import numpy as np
import pytest
from scanflow.backend import LoopClosure, Mapper, SavedRun, ScanNode
from scanflow.backend.loops import draw_keyframes
from scanflow.config import BackendSettings
from scanflow.frontend import (
    Frontend,
    FrontendStatus,
    default_settings,
    insert_scan,
    occupancy_params,
)
from scanflow.geometry import IDENTITY, Pose2D, compose_arrays, normalize_angles, relative_arrays
from scanflow.maps.matching_map import MatchingMap
from scanflow.maps.occupancy import OccupancyGrid

from .conftest import Drive, output, ring_poses

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


def test_a_front_ends_map_must_be_given_as_the_prior(drive: Drive) -> None:
    """The back end redraws the map from its keyframes: on a map it was not told of, that
    map would be lost."""
    frontend = Frontend(default_settings())
    frontend.process(drive.scans[0], 0.0)
    with pytest.raises(ValueError, match="give it to the back end too"):
        Mapper(frontend, SETTINGS)


def _prior(drive: Drive, count: int) -> OccupancyGrid:
    """The map of the drive's first `count` scans at their true poses."""
    world = MatchingMap(OccupancyGrid(occupancy_params(default_settings())))
    for pose, points in zip(drive.truth[:count], drive.scans[:count], strict=True):
        insert_scan(world, points, Pose2D.from_array(pose))
    return world.grid


def test_on_a_prior_map_the_loop_closes_in_its_frame_and_redraws_keep_it(drive: Drive) -> None:
    """The first third of the ring is a prior map, and the front end tracks on it there (the
    true poses); past it the estimates drift, and they come back round into it. The
    closures with the keyframes made on the prior map pull the drifted ones back in the prior
    map's own frame (keyframe 0 holds where the front end localised it), and every redraw
    draws the keyframes on the prior map, which stays as it was."""
    third = len(drive.truth) // 3
    prior = _prior(drive, third)
    before = prior.log_odds.copy()
    frontend = Frontend(default_settings(), grid=copy.deepcopy(prior))
    mapper = Mapper(frontend, SETTINGS, prior=prior)
    # Drifting from the prior map's end on: the true motion with a heading drift.
    start = drive.drifted[third - 1 : third]
    drifted = np.vstack((drive.truth[:third], compose_arrays(
        drive.truth[third - 1 : third],
        relative_arrays(np.repeat(start, len(drive.truth) - third, axis=0), drive.drifted[third:]),
    )))
    frame, redraws = IDENTITY, 0
    for seq, (pose, points) in enumerate(zip(drifted, drive.scans, strict=True)):
        step = mapper.add(output(seq, (frame * Pose2D.from_array(pose)).to_array()), points)
        if step.correction is not None:
            frame, redraws = step.correction * frame, redraws + 1
    mapper.finish()
    assert mapper.closures and redraws >= 1
    was = _position_errors(drifted, drive.truth)
    now = _position_errors(mapper.trajectory(), drive.truth)  # no alignment: the prior's frame
    assert was.max() > 0.4 and now.max() < 0.5 * was.max() and now.mean() < 0.5 * was.mean()
    np.testing.assert_array_equal(mapper.prior.log_odds, before)  # the prior map untouched
    drawn = mapper.draw_map().grid
    want = draw_keyframes(mapper.nodes, mapper.graph.poses, mapper.params, prior).grid
    np.testing.assert_array_equal(drawn.log_odds, want.log_odds)
    alone = draw_keyframes(mapper.nodes, mapper.graph.poses, mapper.params).grid
    assert not np.array_equal(drawn.log_odds, alone.log_odds)


def test_keyframes_drawn_on_a_prior_map_are_the_front_ends_map(drive: Drive) -> None:
    """Before any redraw, the keyframes drawn on the prior map are the front end's map of the
    prior map and its inserts, bit for bit (a redraw changes nothing it need not)."""
    prior = _prior(drive, 10)
    frontend = Frontend(default_settings(), grid=copy.deepcopy(prior))
    mapper = Mapper(frontend, SETTINGS, prior=prior)
    for seq in range(10, 16):
        mapper.add(output(seq, drive.truth[seq]), drive.scans[seq])
        insert_scan(frontend.map, drive.scans[seq], Pose2D.from_array(drive.truth[seq]))
    drawn = mapper.draw_map().grid
    assert drawn.extent == frontend.map.grid.extent
    np.testing.assert_array_equal(drawn.log_odds, frontend.map.grid.log_odds)
    np.testing.assert_array_equal(drawn.hit_sums, frontend.map.grid.hit_sums)


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


CULL = SETTINGS.model_copy(update={"cull_m": 0.3, "cull_deg": 10.0})


def test_a_parked_robot_adds_no_keyframes(drive: Drive) -> None:
    """Inserts at one place (the motion filter's time trigger while parked): with culling the
    first is the only keyframe and the others hang from it; without, each is a keyframe."""
    pose = drive.truth[3]
    for settings, keyframes in ((CULL, 1), (SETTINGS, 20)):
        mapper = Mapper(Frontend(default_settings()), settings)
        steps = [mapper.add(output(seq, pose), drive.scans[3]) for seq in range(20)]
        assert mapper.graph.node_count == len(mapper.nodes) == keyframes
        assert len(mapper.keyframe_seqs) == keyframes
        np.testing.assert_allclose(mapper.trajectory(), np.tile(pose, (20, 1)), atol=1e-12)
        if settings is CULL:
            assert steps[0].node == 0 and steps[0].culled_to is None
            assert all(s.node is None and s.culled_to == 0 for s in steps[1:])
        else:
            assert all(s.culled_to is None for s in steps)


def test_a_second_lap_over_mapped_ground_adds_no_keyframes() -> None:
    """Twice round the ring at the true poses: every insert of the second lap lies within
    0.2 m of one of the first and hangs from it, so the graph holds the first lap only; the
    path still has every scan, where it was."""
    truth = ring_poses(laps=2.0)
    lap = len(ring_poses(laps=1.0))
    points = np.array([[1.0, 0.0], [0.0, 1.0], [1.0, 1.0], [-1.0, 0.5]])
    mapper = Mapper(Frontend(default_settings()), CULL)
    steps = [mapper.add(output(seq, pose), points) for seq, pose in enumerate(truth)]
    assert mapper.graph.node_count == lap
    assert all(s.node == k for k, s in enumerate(steps[:lap]))
    for s, pose in zip(steps[lap:], truth[lap:], strict=True):
        assert s.node is None and s.culled_to is not None
        nearest = np.argmin(np.hypot(*(truth[:lap, :2] - pose[:2]).T))
        assert s.culled_to == nearest
    gap = mapper.trajectory() - truth
    np.testing.assert_allclose(gap[:, :2], 0.0, atol=1e-9)
    np.testing.assert_allclose(normalize_angles(gap[:, 2]), 0.0, atol=1e-9)


def test_only_tracked_scans_are_culled(drive: Drive) -> None:
    """A scan the front end found by a search (recovered, localised) or after an operator's
    pose is a keyframe even where one is: its link to the graph is the news."""
    pose = drive.truth[3]
    mapper = Mapper(Frontend(default_settings()), CULL)
    mapper.add(output(0, pose), drive.scans[3])
    recovered = replace(output(1, pose), status=FrontendStatus.RECOVERED)
    assert mapper.add(recovered, drive.scans[3]).node == 1
    mapper.relocated()
    assert mapper.add(output(2, pose), drive.scans[3]).node == 2
    assert mapper.add(output(3, pose), drive.scans[3]).culled_to in (0, 1, 2)


def test_after_culled_inserts_the_next_keyframe_is_linked_to_the_one_they_hang_from() -> None:
    """Out along a line, back over it, then on past its start: the first keyframe past the
    mapped ground is linked to the keyframe the return hung from, with the motion the front
    end saw from it, and the odometer counts the whole way."""
    out_and_back = [(0.4 * i, 0.0, 0.0) for i in range(6)] + [
        (0.4 * i + 0.05, 0.0, 0.0) for i in range(4, -1, -1)
    ]
    points = np.array([[1.0, 0.0], [0.0, 1.0], [1.0, 1.0]])
    mapper = Mapper(Frontend(default_settings()), CULL.model_copy(update={"cull_deg": 180.0}))
    for seq, pose in enumerate(out_and_back):
        mapper.add(output(seq, np.array(pose)), points)
    assert mapper.graph.node_count == 6  # the way back hung from the way out
    step = mapper.add(output(11, np.array([-0.5, 0.1, 0.2])), points)
    assert step.node == 6
    i, j, z, _, _ = mapper.graph.edges()
    assert (i[-1], j[-1]) == (0, 6)  # from the keyframe the last culled insert hung from
    np.testing.assert_allclose(z[-1], [-0.5, 0.1, 0.2], atol=1e-12)
    np.testing.assert_allclose(mapper._travelled_m[-1], 2.0 + 0.35 + 1.6 + np.hypot(0.55, 0.1))


def test_culling_keyframes_still_closes_the_ring(drive: Drive) -> None:
    """With the heading drift the revisit is 0.6 m off, beyond cull_m: its keyframes are
    kept, close the loop and redraw the map; the later inserts, now on mapped ground, hang
    from the first lap's keyframes through the redraw. The ring is closed with fewer
    keyframes. (This feed keeps drifting after the redraw, where a front end would track on
    the map, and nothing corrects the culled inserts: the last scans keep ~0.1 m of it.)"""
    mapper, _ = _run(drive, CULL)
    every, _ = _run(drive)
    assert mapper.closures and mapper.graph.node_count < every.graph.node_count
    before = _position_errors(drive.drifted, drive.truth)
    after = _position_errors(mapper.trajectory(), drive.truth)
    assert len(after) == len(drive.truth)
    assert after.max() < 0.25 * before.max()
    assert after.mean() < 0.2 * before.mean()


def test_a_redraw_while_culled_moves_the_front_end_with_the_keyframe_it_hangs_from(
    drive: Drive,
) -> None:
    """Round the ring without optimising, then back at an early keyframe's drawn pose: the
    insert hangs from that keyframe, and the closing optimisation's correction of the front
    end is taken on it (the newest keyframe moves differently), so the front end stays where
    the path puts its last scan."""
    settings = CULL.model_copy(update={"optimise_every": 10_000})
    mapper = Mapper(Frontend(default_settings()), settings)
    for seq, (pose, points) in enumerate(zip(drive.drifted, drive.scans, strict=True)):
        mapper.add(output(seq, pose), points)
    back = mapper.drawn_pose(5) * Pose2D(0.02, 0.01, 0.01)
    step = mapper.add(output(len(drive.drifted), back.to_array()), drive.scans[5])
    assert step.culled_to == 5 and mapper.closures
    drawn = mapper.drawn_poses()
    assert [Pose2D.from_array(row) for row in drawn] == [
        mapper.drawn_pose(k) for k in range(mapper.graph.node_count)
    ]
    correction = mapper.finish().correction
    assert correction is not None
    # A copy of where the map had them; after the redraw, the graph's poses.
    np.testing.assert_array_equal(mapper.drawn_poses(), mapper.graph.poses)
    assert not np.array_equal(drawn, mapper.drawn_poses())
    gap = (correction * back).relative_to(Pose2D.from_array(mapper.trajectory()[-1]))
    assert gap.translation_norm() < 1e-9 and abs(gap.theta) < 1e-9
    # On from there (in the redrawn frame): the odometer counts every insert's step, the
    # culled ones (some late in the ring, and `back`) too.
    path = np.vstack([drive.drifted[:, :2], back.to_array()[:2]])
    odometer = np.hypot(*np.diff(path, axis=0).T).sum()
    on = correction * back * Pose2D(0.0, 5.0, 0.0)
    assert mapper.add(output(len(drive.drifted) + 1, on.to_array()), drive.scans[5]).node
    np.testing.assert_allclose(mapper._travelled_m[-1], odometer + 5.0, atol=1e-9)


def test_two_exact_closures_of_a_turning_robot_agree(monkeypatch: pytest.MonkeyPatch) -> None:
    """The robot comes back drifted by one rigid motion (0.4 m, 3 deg) and turns 30 deg on
    the spot between two keyframes. Exact closures of both imply the same correction of the
    estimates, so the second confirms the first and both enter the graph, whichever way the
    two keyframes face."""
    drift = Pose2D(0.3, -0.25, math.radians(3.0))  # T_estimate_truth of the revisit
    out_and_back = [(0.4 * k, 0.0, 0.0) for k in range(32)] + [(12.4, 0.5, math.pi)]
    out_and_back += [(12.0 - 0.4 * k, 1.0, math.pi) for k in range(29)]
    truth = [Pose2D(*p) for p in out_and_back]
    truth += [Pose2D(0.1, 0.1, 0.0), Pose2D(0.1, 0.1, math.radians(30.0))]
    estimates = truth[:-2] + [drift * t for t in truth[-2:]]
    k1, k2 = len(truth) - 2, len(truth) - 1
    monkeypatch.setattr(
        "scanflow.backend.mapper.loop_candidates",
        lambda poses, travelled, k, settings: [0] if k in (k1, k2) else [],
    )
    mapper = Mapper(Frontend(default_settings()), SETTINGS)

    def exact(nodes, poses, j, k):  # type: ignore[no-untyped-def]
        return LoopClosure(j, k, truth[k].relative_to(truth[j]), np.eye(3) * 1e-6, 0.9)

    mapper.detector.verify = exact  # type: ignore[method-assign]
    points = np.array([[1.0, 0.0], [0.0, 1.0]])
    for seq, pose in enumerate(estimates):
        mapper.add(output(seq, pose.to_array()), points)
    assert [(c.older, c.newer) for c in mapper.closures] == [(0, k1), (0, k2)]


@pytest.mark.parametrize("keyframes", [0, 1])
def test_a_saved_path_without_a_pose_per_stamp_is_refused(drive: Drive, keyframes: int) -> None:
    """A saved run whose path and stamps differ in length is named at once, not kept as a
    path that no longer lines up with its stamps (or left to numpy to trip over)."""
    nodes = [ScanNode(0.0, drive.scans[0], np.zeros((0, 2)), IDENTITY)][:keyframes]
    for path in (np.zeros((2, 3)), np.zeros((3, 2))):
        saved = SavedRun(nodes, [0][:keyframes], drive.truth[:keyframes], np.arange(3.0), path)
        with pytest.raises(ValueError, match=r"path must have shape \(3, 3\)"):
            Mapper(Frontend(default_settings()), SETTINGS, saved)
