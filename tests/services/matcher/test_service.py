"""The matcher service: robots, resumes, resends and requests; a bad prior map stops it."""

from __future__ import annotations

import itertools
import logging
import re
import threading
import time
from dataclasses import replace

import numpy as np
import pytest
from scanflow import keys
from scanflow.backend import Mapper
from scanflow.backend.loops import ScanNode, draw_keyframes
from scanflow.config import BackendSettings, FrontendSettings, MatcherSettings, ZenohSettings
from scanflow.frontend import Frontend
from scanflow.geometry import IDENTITY, Pose2D
from scanflow.maps.export import grid_from_npz_bytes, npz_arrays, save_npz, write_npz
from scanflow.maps.occupancy import OccupancyGrid, OccupancyParams
from scanflow.pipeline import DeskewStage
from scanflow.sim import SimConfig, simulate
from scanflow.wire import (
    DeskewedScanMessage,
    MapInsertMessage,
    MapRedrawMessage,
    MapRef,
    MapStateMessage,
    MatchRequest,
    PoseEstimateMessage,
    ResumeMessage,
    codec,
    decode_any,
)

from services.common.keyframes import keyframes_message
from services.common.resend import FIRST, resend_selector
from services.common.robots import RobotLimitError
from services.matcher import service as service_module
from services.matcher.recent import RecentInserts
from services.matcher.service import MatcherService, _NoMapServerYetError
from services.matcher.waiting import Placed, Waiting

LOOP_CLOSURE = BackendSettings.model_construct(loop_closure=True)


def asked(service: MatcherService, robot_id: str):
    """What the robot's front end would start from, the resume query asked here and now."""
    return service._seeded(robot_id, *service._resume_query(robot_id))


def answered(service: MatcherService, timeout_s: float = 10.0) -> None:
    """Handle what comes into the inbox (a resume query's answer) until it stays empty."""
    while (item := service.shell.inbox.get(timeout_s)) is not None:
        service.handle(*item)
        timeout_s = 0.2


def recording(service: MatcherService) -> list:
    """The messages the service puts from now on, decoded, instead of putting them."""
    sent: list = []
    service.shell.put = lambda key, payload: sent.append(decode_any(payload))
    return sent


def resume_answer(tmp_path, robot_id: str, **fields) -> bytes:
    """A map server's resume answer for `robot_id`: a two-hit map and a path of two poses."""
    grid = OccupancyGrid(OccupancyParams())
    grid.insert_scan(np.array([[2.0, 0.0], [2.0, 0.5]]), np.zeros(2))
    npz = write_npz(tmp_path / "map.npz", npz_arrays(grid)).read_bytes()
    path = np.array([[0.0, 0.0, 0.0], [0.4, 0.1, 0.2]])
    return ResumeMessage(robot_id, grid.revision, npz, np.array([0.1, 0.2]), path,
                         **fields).encode()


def matcher() -> MatcherService:
    return MatcherService(
        MatcherSettings(), FrontendSettings(), ZenohSettings(mode="peer", connect=[]),
        LOOP_CLOSURE,
    )


def test_a_redraw_too_big_for_the_wire_is_counted_not_raised(monkeypatch) -> None:
    """A path past MAX_BULK_BYTES (~16M scans; made small here) no longer fits one message:
    the redraw is dropped, counted and logged, and the estimate after it still goes out (the
    caller carries on)."""
    monkeypatch.setattr(codec, "MAX_BULK_BYTES", 2**20)
    service = matcher()
    try:
        n = 2**20 // 32 + 1
        huge = MapRedrawMessage("r", n, Pose2D(), np.zeros(0, np.int64), np.zeros((0, 3)),
                                np.zeros(n), np.zeros((n, 3)))
        service._put_redraw(huge)
        assert service.shell.counters.get("backend.redraws_unsent") == 1
        assert service.shell.outbox.depth() == 0
    finally:
        service.shell.close(flush_s=0.0)


def test_an_operators_pose_before_a_resumed_robots_first_scan_is_a_weak_link() -> None:
    """The pose waits for the robot's first scan; when that scan resumes the robot with its
    keyframes, the pose is applied and the graph told that the motion across it is unknown."""
    service = matcher()
    try:
        told = Pose2D(3.0, 1.0, 0.5)
        service.initial_poses["r"] = Placed(told)
        relocated: list[bool] = []

        class Spy(Mapper):
            def relocated(self) -> None:
                relocated.append(True)
                super().relocated()

        frontend_of: dict[str, Frontend] = {}

        def seeded(robot_id: str) -> tuple[Frontend, ResumeMessage]:
            frontend = Frontend(FrontendSettings())
            frontend_of[robot_id] = frontend
            return frontend, ResumeMessage(robot_id, 0, b"", np.zeros(0), np.zeros((0, 3)))

        service._resumed_back_end = lambda robot_id, frontend, resumed: Spy(frontend, LOOP_CLOSURE)
        frontend = service._install("r", seeded("r"))
        assert frontend is frontend_of["r"] and relocated == [True]
        assert "r" not in service.initial_poses
    finally:
        service.shell.close(flush_s=0.0)


def test_operators_poses_for_robots_not_seen_yet_take_places_among_max_robots() -> None:
    """Poses PUT for ever new robot ids are bounded as their scans are (an audit stored 1,500
    and answered each 200 while the robot was refused): a kept pose holds one of the robot's
    places, so its own first scan is still admitted."""
    service = MatcherService(
        MatcherSettings(max_robots=2), FrontendSettings(), ZenohSettings(mode="peer", connect=[]),
        BackendSettings(),
    )
    try:
        service.place("a", Pose2D(1.0, 0.0, 0.0))
        service.place("b", Pose2D(2.0, 0.0, 0.0))
        with pytest.raises(RobotLimitError, match="robot 'c' refused: this matcher keeps 2"):
            service.place("c", Pose2D())
        assert sorted(service.initial_poses) == ["a", "b"]
        assert service.shell.counters.get("robots_refused") == 1
        service.place("a", Pose2D(3.0, 0.0, 0.0))  # a robot with a place keeps it
        assert service.initial_poses["a"] == Placed(Pose2D(3.0, 0.0, 0.0))
        frontend = service._install("a", None)
        assert frontend.initial_pose == Pose2D(3.0, 0.0, 0.0) and "a" not in service.initial_poses
        with pytest.raises(RobotLimitError):
            service.place("c", Pose2D())  # a and b still hold the two places
    finally:
        service.shell.close(flush_s=0.0)


def test_a_new_robots_scan_in_hand_holds_its_place_against_an_operators_pose() -> None:
    """The worker admits a new robot's scan and registers it a moment later; an operator's pose
    for another robot, on a query thread, could take the last place meanwhile and both were
    kept, one past max_robots (a review). The scan in hand holds its place under the lock."""
    service = MatcherService(
        MatcherSettings(max_robots=2), FrontendSettings(), ZenohSettings(mode="peer", connect=[]),
        BackendSettings(),
    )
    try:
        service.place("a", Pose2D())
        placed_meanwhile: list[BaseException] = []
        install = service._install

        def install_after_a_pose(robot_id: str, seeded: object) -> Frontend:
            try:  # an operator's pose arrives between the admission and the registration
                service.place("b", Pose2D())
            except RobotLimitError as exc:
                placed_meanwhile.append(exc)
            return install(robot_id, seeded)

        service._install = install_after_a_pose
        arc = np.linspace(0, 6, 60)
        ring = np.column_stack((3 * np.cos(arc), 3 * np.sin(arc)))
        service.handle("scan", DeskewedScanMessage("x", 0, 0.0, ring, "odometry", False, 60, 0))
        assert len(placed_meanwhile) == 1 and "x" in service.frontends
        assert sorted({*service.frontends, *service.initial_poses}) == ["a", "x"]
        assert service._entering is None
    finally:
        service.shell.close(flush_s=0.0)


def test_a_robot_resumes_from_the_map_servers_one_answer_or_says_why_not(
    tmp_path, caplog
) -> None:
    """The map server's answer (here served on the matcher's own session) seeds the front end
    at the path's last pose; an answer without keyframes (loop closure off there) leaves the
    robot without loop closure, counted and named; an unreadable one starts it afresh."""
    caplog.set_level(logging.INFO)
    service = matcher()
    grid = OccupancyGrid(OccupancyParams())
    grid.insert_scan(np.array([[2.0, 0.0], [2.0, 0.5]]), np.zeros(2))
    npz = write_npz(tmp_path / "map.npz", npz_arrays(grid)).read_bytes()
    path = np.array([[0.0, 0.0, 0.0], [0.4, 0.1, 0.2]])
    answers = {
        "a": ResumeMessage("a", grid.revision, npz, np.array([1.0, 2.0]), path).encode(),
        "b": b"\x81\xa4type\xa6resume",  # another version's, say
        "c": ResumeMessage("c", 1, b"PK\x03\x04 cut short", np.array([1.0, 2.0]), path).encode(),
        "d": ResumeMessage("d", grid.revision, npz, np.array([1.0, 2.0]), path,
                           odom_pose=Pose2D(10.0, 0.0, 0.0)).encode(),
    }
    service.shell.serve(
        "scanflow/*/map/resume",
        lambda q: q.reply(q.key_expr, answers[str(q.key_expr).split("/")[1]]), side=True,
    )
    try:
        seeded = asked(service, "a")
        assert seeded is not None
        frontend, resumed = seeded
        assert frontend.initial_pose == Pose2D.from_array(path[-1])
        np.testing.assert_array_equal(frontend.map.grid.log_odds, grid.log_odds)
        assert service._resumed_back_end("a", frontend, resumed) is None
        assert service.shell.counters.get("backend.resumed_without") == 1
        assert "keeps no keyframes of it (SCANFLOW_BACKEND_LOOP_CLOSURE is off there" in caplog.text
        assert asked(service, "b") is None
        assert "robot b: no map to resume from, starting fresh (its answer is unreadable" in (
            caplog.text
        )
        assert asked(service, "c") is None  # a broken map: named, and the robot starts afresh
        assert ("robot c: no map to resume from, starting fresh (its answer is unreadable: the "
                "map server's map of c: not a readable .npz (BadZipFile") in caplog.text
        # With the odometry pose of the path's end, the first scan after a long outage is
        # predicted by the odometry since then (without it: held at the path's end).
        for robot, source in (("a", "initial"), ("d", "odometry")):
            frontend, _ = asked(service, robot)
            out = frontend.process(np.zeros((3, 2)), 30.0, Pose2D(13.0, 0.0, 0.0))
            assert out.prediction_source == source, robot
        assert out.pose == Pose2D.from_array(path[-1]) * Pose2D(3.0, 0.0, 0.0)
    finally:
        service.shell.close(flush_s=0.0)


def feed(service: MatcherService, duration_s: float, robot: str = "r") -> None:
    """The simulator's scans of `robot`, deskewed as the deskew service does, handled."""
    stage = DeskewStage()
    for frame in simulate(SimConfig(duration_s=duration_s, seed=2)):
        for sample in frame.odometry:
            stage.add_odometry(sample)
        result = stage.process(frame.scan)
        stamp = result.reference_stamp_s
        beams = len(frame.scan.ranges_m)
        service.handle("scan", DeskewedScanMessage(
            robot, frame.scan.seq, stamp, result.points, result.source_used, False, beams,
            beams - len(result.points), result.no_return_points, stage.odometry_pose_at(stamp),
        ))


def test_every_message_of_a_run_carries_its_token_and_a_resumed_run_the_map_servers(
    tmp_path,
) -> None:
    """Inserts and estimates of one run carry one token; a replay (seqs back to 0) draws a new
    one; a robot resumed from the map server carries on the token of the run its map is of
    (a new one when the map server knows none); one that could not resume starts a map of
    its own under a new one."""
    service = MatcherService(MatcherSettings(), FrontendSettings(),
                             ZenohSettings(mode="peer", connect=[]))
    sent = recording(service)
    answers = {robot: resume_answer(tmp_path, robot, run=run)
               for robot, run in (("a", 5), ("b", 0))}
    service.shell.serve(
        "scanflow/*/map/resume",
        lambda q: q.reply(q.key_expr, answers[str(q.key_expr).split("/")[1]]), side=True,
    )
    try:
        runs = []
        for _ in range(2):
            feed(service, 1.0)
            assert {type(m).__name__ for m in sent} == {"MapInsertMessage", "PoseEstimateMessage"}
            runs.append({m.run for m in sent})
            sent.clear()
        assert [len(r) for r in runs] == [1, 1] and runs[0] != runs[1] and 0 not in runs[0]
        for robot in "abc":  # c: the map server fails to answer
            service._install(robot, asked(service, robot))
        assert service.recent["a"].run == 5
        assert service.recent["b"].run not in (0, 5, *runs[1])
        assert service.recent["c"].run not in (0, 5, service.recent["b"].run, *runs[1])
        # A resend answered from a run that ended while it was asked for: refused, not sent
        # with the new run's map under the old token.
        with pytest.raises(LookupError, match="r: its tracker started another run meanwhile"):
            service._older("r", RecentInserts(4, runs[0].pop()), -1, 5, LookupError("not kept"))
    finally:
        service.shell.close(flush_s=0.0)


def test_past_its_recent_inserts_a_matcher_without_a_back_end_sends_its_whole_map() -> None:
    """Inserts older than the last `resend_inserts` are gone, and without loop closure there
    are no keyframes to rebuild them from: the answer is the front end's whole map, the seq of
    its last insert and its path, taken at one instant. The recent ones still come as
    inserts."""
    service = MatcherService(
        MatcherSettings(resend_inserts=2), FrontendSettings(),
        ZenohSettings(mode="peer", connect=[]),
    )
    try:
        feed(service, 6.0)
        recent = service.recent["r"]
        inserted = recent.map_seq
        assert recent.scan_seq == 59 and inserted is not None and inserted > 20
        key = keys.map_key("r", "resend")
        payloads, errors = service.shell.get(resend_selector(key, FIRST, inserted), 5.0)
        assert errors == [] and len(payloads) == 1
        state = decode_any(payloads[0])
        assert isinstance(state, MapStateMessage) and state.robot_id == "r"
        assert (state.seq, state.insert_seq) == (59, inserted)
        frontend = service.frontends["r"]
        grid = grid_from_npz_bytes(state.map_npz, "the state")
        np.testing.assert_array_equal(grid.log_odds, frontend.map.grid.log_odds)
        np.testing.assert_array_equal(grid.hit_sums, frontend.map.grid.hit_sums)
        np.testing.assert_array_equal(state.poses, frontend.trajectory.poses)
        assert len(state.stamps_s) == 60
        assert service.shell.counters.get("map_states_sent") == 1
        # The insert before the last: the one the kept chain starts from.
        before = next(a for a in range(inserted - 1, FIRST, -1) if _chains(recent, a, inserted))
        payloads, errors = service.shell.get(resend_selector(key, before, inserted), 5.0)
        (again,) = [decode_any(p) for p in payloads]
        assert isinstance(again, MapInsertMessage) and again.seq == inserted
        assert service.shell.counters.get("inserts_resent") == 1
        assert service.shell.counters.get("map_states_sent") == 1
    finally:
        service.shell.close(flush_s=0.0)


def _chains(recent: RecentInserts, after: int, through: int) -> bool:
    try:
        recent.between(after, through)
    except LookupError:
        return False
    return True


def test_a_gap_with_culled_inserts_gets_the_whole_map_and_the_keyframes() -> None:
    """With loop closure past its recent inserts the matcher rebuilds a gap from the back
    end's keyframes when they are all of it; when the back end culled some of the missing
    inserts it sends its whole map instead, with the keyframes where they are drawn (the map
    server needs them for the next redraw)."""
    culling = BackendSettings.model_construct(loop_closure=True, cull_m=0.3)
    service = MatcherService(
        MatcherSettings(resend_inserts=2), FrontendSettings(),
        ZenohSettings(mode="peer", connect=[]), culling,
    )
    try:
        feed(service, 6.0)
        mapper, recent = service.mappers["r"], service.recent["r"]
        seqs, culled = list(mapper.keyframe_seqs), list(mapper.culled_seqs)
        assert len(seqs) > 3 and culled
        key = keys.map_key("r", "resend")
        # Two keyframes with no culled insert between them: the chain.
        a, b = next((a, b) for a, b in itertools.pairwise(seqs)
                    if not any(a < c < b for c in culled) and b < seqs[-1])
        payloads, _ = service.shell.get(resend_selector(key, a, b), 5.0)
        (again,) = [decode_any(p) for p in payloads]
        assert isinstance(again, MapInsertMessage) and (again.seq, again.previous_seq) == (b, a)
        # From the start, culled inserts included: the whole map.
        payloads, _ = service.shell.get(resend_selector(key, FIRST, recent.map_seq), 5.0)
        (state,) = [decode_any(p) for p in payloads]
        assert isinstance(state, MapStateMessage) and state.keyframes is not None
        assert state.keyframes.seqs.tolist() == seqs
        np.testing.assert_array_equal(state.keyframes.poses, mapper.drawn_poses())
        np.testing.assert_array_equal(state.keyframes.hits, np.concatenate(
            [n.points for n in mapper.nodes]))
        assert state.insert_seq == recent.map_seq and state.seq == 59
        assert service.shell.counters.get("map_states_sent") == 1
        assert service.shell.counters.get("inserts_resent") == 1
    finally:
        service.shell.close(flush_s=0.0)


def test_a_robot_resumed_on_a_prior_map_keeps_drawing_on_it(tmp_path) -> None:
    """A restarted matcher on a prior map rebuilds the back end from the map server's
    keyframes on that prior map: its redraws keep the prior map's walls."""
    grid = OccupancyGrid(OccupancyParams())
    grid.insert_scan(np.array([[2.0, 0.0], [2.0, 0.5]]), np.zeros(2))
    prior = save_npz(grid, tmp_path / "prior.npz")
    service = MatcherService(
        MatcherSettings(), FrontendSettings(prior_map=str(prior)),
        ZenohSettings(mode="peer", connect=[]), LOOP_CLOSURE,
    )
    try:
        node = ScanNode(0.1, np.array([[1.0, 1.0], [1.0, 1.5]]), np.zeros((0, 2)), IDENTITY)
        kept = keyframes_message("r", [3], [node], np.zeros((1, 3)))
        resumed = ResumeMessage("r", 1, b"", np.array([0.1]), np.zeros((1, 3)), kept)
        frontend = Frontend(FrontendSettings(), grid=service.start.grid())
        mapper = service._resumed_back_end("r", frontend, resumed)
        assert mapper is not None and mapper.prior is not None
        np.testing.assert_array_equal(mapper.prior.log_odds, grid.log_odds)
        drawn = mapper.draw_map().grid
        assert drawn.occupied_mask().sum() > draw_keyframes(
            mapper.nodes, mapper.graph.poses, mapper.params).grid.occupied_mask().sum()
    finally:
        service.shell.close(flush_s=0.0)


@pytest.mark.parametrize(
    ("method", "under_lock"),
    [("csm", False), ("csm_exhaustive", False), ("csm+plicp", False), ("global", False),
     ("gn", True), ("ndt", True)],
)
def test_a_search_request_runs_on_a_copy_of_the_map_without_the_lock(
    monkeypatch, method, under_lock
) -> None:
    """A csm search with a wide window takes seconds to minutes: holding the lock that every
    robot's tracking takes would stall them all (an audit saw 11 s). Searches read a copy of
    the map, with the same answer; the quick methods read the live map under the lock."""
    service = matcher()
    try:
        frames = list(simulate(SimConfig(beams=180, duration_s=0.6, seed=2)))
        stage = DeskewStage()
        frontend = service._install("r", None)
        for frame in frames[:-1]:
            deskewed = stage.process(frame.scan)
            frontend.process(deskewed.points, frame.scan.stamp_s, None, 0)
        source = DeskewStage().process(frames[-1].scan).points
        request = MatchRequest(method, source, MapRef("r"), frames[-1].true_pose)
        seen: list[bool] = []
        real_answer = service_module.answer

        def spy(request, map_of):  # type: ignore[no-untyped-def]
            free = service.lock.acquire(blocking=False)
            if free:
                service.lock.release()
            seen.append(not free)
            return real_answer(request, map_of)

        monkeypatch.setattr(service_module, "answer", spy)
        response = service.respond(request)
        assert seen == [under_lock]
        expected = real_answer(request, service._map_of)
        assert (response.status, response.pose) == (expected.status, expected.pose)
    finally:
        service.shell.close(flush_s=0.0)


def test_a_map_server_too_busy_to_answer_in_time_is_waited_for_not_started_over(caplog) -> None:
    """A resume query the map server holds past resume_timeout_s gets Zenoh's 'Timeout' error
    reply: that is no answer yet, as silence is (the robot waits, its scans counted), not an
    answer that starts the robot afresh over the map server's map."""
    caplog.set_level(logging.INFO)
    service = MatcherService(
        MatcherSettings(resume_timeout_s=0.5), FrontendSettings(),
        ZenohSettings(mode="peer", connect=[]), BackendSettings(),
    )
    held: list[object] = []  # queries kept unanswered: the map server is busy
    # A plain queryable that keeps its queries open (the shell's own serve closes each one).
    busy = service.shell._side_session().declare_queryable("scanflow/*/map/resume", held.append)
    try:
        with pytest.raises(_NoMapServerYetError):
            asked(service, "r")
        assert held and "r" in service.awaiting and "r" not in service.frontends
        assert "starting fresh" not in caplog.text
    finally:
        busy.undeclare()
        service.shell.close(flush_s=0.0)


def test_a_robot_waiting_for_its_map_holds_up_no_other_robot(tmp_path) -> None:
    """The resume query goes out on a thread of its own: while the map server sits on it, the
    other robots' scans are tracked; the answer then starts the robot from the map server's
    map and its scans that waited are tracked in order. A replay while it waits, or a retire,
    drops the wait (and the answer when it comes)."""
    service = MatcherService(MatcherSettings(), FrontendSettings(),
                             ZenohSettings(mode="peer", connect=[]))
    sent = recording(service)
    held: list = []  # the map server is busy: it answers when the test says
    busy = service.shell._side_session().declare_queryable("scanflow/*/map/resume", held.append)
    ring = np.column_stack((3 * np.cos(np.linspace(0, 6, 60)), 3 * np.sin(np.linspace(0, 6, 60))))

    def scan(robot: str, seq: int) -> DeskewedScanMessage:
        return DeskewedScanMessage(robot, seq, 0.1 * seq, ring, "odometry", False, 60, 0)

    def poses_of(robot: str) -> list[int]:
        return [m.seq for m in sent if isinstance(m, PoseEstimateMessage) and m.robot_id == robot]

    try:
        for seq in (5, 6, 7):
            service.handle("scan", scan("slow", seq))
        for seq in range(3):
            service.handle("scan", scan("other", seq))
        assert poses_of("other") == [0, 1, 2] and poses_of("slow") == []
        deadline = time.monotonic() + 10.0
        while not held:
            assert time.monotonic() < deadline, "the resume query never reached the map server"
            time.sleep(0.01)
        (query,) = held
        query.reply(query.key_expr, resume_answer(tmp_path, "slow"))
        query.drop()
        answered(service)
        assert poses_of("slow") == [5, 6, 7] and service.shell.counters.get("resumed_robots") == 1
        assert "slow" not in service.resuming and "slow" not in service.awaiting
        for robot in ("replayed", "retired"):
            service.handle("scan", scan(robot, 9))
        service.handle("scan", scan("replayed", 0))  # a new run while it waited
        assert service.retire("retired").known  # its waiting scans: something of it
        assert poses_of("replayed") == [0] and "retired" not in service.frontends
        deadline = time.monotonic() + 10.0
        while len(held) < 3:
            assert time.monotonic() < deadline, "the resume queries never reached the map server"
            time.sleep(0.01)
        service.handle("scan", scan("retired", 10))  # back after its retire: asks again
        while len(held) < 4:
            assert time.monotonic() < deadline, "the resume queries never reached the map server"
            time.sleep(0.01)
        for query in held[1:3]:  # the answers to the queries before: of the retired map
            query.reply(query.key_expr, resume_answer(tmp_path, str(query.key_expr).split("/")[1]))
            query.drop()
        answered(service)
        assert "retired" not in service.frontends and poses_of("replayed") == [0]
        assert service.resuming["retired"].ask == 4  # the answers to earlier asks are not its
        assert service.shell.counters.get("scans_awaiting_resume") == 2  # the two 9s
        held[3].drop()
    finally:
        busy.undeclare()
        service.shell.close(flush_s=0.0)


def test_an_operators_pose_while_a_robot_waits_for_its_map_applies_where_it_was_sent(
    tmp_path,
) -> None:
    """A pose sent while the robot's scans wait for the map server's map applies to the scans
    sent after it, not to the oldest waiting; when no map server answers, the scans go and the
    pose waits for the robot's next start, anchored to the first scan after it that went (a
    chaos test saw a pose applied seconds late as it stood: the robot tracked metres off)."""
    service = matcher()
    sent = recording(service)
    release = threading.Event()

    def query(selector: str, timeout_s: float) -> tuple[list[bytes], list[str]]:
        release.wait(10.0)  # the map server answers when the test says
        return ([resume_answer(tmp_path, "r")] if "/r/" in selector else []), []

    service.shell.query = query
    events: list[int | Pose2D] = []
    track, put_at = service._track, service._put_at
    service._track = lambda r, f, m: (events.append(m.seq), track(r, f, m))[-1]
    service._put_at = lambda r, f, p: (events.append(p.pose), put_at(r, f, p))[-1]
    ring = np.column_stack((3 * np.cos(np.linspace(0, 6, 60)), 3 * np.sin(np.linspace(0, 6, 60))))

    def scan(robot: str, seq: int) -> DeskewedScanMessage:
        return DeskewedScanMessage(robot, seq, 0.1 * seq, ring, "odometry", False, 60, 0)

    try:
        told, later = Pose2D(6.0, -1.0, 0.5), Pose2D(-4.0, 2.0, -1.0)
        for robot in ("r", "q"):
            service.handle("scan", scan(robot, 5))
            service.handle("scan", scan(robot, 6))
        service.place("r", told)
        service.place("q", later)
        service.handle("scan", scan("r", 7))
        moved = replace(scan("q", 7), odom_pose=Pose2D(1.0, 2.0, 0.3))
        service.handle("scan", moved)
        service.place("p", told)  # before its first scan, which is then lost
        service.handle("scan", replace(scan("p", 5), odom_pose=Pose2D(0.5, 0.0, 0.0)))
        service.handle("scan", scan("s", 5))
        service.place("s", later)
        service.handle("scan", scan("s", 6))  # no odometry to carry the pose on from it
        assert events == [] and not service.initial_poses  # p's waits in line, before 5
        release.set()
        while service.resuming:  # the four answers, in whatever order they come
            service.handle(*service.shell.inbox.get(10.0))
        assert events == [5, 6, told, 7]
        estimates = {m.seq: m.pose for m in sent if isinstance(m, PoseEstimateMessage)}
        assert sorted(estimates) == [5, 6, 7]
        resumed = Pose2D(0.4, 0.1, 0.2)  # the answer's last pose
        assert estimates[6].relative_to(resumed).translation_norm() < 0.5
        assert estimates[7].relative_to(told).translation_norm() < 0.5
        assert "r" not in service.resuming and service.frontends["r"] is not None
        assert "q" not in service.resuming
        assert service.initial_poses == {"q": Placed(later, moved.stamp_s, moved.odom_pose),
                                         "s": Placed(later, 0.1 * 6, None),
                                         "p": Placed(told, 0.1 * 5, Pose2D(0.5, 0.0, 0.0))}
        assert service.shell.counters.get("scans_awaiting_resume") == 6  # q's 3, s's 2, p's 1
        assert service._install("s", None).initial_pose != later  # stale: not applied
        assert service.shell.counters.get("initial_poses_stale") == 1
        # A stream that restarts while it waits: its odometry may have restarted too, so the
        # pose is taken as it stands, not carried on by the old run's odometry (a review).
        service.handle("scan", scan("z", 5))  # its (empty) answer waits in the inbox
        service.place("z", later)
        service.handle("scan", replace(scan("z", 6), odom_pose=Pose2D(9.0, 0.0, 0.0)))
        service.handle("scan", scan("z", 0))
        assert service.frontends["z"].initial_pose == later
    finally:
        release.set()
        service.shell.close(flush_s=0.0)


def test_a_resume_that_fails_anywhere_leaves_no_robot_waiting_for_nothing(
    tmp_path, monkeypatch, caplog
) -> None:
    """Every way a resume can fail ends the wait, counted and logged (an audit left robots
    waiting for ever): a thread that cannot start fails its scan, the next asks again; a
    query that raises is an answer with its error (the robot starts afresh, saying why); a
    seed that cannot be installed drops the waiting scans, counted; one waiting scan that
    fails is that scan's error alone, the rest are tracked."""
    caplog.set_level(logging.INFO)
    service = matcher()
    sent = recording(service)
    ring = np.column_stack((3 * np.cos(np.linspace(0, 6, 60)), 3 * np.sin(np.linspace(0, 6, 60))))

    def scan(robot: str, seq: int) -> DeskewedScanMessage:
        return DeskewedScanMessage(robot, seq, 0.1 * seq, ring, "odometry", False, 60, 0)

    def handled(robot: str, seq: int) -> None:  # as the shell's worker does
        service.shell._handle(service.handle, "scan", scan(robot, seq))

    def poses_of(robot: str) -> list[int]:
        return [m.seq for m in sent if isinstance(m, PoseEstimateMessage) and m.robot_id == robot]

    try:
        def refuse(_thread: threading.Thread) -> None:
            raise RuntimeError("can't start new thread")

        with monkeypatch.context() as patched:
            patched.setattr(threading.Thread, "start", refuse)
            handled("t", 5)
        assert "t" not in service.resuming and service.shell.counters.get("errors.scan") == 1

        def unreadable(robot_id: str) -> tuple[list[bytes], list[str]]:
            raise ValueError("replies unreadable")

        service._resume_query = unreadable
        handled("t", 6)
        answered(service)
        assert poses_of("t") == [6] and "t" not in service.resuming
        assert "robot t: no map to resume from, starting fresh (the query failed: ValueError: " \
            "replies unreadable)" in caplog.text

        service._resume_query = lambda robot_id: ([resume_answer(tmp_path, robot_id)], [])
        install = service._install

        def broken(robot_id: str, seeded: object) -> None:
            raise RuntimeError("keyframes inconsistent")

        service._install = broken
        for seq in (5, 6):
            handled("u", seq)
        while (item := service.shell.inbox.get(10.0)) is not None:
            service.shell._handle(service.handle, *item)
            break
        assert "u" not in service.resuming and "u" not in service.frontends
        assert service.shell.counters.get("errors.resume") == 1
        assert service.shell.counters.get("scans_awaiting_resume") == 2

        service._install = install
        track = service._track

        def flaky(robot_id: str, frontend: object, message: DeskewedScanMessage) -> None:
            if message.seq == 8:
                raise RuntimeError("one bad scan")
            track(robot_id, frontend, message)

        service._track = flaky
        for seq in (7, 8, 9):
            handled("u", seq)
        answered(service)
        assert poses_of("u") == [7, 9] and "u" not in service.resuming
        assert service.shell.counters.get("errors.scan") == 2
    finally:
        service.shell.close(flush_s=0.0)


def test_scans_still_waiting_for_the_map_server_at_a_stop_are_counted(caplog) -> None:
    service = matcher()
    service._ask_for_resume = lambda robot_id, first: service.resuming.setdefault(
        robot_id, Waiting(1, first))  # a query that never comes back
    ring = np.full((20, 2), 2.0)
    try:
        for seq in (5, 6):
            service.handle("scan", DeskewedScanMessage("r", seq, 0.1 * seq, ring, "odometry",
                                                       False, 20, 0))
        service._count_waiting_at_stop()
        assert service.shell.counters.get("scans_awaiting_resume") == 2
        assert "stopping: 2 scans of 1 robots were still waiting" in caplog.text
    finally:
        service.shell.close(flush_s=0.0)


def test_a_robot_met_mid_stream_waits_for_a_map_server_not_up_yet(tmp_path, caplog) -> None:
    """Matcher and map server restarted together, the matcher first: a front end started afresh
    would replace the map server's map with its own (an audit saw it). The robot's scans are
    dropped, counted, until the map server answers, then it resumes; past resume_timeout_s
    without an answer it starts afresh, saying why."""
    caplog.set_level(logging.INFO)
    service = matcher()
    grid = OccupancyGrid(OccupancyParams())
    grid.insert_scan(np.array([[2.0, 0.0], [2.0, 0.5]]), np.zeros(2))
    npz = write_npz(tmp_path / "map.npz", npz_arrays(grid)).read_bytes()
    answers: list[bytes] = []  # the resume query's answers: none while the map server is down
    service.shell.query = lambda selector, timeout_s: (list(answers), [])
    ring = np.column_stack((3 * np.cos(np.linspace(0, 6, 60)), 3 * np.sin(np.linspace(0, 6, 60))))

    def scan(robot: str, seq: int) -> DeskewedScanMessage:
        return DeskewedScanMessage(robot, seq, 0.1 * seq, ring, "odometry", False, 60, 0)

    try:
        service.handle("scan", scan("r", 5))
        answered(service)
        service.handle("scan", scan("r", 6))
        answered(service)
        assert "r" not in service.frontends and "r" in service.awaiting
        assert service.shell.counters.get("scans_awaiting_resume") == 2
        assert "robot r met mid-stream and no map server answers: waiting up to 30 s" in (
            caplog.text
        )
        path = np.array([[0.0, 0.0, 0.0], [0.4, 0.1, 0.2]])
        answers.append(ResumeMessage("r", grid.revision, npz, np.array([0.1, 0.2]), path).encode())
        service.handle("scan", scan("r", 7))
        answered(service)
        assert service.frontends["r"].initial_pose == Pose2D.from_array(path[-1])
        assert service.shell.counters.get("resumed_robots") == 1 and "r" not in service.awaiting
        answers.clear()
        service.awaiting["q"] = time.monotonic() - 31.0  # waited past resume_timeout_s
        service.handle("scan", scan("q", 9))
        answered(service)
        assert "q" in service.frontends and "q" not in service.awaiting
        assert "robot q: no map to resume from, starting fresh (no map server answered in 30 s)" \
            in caplog.text
    finally:
        service.shell.close(flush_s=0.0)


@pytest.mark.integration
@pytest.mark.slow
def test_a_bad_prior_map_stops_the_matcher_naming_it(launcher, tmp_path):
    missing = tmp_path / "nowhere.npz"
    proc = launcher.start("matcher", SCANFLOW_FRONTEND_PRIOR_MAP=str(missing))
    proc.wait(60.0)
    assert proc.returncode != 0
    assert f"prior_map: no file at {missing}" in launcher.log_text("matcher")


@pytest.mark.integration
@pytest.mark.slow
def test_scans_waiting_in_the_matchers_inbox_at_sigterm_still_get_their_poses(launcher, bus,
                                                                             start):
    """SIGTERM while deskewed scans wait in the matcher's inbox: they were accepted off the
    bus, so each still gets its pose on the bus before the process exits cleanly."""
    start("matcher", SCANFLOW_MATCHER_INBOX_DRAIN_S="120")  # a slow machine: all the same
    poses = bus.record(keys.pose("r"))
    stage = DeskewStage()
    frames = list(simulate(SimConfig(duration_s=30.0, seed=2)))
    payloads = []
    for frame in frames:  # all encoded first: the puts then outrun the matcher by far
        for sample in frame.odometry:
            stage.add_odometry(sample)
        result = stage.process(frame.scan)
        beams = len(frame.scan.ranges_m)
        payloads.append(DeskewedScanMessage(
            "r", frame.scan.seq, result.reference_stamp_s, result.points, result.source_used,
            False, beams, beams - len(result.points), result.no_return_points,
        ).encode())
    for payload in payloads:
        bus.put(keys.deskewed_scan("r"), payload)
    # The stop comes while most of the 300 scans wait (the inbox holds 256, the bus the rest);
    # a stats query here would be a race: a fast machine matches 256 scans in half a second.
    assert launcher.stop("matcher", timeout_s=180.0) == 0
    bus.wait_until(lambda: len(poses) == len(frames), 10.0, "every pose on the bus")
    assert sorted(p.seq for p in poses) == [f.scan.seq for f in frames]
    drained = re.search(r"handled the (\d+) messages left in the inbox",
                        launcher.log_text("matcher"))
    assert drained is not None and int(drained[1]) > 0


def test_a_retired_robot_is_dropped_whole_and_frees_its_place_and_its_match_key() -> None:
    """SCANFLOW_MATCHER_MAX_ROBOTS=1: the retire drops the robot's front end and map, back
    end, recent inserts and match queryable; another robot then takes the place, and the first
    one's scans start it afresh (a new map, one match queryable)."""
    service = MatcherService(
        MatcherSettings(max_robots=1), FrontendSettings(), ZenohSettings(mode="peer", connect=[]),
        LOOP_CLOSURE,
    )
    service.shell.put = lambda key, payload: None
    try:
        feed(service, 1.0)
        with pytest.raises(RobotLimitError, match="robot 'b' refused"):
            service.place("b", Pose2D())
        old = service.frontends["r"]
        expected = {
            "map_revision": old.map.revision,
            "keyframes": len(service.mappers["r"].keyframe_seqs),
            "inserts_kept": service.recent["r"].kept(),
        }
        assert expected["map_revision"] > 0 and expected["inserts_kept"] > 0
        declared = len(service.shell._declared)
        dropped = service.retire("r")
        assert dropped.known and dropped.counts == expected
        for held in (service.frontends, service.mappers, service.recent, service.initial_poses,
                     service.awaiting, service.match_queryables):
            assert "r" not in held
        assert len(service.shell._declared) == declared - 1  # its match queryable is gone
        points = np.array([[1.0, 0.0], [0.0, 1.0], [1.0, 1.0]])
        answer = service.respond(MatchRequest("gn", points, MapRef("r")))
        assert answer.error == "no map for robot 'r' on this matcher"
        service.place("b", Pose2D(1.0, 0.0, 0.0))  # the place is free
        assert not service.retire("nobody").known
        assert service.retire("b").known  # a pose waiting for the first scan is state too
        feed(service, 1.0)
        assert service.frontends["r"] is not old and list(service.match_queryables) == ["r"]
    finally:
        service.shell.close(flush_s=0.0)
