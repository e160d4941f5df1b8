"""The matcher's recent inserts, the inserts rebuilt from keyframes, and its whole-map state."""

from __future__ import annotations

import numpy as np
import pytest
from scanflow.backend import Mapper, SavedRun
from scanflow.backend.loops import ScanNode
from scanflow.config import BackendSettings, FrontendSettings
from scanflow.frontend import Frontend, FrontendOutput, FrontendStatus
from scanflow.geometry import IDENTITY, Pose2D
from scanflow.wire import MapRedrawMessage

from services.matcher.recent import RecentInserts, keyframe_inserts, map_state

LOOP_CLOSURE = BackendSettings.model_construct(loop_closure=True)
RUN = 77  # the tracker's run token


def test_recent_inserts_send_a_chain_again_or_name_what_they_keep() -> None:
    recent = RecentInserts(3, RUN)
    assert recent.last_seq is None
    for seq, previous in ((0, None), (3, 0), (5, 3), (9, 5)):
        recent.add(seq, previous, f"insert {seq}".encode())
    assert recent.last_seq == 9
    assert recent.between(0, 9) == [b"insert 3", b"insert 5", b"insert 9"]
    assert recent.between(3, 5) == [b"insert 5"]
    with pytest.raises(LookupError, match=r"after seq -1 through 3 .* seqs 3\.\.9"):
        recent.between(-1, 3)  # the run's first is no longer kept
    with pytest.raises(LookupError, match="through 7"):
        recent.between(5, 7)  # no insert of seq 7
    with pytest.raises(LookupError, match="the last 0 inserts: none"):
        RecentInserts(0, RUN).between(-1, 0)


def test_a_resumed_runs_first_insert_is_not_the_runs_first() -> None:
    """A matcher resumed mid-run: asked for everything from the run's first insert (a map
    server that lost its map), it must not answer with the inserts since it resumed."""
    recent = RecentInserts(8, RUN, resumed=True)
    for seq, previous in ((100, None), (101, 100), (104, 101)):
        recent.add(seq, previous, f"insert {seq}".encode())
    with pytest.raises(LookupError, match="after seq -1 through 104"):
        recent.between(-1, 104)
    assert recent.between(100, 104) == [b"insert 101", b"insert 104"]


def test_inserts_past_the_recent_ones_come_from_the_back_ends_keyframes() -> None:
    """Without culling, every insert of a robot tracked with loop closure is a keyframe:
    rebuilt at the pose it is drawn at, chained by seq; seqs it does not hold are named."""
    seqs, poses = [2, 5, 9], np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.1], [2.0, 0.5, 0.2]])
    nodes = [ScanNode(0.1 * s, np.full((3, 2), s, float), np.zeros((1, 2)), Pose2D(0.1, 0, 0))
             for s in seqs]
    saved = SavedRun(nodes, seqs, poses, np.array([0.2, 0.5, 0.9]), poses)
    mapper = Mapper(Frontend(FrontendSettings()), LOOP_CLOSURE, saved)
    inserts, culled = keyframe_inserts(mapper, "r", RUN, 2, 9)
    assert [(m.seq, m.previous_seq) for m in inserts] == [(5, 2), (9, 5)] and culled == 0
    assert [m.pose for m in inserts] == [Pose2D.from_array(p) for p in poses[1:]]
    assert all(m.keyframe and m.run == RUN for m in inserts)
    np.testing.assert_array_equal(inserts[1].points, nodes[2].points)
    assert inserts[0].mount == Pose2D(0.1, 0, 0) and inserts[0].stamp_s == 0.5
    assert [m.previous_seq for m in keyframe_inserts(mapper, "r", RUN, -1, 2)[0]] == [None]
    with pytest.raises(LookupError, match=r"keyframes \(3: seqs 2\.\.9\) .* seq 10 \(through\)"):
        keyframe_inserts(mapper, "r", RUN, 2, 10)


@pytest.mark.parametrize("culled_first", [True, False], ids=["culled first", "keyframe first"])
def test_a_resumed_back_end_takes_an_unknown_seq_from_before_its_restart(
    culled_first: bool,
) -> None:
    """A resumed back end knows no culled seqs from before the restart: a map server whose
    last insert is one of them (seq 11, culled then) is sent the keyframes after it. Seqs
    since the restart (its first insert a culled one or a keyframe) must be known (13: no
    insert)."""
    seqs, poses = [2, 5, 9], np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.1], [2.0, 0.5, 0.2]])
    nodes = [ScanNode(0.1 * s, np.full((3, 2), s, float), np.zeros((1, 2)), IDENTITY)
             for s in seqs]
    saved = SavedRun(nodes, seqs, poses, np.array([0.2, 0.5, 0.9]), poses)
    mapper = Mapper(Frontend(FrontendSettings()), CULLING, saved)
    assert mapper.resumed_keyframes == 3
    assert keyframe_inserts(mapper, "r", RUN, 7, 9)[0][0].previous_seq == 7  # none since: any
    far = [5.0, 0.0, 0.0]
    for seq, pose in ((12, poses[2]), (14, far)) if culled_first else ((12, far), (14, far)):
        mapper.add(_tracked(seq, Pose2D.from_array(pose)), nodes[0].points)
    new, culled_seq = (14, 12) if culled_first else (12, 14)
    assert mapper.keyframe_seqs == [2, 5, 9, new] and list(mapper.culled_seqs) == [culled_seq]
    inserts, culled = keyframe_inserts(mapper, "r", RUN, 11, 14)
    assert [(m.seq, m.previous_seq) for m in inserts] == [(new, 11)] and culled == 1
    with pytest.raises(LookupError, match=r"seq 13 \(after\)"):
        keyframe_inserts(mapper, "r", RUN, 13, 14)
    fresh = Mapper(Frontend(FrontendSettings()), CULLING)  # not resumed: every seq is known
    fresh.add(_tracked(0, IDENTITY), nodes[0].points)
    with pytest.raises(LookupError, match=r"seq -3 \(after\)"):
        keyframe_inserts(fresh, "r", RUN, -3, 0)


def test_inserts_culled_as_keyframes_are_left_out_and_counted() -> None:
    """Parked at two places (culling on): seqs 0 and 3 are keyframes, 1, 2 and 4 hang from
    them. A resend rebuilds the keyframes, chained from `after` across the culled ones, and
    says how many culled inserts it lacks; it accepts a culled seq at either end."""
    mapper = Mapper(Frontend(FrontendSettings()), CULLING)
    points = np.array([[1.0, 0.0], [0.0, 1.0], [1.0, 1.0]])
    for seq, x in enumerate((0.0, 0.0, 0.0, 1.0, 1.0)):
        mapper.add(_tracked(seq, Pose2D(x, 0.0, 0.0)), points)
    assert mapper.keyframe_seqs == [0, 3] and list(mapper.culled_seqs) == [1, 2, 4]
    inserts, culled = keyframe_inserts(mapper, "r", RUN, 0, 4)
    assert [(m.seq, m.previous_seq) for m in inserts] == [(3, 0)] and culled == 3
    inserts, culled = keyframe_inserts(mapper, "r", RUN, 1, 3)
    assert [(m.seq, m.previous_seq) for m in inserts] == [(3, 1)] and culled == 1
    inserts, culled = keyframe_inserts(mapper, "r", RUN, -1, 2)
    assert [(m.seq, m.previous_seq) for m in inserts] == [(0, None)] and culled == 2
    assert keyframe_inserts(mapper, "r", RUN, 1, 2) == ([], 1)
    with pytest.raises(LookupError, match=r"culled inserts \(3\) do not hold seq 5"):
        keyframe_inserts(mapper, "r", RUN, 0, 5)


CULLING = LOOP_CLOSURE.model_copy(update={"cull_m": 0.3, "cull_deg": 10.0})


def _tracked(seq: int, pose: Pose2D) -> FrontendOutput:
    """An insert the front end tracked on its map (one the back end may cull)."""
    return FrontendOutput(
        seq=seq, stamp_s=0.1 * seq, pose=pose, covariance=np.eye(3) * 1e-4,
        status=FrontendStatus.TRACKED, method="gn", iterations=3, score=0.8, message="",
        inserted=True, prediction_source="odometry",
    )


def test_the_whole_maps_path_is_the_last_redraws_then_the_front_ends() -> None:
    """The path as the map server has it: corrected at the last redraw (its path through the
    redraw's scan), then the estimates the front end made since."""
    frontend = Frontend(FrontendSettings())
    for k in range(5):
        frontend.trajectory.append(float(k), Pose2D(float(k), 0.0, 0.0))
    recent = RecentInserts(2, RUN)
    redrawn = np.array([[0.0, 1.0, 0.0], [1.0, 1.0, 0.0], [2.0, 1.0, 0.0]])
    redraw = MapRedrawMessage("r", 2, Pose2D(), np.zeros(0, np.int64), np.zeros((0, 3)),
                              np.arange(3.0), redrawn)
    recent.tracked(2, True, redraw)
    recent.tracked(4, False)
    state = map_state("r", frontend, recent)
    assert state.run == RUN
    np.testing.assert_array_equal(state.stamps_s, np.arange(5.0))
    np.testing.assert_array_equal(state.poses[:3], redrawn)
    np.testing.assert_array_equal(state.poses[3:], [[3.0, 0.0, 0.0], [4.0, 0.0, 0.0]])
    assert (state.seq, state.insert_seq, state.keyframes) == (4, 2, None)
    with pytest.raises(LookupError, match="has put no scan into its map"):
        map_state("r", frontend, RecentInserts(2, RUN))
