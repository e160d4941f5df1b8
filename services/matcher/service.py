"""Matcher service: one `Frontend` per robot of this shard, fed deskewed scans.

Each deskewed scan carries the odometry pose at its stamp (the deskewer's buffer, as the
in-process pipeline takes it), so the matcher subscribes to nothing else: one stream per robot
in publication order, and no other service's output on its link (a full inbox blocks that
link, and two matchers subscribed to each other's poses could wait on each other).
Per scan it publishes the pose estimate; for each scan the front end put into its map it first
publishes that scan (no-return beams included) with the pose it went in at on `map/insert`, so
the map server inserts exactly the same scans at the same poses. A new robot starts on the
prior map when SCANFLOW_FRONTEND_PRIOR_MAP names one (the map server starts from the same
file). A robot first seen mid-stream (this matcher restarted) resumes from the map server's
one answer on `map/resume` (ResumeMessage): its map and last pose seed the front end. The
query goes out on a thread of its own, so the other robots are tracked meanwhile; the robot's
scans wait for the answer (`waiting.py`) and are then tracked in order. An
operator's pose on `<prefix>/<robot>/initial_pose` (InitialPoseMessage, echoed once taken)
puts the robot there: the next scan to come is matched from it (after the scans waiting for
the map server's map, if any), or, for a robot not seen yet, its first scan. Match requests
are answered on `<prefix>/match` (any scans) and
`<prefix>/<robot>/match` (also against that robot's current map). Each insert names the one
before it (`previous_seq`), and the last `resend_inserts` are kept to send again to a map
server that missed some (`map/resend`); with loop closure, older ones are rebuilt from the
back end's keyframes; without it, or when the back end culled some of them as keyframes, the
matcher sends its whole map and path instead (MapStateMessage).

With SCANFLOW_BACKEND_LOOP_CLOSURE a `Mapper` runs around each robot's front end (keyframes,
loop closures, the pose graph). When it redraws the map, the matcher sends a MapRedrawMessage
on the inserts' key (between the same inserts it made, so the map server redraws at the same
point of the stream), and the scan's pose estimate carries the frame's `correction`, which the
deskewer's motion prior and the gateway's pose cache follow. A robot resumed from the map
server mid-stream gets its back end back from the keyframes in that answer (the closures
found before are in their poses); without them it is tracked without loop closure.

A robot retired (`<prefix>/<robot>/retire/matcher`, every shard answers) loses its front end
and map, back end, recent inserts, waiting operator's pose, the scans waiting for the map
server's map and its `<prefix>/<robot>/match` queryable, on the worker between two scans and
under the lock match requests take; a scan of it that comes later starts it afresh (seq past
0: the map server, which retired it too, has no map to resume it from).
"""

from __future__ import annotations

import copy
import itertools
import threading
import time
from dataclasses import dataclass

import numpy as np
import zenoh
from scanflow import keys
from scanflow.backend import Mapper, MapperStep, SavedRun
from scanflow.config import BackendSettings, FrontendSettings, MatcherSettings, ZenohSettings
from scanflow.frontend import Frontend, FrontendOutput
from scanflow.frontend.prior import FrontendStart
from scanflow.geometry import Pose2D
from scanflow.maps.export import grid_from_npz_bytes
from scanflow.maps.matching_map import MatchingMap
from scanflow.warmup import warm_up
from scanflow.wire import (
    DeskewedScanMessage,
    InitialPoseMessage,
    MapInsertMessage,
    MapRedrawMessage,
    MapRef,
    MatchRequest,
    MatchResponse,
    MessageError,
    PoseEstimateMessage,
    ResumeMessage,
    new_run,
)

from services.common.keyframes import scan_nodes
from services.common.process import init_process, require_settings
from services.common.resend import resend_range
from services.common.retire import Dropped
from services.common.robots import RobotLimitError
from services.common.shell import TIMED_OUT, ServiceShell
from services.matcher.recent import (
    RecentInserts,
    culled_between,
    keyframe_inserts,
    map_state,
)
from services.matcher.requests import answer
from services.matcher.shard import owns
from services.matcher.waiting import Placed, Waiting

# Scan-to-map methods that read the live map under the lock: quick, and bounded by their
# max_iterations. Any other (csm, its exhaustive form, csm+plicp, global: searches) reads a copy.
LOCAL_METHODS = frozenset({"gn", "lm", "ndt", "gn+plicp", "icp", "plicp"})


class MatcherService:
    """Tracks the robots of its shard; answers match requests."""

    def __init__(
        self,
        settings: MatcherSettings,
        frontend_settings: FrontendSettings,
        zenoh_settings: ZenohSettings,
        backend_settings: BackendSettings | None = None,
    ) -> None:
        """`backend_settings` with loop_closure on: a back end per robot (drawing its
        keyframes on the prior map, if any)."""
        self.settings = settings
        self.frontend_settings = frontend_settings
        self.backend = backend_settings if backend_settings is not None else BackendSettings()
        self.start = FrontendStart(frontend_settings)  # a bad prior map stops the start here
        self.shell = ServiceShell("matcher", settings, zenoh_settings)
        self.frontends: dict[str, Frontend] = {}
        self.mappers: dict[str, Mapper] = {}  # robots tracked with loop closure
        # Operators' poses for robots not seen yet (or whose waiting scans were all lost).
        self.initial_poses: dict[str, Placed] = {}
        self.recent: dict[str, RecentInserts] = {}  # per robot: its run's last inserts
        self.awaiting: dict[str, float] = {}  # robots met mid-stream waiting for the map server
        # Robots whose resume query is out: its number, their scans and operators' poses since.
        # The worker adds and removes them; an operator's pose is added under the lock.
        self.resuming: dict[str, Waiting] = {}
        self._asks = itertools.count(1)  # resume queries' numbers: an answer names its own
        self._entering: str | None = None  # a new robot admitted by the scan in hand
        self.match_queryables: dict[str, zenoh.Queryable] = {}  # per robot: `<robot>/match`
        self.lock = threading.Lock()  # the worker updates maps that match requests read
        prefix = self.shell.prefix
        self.shell.subscribe(
            keys.deskewed_scan("*", prefix), "scan", DeskewedScanMessage.decode
        )
        self.shell.serve(keys.scan_match(prefix), self._on_match)
        self.shell.serve(keys.initial_pose("*", prefix), self._on_initial_pose)
        self.shell.serve(keys.map_key("*", "resend", prefix), self._on_resend, side=True)
        self.shell.add_stats(lambda: {"robots": len(self.frontends)})
        self.shell.serve_retire(self.retire)

    def owns(self, robot_id: str) -> bool:
        """Whether this instance tracks `robot_id`: in its `robots` list, else by CRC-32 shard."""
        return owns(robot_id, self.settings.shard, self.settings.robots)

    def handle(self, kind: str, message: DeskewedScanMessage | _ResumeAnswer) -> None:
        """Track a scan of an owned, admitted robot (front end, then back end, under the lock) and
        publish its insert, redraw and pose. A robot met mid-stream (this matcher restarted)
        asks the map server for its map on a thread of its own, so the other robots go on
        meanwhile; its scans wait for the answer (`_on_resume_answer`), in order."""
        if isinstance(message, _ResumeAnswer):
            self._on_resume_answer(message)
            return
        robot_id = message.robot_id
        if not self.owns(robot_id):
            self.shell.counters.add(f"other_shard.{kind}")
            return
        held = _Held(self)
        if robot_id not in held:  # a new robot: its place is taken under the lock, as an
            with self.lock:  # operator's pose for another takes one, and held till it is in
                if not self.shell.admits(robot_id, held):
                    return
                self._entering = robot_id
        try:
            self._scan(kind, message)
        finally:
            self._entering = None

    def _scan(self, kind: str, message: DeskewedScanMessage) -> None:
        """`handle`'s work for a scan of an admitted robot."""
        robot_id = message.robot_id
        stream = f"{robot_id}/{kind}"
        restarted = self.shell.seqs.is_restart(stream, message.seq)
        self.shell.seqs.observe(stream, message.seq)
        waiting = self.resuming.get(robot_id)
        if waiting is not None and not restarted:
            with self.lock:  # operators' poses join it under the lock
                dropped = waiting.hold(message)
            self.shell.counters.add("scans_awaiting_resume", dropped)
            return
        if waiting is not None:  # a new run: the old one's scans cannot be tracked any more
            self._give_up(robot_id, waiting, restarted=True)
            self.awaiting.pop(robot_id, None)  # its wait for a map server starts again too
        frontend = self.frontends.get(robot_id)
        if frontend is None and message.seq > 0:  # met mid-stream: ask for the map server's map
            self._ask_for_resume(robot_id, message)
            return
        if frontend is None or restarted:
            frontend = self._install(robot_id, None)
        self._track(robot_id, frontend, message)

    def _track(self, robot_id: str, frontend: Frontend, message: DeskewedScanMessage) -> None:
        """One scan through the robot's front end and back end, then its messages out."""
        with self.lock:  # a redraw replaces the map that match requests read
            out = frontend.process(
                message.points,
                message.stamp_s,
                message.odom_pose,
                message.seq,
                message.no_return_points,
                message.mount,
            )
            mapper = self.mappers.get(robot_id)
            step: MapperStep | None = None
            redraw: MapRedrawMessage | None = None
            if mapper is not None:
                step = mapper.add(out, message.points, message.no_return_points, message.mount)
                redraw = None if step is None else self._redraw(robot_id, out.seq, mapper, step)
            self.recent[robot_id].tracked(out.seq, out.inserted, redraw)
        keyframe = step is None or step.culled_to is None
        self._publish(robot_id, message, out, keyframe, redraw)

    def _redraw(
        self, robot_id: str, seq: int, mapper: Mapper, step: MapperStep
    ) -> MapRedrawMessage | None:
        """Count what the back end did; the redraw to send, if it redrew the map."""
        self.shell.counters.add("backend.closures", len(step.closures))
        if step.culled_to is not None:
            self.shell.counters.add("backend.culled")
        if step.optimised is not None:
            self.shell.counters.add("backend.optimisations")
        if step.correction is None:
            return None
        self.shell.counters.add("backend.redraws")
        return MapRedrawMessage(
            robot_id, seq, step.correction, np.asarray(mapper.keyframe_seqs, dtype=np.int64),
            mapper.graph.poses, mapper.stamps_s(), mapper.trajectory(), self.recent[robot_id].run,
        )

    def _publish(
        self, robot_id: str, scan: DeskewedScanMessage, out: FrontendOutput, keyframe: bool,
        redraw: MapRedrawMessage | None,
    ) -> None:
        """The insert (the scan at the pose it went in at; `keyframe` false when the back end
        culled it), then the redraw that followed it, then the estimate (in the redrawn map's
        frame, with the correction, after a redraw)."""
        prefix = self.shell.prefix
        if out.inserted:
            recent = self.recent[robot_id]
            insert = MapInsertMessage(
                robot_id, out.seq, out.stamp_s, out.pose, scan.points, scan.no_return_points,
                scan.mount, recent.last_seq, keyframe, recent.run,
            )
            payload = insert.encode()
            recent.add(insert.seq, insert.previous_seq, payload)
            self.shell.put(keys.map_key(robot_id, "insert", prefix), payload)
        correction = None if redraw is None else redraw.correction
        if redraw is not None:
            self._put_redraw(redraw)
            out = out.in_frame(redraw.correction)
        estimate = PoseEstimateMessage.from_result(
            out, robot_id, out.seq, out.stamp_s, correction, scan.odom_pose,
            self.recent[robot_id].run,
        )
        self.shell.put(keys.pose(robot_id, prefix), estimate.encode())
        self.shell.counters.add(f"status.{out.status}")

    def _put_redraw(self, redraw: MapRedrawMessage) -> None:
        """Send the redraw; one too big for the wire (a path of ~16M scans) is logged and
        counted, and the map server then keeps its map unredrawn."""
        try:
            payload = redraw.encode()
        except MessageError as exc:
            self.shell.counters.add("backend.redraws_unsent")
            self.shell.log.error("robot %s: redraw not sent: %s", redraw.robot_id, exc)
            return
        self.shell.put(keys.map_key(redraw.robot_id, "insert", self.shell.prefix), payload)

    # -- robots ---------------------------------------------------------------------------
    def _install(self, robot_id: str, seeded: tuple[Frontend, ResumeMessage] | None) -> Frontend:
        """The robot's new front end (and back end): `seeded` from the map server's map, or
        afresh (on first sight, when the stream restarts, or when the map server had no map
        to resume it from). An operator's pose sent before it existed is applied as it is stored
        (one lock: a pose arriving meanwhile finds it)."""
        mapper = None
        if seeded is None:
            new = Frontend(self.frontend_settings, self.start.pose, self.start.grid())
            if self.backend.loop_closure:
                mapper = Mapper(new, self.backend, prior=self.start.grid())
        else:
            new, resumed = seeded
            if self.backend.loop_closure:
                mapper = self._resumed_back_end(robot_id, new, resumed)
        if robot_id not in self.match_queryables:
            self.match_queryables[robot_id] = self.shell.serve(
                keys.robot_match(robot_id, self.shell.prefix), self._on_match
            )
        with self.lock:
            self.frontends[robot_id] = new
            self.awaiting.pop(robot_id, None)
            self.recent[robot_id] = RecentInserts(
                self.settings.resend_inserts, _run_token(seeded), bool(seeded)
            )
            if mapper is None:
                self.mappers.pop(robot_id, None)
            else:
                self.mappers[robot_id] = mapper
            told = self.initial_poses.pop(robot_id, None)
            if told is not None:
                self._put_at(robot_id, new, told)
        return new

    def _put_at(self, robot_id: str, frontend: Frontend, placed: Placed) -> None:
        """(Under the lock.) The robot's next scan is matched from an operator's pose, moved
        by the odometry since the scan it was anchored to (lost while waiting for the map
        server); its back end, if any, links across it only weakly. One anchored to a scan
        without odometry cannot be carried on: not applied, logged, counted."""
        if placed.anchored and placed.odom_pose is None:
            self.shell.counters.add("initial_poses_stale")
            self.shell.log.warning(
                "robot %s: the operator's pose %s came before scans lost while waiting for the "
                "map server, and no odometry carries it on to the next: not applied (send it "
                "again)", robot_id, placed.pose,
            )
            return
        frontend.set_pose(placed.pose, placed.stamp_s, placed.odom_pose)
        mapper = self.mappers.get(robot_id)
        if mapper is not None:
            mapper.relocated()

    def _resumed_back_end(
        self, robot_id: str, frontend: Frontend, resumed: ResumeMessage
    ) -> Mapper | None:
        """The back end carried on from the map server's keyframes of `robot_id`; None (the
        robot is tracked without loop closure, counted) when it has none to give."""
        kept = resumed.keyframes
        if kept is None or len(kept.seqs) == 0:
            self.shell.counters.add("backend.resumed_without")
            self.shell.log.warning(
                "robot %s: the map server %s; tracked without loop closure", robot_id,
                "keeps no keyframes of it (SCANFLOW_BACKEND_LOOP_CLOSURE is off there, or its "
                "map was resumed from a snapshot without them)"
                if kept is None else "has no keyframes to resume it from",
            )
            return None
        saved = SavedRun(scan_nodes(kept), kept.seqs.tolist(), kept.poses, resumed.stamps_s,
                         resumed.poses)
        self.shell.counters.add("backend.resumed")
        self.shell.log.info("robot %s: loop closure resumed on %d keyframes", robot_id,
                            len(kept.seqs))
        return Mapper(frontend, self.backend, saved, self.start.grid())

    def _ask_for_resume(self, robot_id: str, first: DeskewedScanMessage) -> None:
        """Ask the map server for the robot's map on a thread of its own (the answer comes
        back through the inbox); `first` and the robot's later scans wait for it."""
        ask = next(self._asks)
        threading.Thread(
            target=self._resume_in_inbox, args=(robot_id, ask), name=f"resume-{robot_id}",
            daemon=True,
        ).start()  # a thread that cannot start: the scan fails (counted), the next asks again
        with self.lock:  # the answer comes on this thread; a pose sent before waits in line
            told = self.initial_poses.pop(robot_id, None)
            self.resuming[robot_id] = Waiting(ask, first, placed=told)

    def _resume_in_inbox(self, robot_id: str, ask: int) -> None:
        """(Its own thread.) The map server's answer to query `ask` for `robot_id`, into the
        worker's inbox: always one, so the robot's scans never wait for nothing."""
        try:
            payloads, errors = self._resume_query(robot_id)
        except Exception as exc:  # no side session, a refused query, unreadable replies
            payloads, errors = [], [f"the query failed: {type(exc).__name__}: {exc}"]
        self.shell.inbox.put("resume", _ResumeAnswer(robot_id, ask, payloads, errors))

    def _resume_query(self, robot_id: str) -> tuple[list[bytes], list[str]]:
        """The map server's answers to the resume query for `robot_id` (up to
        resume_timeout_s) and its errors (a query that cannot be asked raises:
        `_resume_in_inbox` makes that an error too)."""
        selector = keys.map_key(robot_id, "resume", self.shell.prefix)
        return self.shell.query(selector, self.settings.resume_timeout_s)

    def _on_resume_answer(self, answer: _ResumeAnswer) -> None:
        """The map server answered (or not) for a robot met mid-stream: its front end starts
        from the answer and its scans that waited are tracked, in order, each operator's pose
        sent meanwhile applied where it came among them. While no map server answers at all,
        they are dropped (counted) and the robot's next scan asks again."""
        robot_id = answer.robot_id
        waiting = self.resuming.get(robot_id)
        if waiting is None or waiting.ask != answer.ask:  # retired or restarted meanwhile
            return
        try:
            frontend = self._install(
                robot_id, self._seeded(robot_id, answer.payloads, answer.errors)
            )
        except _NoMapServerYetError:
            self._give_up(robot_id, waiting)
            return
        except Exception:  # counted as the answer's error; the next scan asks again
            self._give_up(robot_id, waiting)
            raise
        try:
            while (scan := self._next_waiting(robot_id, waiting, frontend)) is not None:
                try:
                    self._track(robot_id, frontend, scan)
                except Exception:  # one scan, as if it came alone: the others still go on
                    self.shell.failed("scan")
        finally:  # (the wait ends whatever failed: the robot's later scans are tracked)
            if self.resuming.get(robot_id) is waiting:
                self._give_up(robot_id, waiting)

    def _next_waiting(
        self, robot_id: str, waiting: Waiting, frontend: Frontend
    ) -> DeskewedScanMessage | None:
        """The robot's next scan that waited for the map server, the operators' poses sent
        before it applied; None, the wait over, when none is left (one lock: a pose sent
        meanwhile joins the wait, or finds it over and applies to the next scan)."""
        with self.lock:
            while (item := waiting.next()) is not None:
                if isinstance(item, DeskewedScanMessage):
                    return item
                self._put_at(robot_id, frontend, item)
            del self.resuming[robot_id]
        return None

    def _give_up(self, robot_id: str, waiting: Waiting, restarted: bool = False) -> None:
        """Drop the robot's wait for the map server: its scans go (counted); the last
        operator's pose in it waits for the robot's next start, anchored to the first scan
        after it that went (the odometry carries it on from there), unless the stream
        `restarted` (its odometry may have restarted too: the pose is taken as it stands)."""
        with self.lock:
            del self.resuming[robot_id]
            told = waiting.last_placed()
            if told is not None:
                self.initial_poses[robot_id] = Placed(told.pose) if restarted else told
        self.shell.counters.add("scans_awaiting_resume", waiting.scans)

    def _seeded(
        self, robot_id: str, payloads: list[bytes], errors: list[str]
    ) -> tuple[Frontend, ResumeMessage] | None:
        """A front end continuing the map server's map and last pose of `robot_id`, and all
        it answered (the path, the keyframes), from its answer to the resume query (`payloads`,
        `errors`), if it knows the robot. While no map server answers at all (it is restarting
        too, or too busy to answer in time), _NoMapServerYetError, for up to resume_timeout_s:
        a front end started afresh meanwhile would replace the map server's map with its own
        (the robot's scans meanwhile are dropped, counted)."""
        # A map server there but too slow to answer (busy, its reply held up) has not answered
        # yet either: a front end started afresh would replace its map all the same.
        errors = [e for e in errors if e != TIMED_OUT]
        if not payloads and not errors:
            now = time.monotonic()
            since = self.awaiting.setdefault(robot_id, now)
            if now - since < self.settings.resume_timeout_s:
                if since == now:
                    self.shell.log.info(
                        "robot %s met mid-stream and no map server answers: waiting up to %.0f s "
                        "for its map (its scans are dropped meanwhile)", robot_id,
                        self.settings.resume_timeout_s,
                    )
                raise _NoMapServerYetError(robot_id)
            errors.append(f"no map server answered in {self.settings.resume_timeout_s:.0f} s")
        self.awaiting.pop(robot_id, None)
        resumed = grid = None
        try:
            resumed = ResumeMessage.decode(payloads[0]) if payloads else None
            if resumed is not None and len(resumed.poses):
                grid = grid_from_npz_bytes(resumed.map_npz, f"the map server's map of {robot_id}")
        except ValueError as exc:  # another schema version, a broken map: say so, start afresh
            errors.append(f"its answer is unreadable: {exc}")
        if resumed is None or grid is None:
            self.shell.log.info("robot %s: no map to resume from, starting fresh%s", robot_id,
                                f" ({'; '.join(errors)})" if errors else "")
            return None
        pose = Pose2D.from_array(resumed.poses[-1])
        self.shell.counters.add("resumed_robots")
        self.shell.log.info(
            "robot %s: resumed from the map server (revision %d, %d poses, last %s)",
            robot_id, resumed.revision, len(resumed.poses), pose,
        )
        frontend = Frontend(self.frontend_settings, initial_pose=pose, grid=grid)
        if resumed.odom_pose is not None:  # the odometry bridges the time this matcher was out
            frontend.carry_on(float(resumed.stamps_s[-1]), pose, resumed.odom_pose)
        return frontend, resumed

    def _on_resend(self, query: zenoh.Query) -> None:
        """Send an owned robot's inserts again (the map server missed them): the recent ones,
        or with loop closure the back end's keyframes, or else the whole map and path (one
        MapStateMessage); other shards' robots are left to their matcher."""
        robot_id = keys.robot_of(str(query.key_expr), self.shell.prefix)
        if not self.owns(robot_id):
            return
        after, through = resend_range(query.parameters)
        recent = self.recent.get(robot_id)
        if recent is None:
            raise LookupError(f"robot {robot_id}: this matcher has sent no inserts of it")
        try:
            payloads = recent.between(after, through)
        except LookupError as not_recent:
            payloads = self._older(robot_id, recent, after, through, not_recent)
        else:
            self._resent(robot_id, after, through, len(payloads))
        key = keys.map_key(robot_id, "resend", self.shell.prefix)
        for payload in payloads:
            query.reply(key, payload)

    def _resent(self, robot_id: str, after: int, through: int, count: int) -> None:
        self.shell.counters.add("inserts_resent", count)
        self.shell.log.info("robot %s: sent inserts %d..%d again (%d)", robot_id, after + 1,
                            through, count)

    def _older(
        self, robot_id: str, recent: RecentInserts, after: int, through: int,
        not_recent: LookupError,
    ) -> list[bytes]:
        """What stands in for inserts no longer kept: the back end's keyframes when they are
        all of them, else the whole map."""
        with self.lock:  # the worker inserts, adds keyframes and redraws
            if self.recent.get(robot_id) is not recent:  # map, back end and run: one run's
                raise LookupError(f"robot {robot_id}: its tracker started another run meanwhile")
            mapper = self.mappers.get(robot_id)
            try:
                culled = 0 if mapper is None else culled_between(mapper, after, through)
            except LookupError as exc:
                raise LookupError(f"{not_recent}; {exc}") from None
            frontend = self.frontends.get(robot_id)
            if frontend is None:  # retired meanwhile
                raise LookupError(f"robot {robot_id}: this matcher tracks it no more")
            if mapper is not None and not culled:
                inserts, _ = keyframe_inserts(mapper, robot_id, recent.run, after, through)
            else:
                state = map_state(robot_id, frontend, recent, mapper)
        if mapper is not None and not culled:
            self._resent(robot_id, after, through, len(inserts))
            return [insert.encode() for insert in inserts]
        self.shell.counters.add("map_states_sent")
        self.shell.log.warning(
            "robot %s: inserts %d..%d are no longer kept (%s); sent the whole map instead "
            "(every insert through seq %d)", robot_id, after + 1, through,
            f"{culled} of them were culled as keyframes" if culled else not_recent,
            state.insert_seq,
        )
        return [state.encode()]

    def _on_initial_pose(self, query: zenoh.Query) -> None:
        """Put an owned robot at the operator's pose (kept for its first scan if not seen yet);
        other shards' robots are left to their matcher, which answers instead."""
        payload = query.payload
        if payload is None:
            raise ValueError("an initial pose query needs an InitialPoseMessage payload")
        message = InitialPoseMessage.decode(payload.to_bytes())
        robot_id = keys.check_robot_id(message.robot_id)
        key = keys.initial_pose(robot_id, self.shell.prefix)
        if str(query.key_expr) != key:
            raise ValueError(f"initial pose for {robot_id!r} must be sent on {key}")
        if not self.owns(robot_id):
            return
        self.place(robot_id, message.pose)
        self.shell.log.info("robot %s: placed at %s by request", robot_id, message.pose)
        query.reply(key, message.encode())

    def place(self, robot_id: str, pose: Pose2D) -> None:
        """Put the robot at an operator's `pose`: its next scan is matched from it, a robot
        waiting for the map server's map included. For a robot not seen yet the pose is kept
        for its first scan, taking one of the max_robots places (RobotLimitError when none
        is left)."""
        with self.lock:
            frontend = self.frontends.get(robot_id)
            waiting = self.resuming.get(robot_id)
            if waiting is not None:  # its waiting scans come first
                waiting.place(pose)
            elif frontend is None:
                if not self.shell.admits(robot_id, _Held(self)):
                    raise RobotLimitError(
                        f"robot {robot_id!r} refused: this matcher keeps "
                        f"{self.settings.max_robots} robots already (SCANFLOW_MATCHER_MAX_ROBOTS)"
                    )
                self.initial_poses[robot_id] = Placed(pose)
            else:
                self._put_at(robot_id, frontend, Placed(pose))
        self.shell.counters.add("initial_poses")

    def retire(self, robot_id: str) -> Dropped:
        """Let go of the robot (on the worker, between two scans; under the lock that match
        requests, resends and operators' poses take): its front end and map, back end, recent
        inserts, a waiting operator's pose, its wait for the map server, and its match
        queryable. What it held is counted (`map_revision`, `keyframes`, `inserts_kept`)."""
        with self.lock:
            frontend = self.frontends.pop(robot_id, None)
            mapper = self.mappers.pop(robot_id, None)
            recent = self.recent.pop(robot_id, None)
            told = self.initial_poses.pop(robot_id, None)
            waited = self.awaiting.pop(robot_id, None)
            waiting = self.resuming.pop(robot_id, None)  # its answer, when it comes, is dropped
        if waiting is not None:
            self.shell.counters.add("scans_awaiting_resume", waiting.scans)
        queryable = self.match_queryables.pop(robot_id, None)
        if queryable is not None:
            self.shell.undeclare(queryable)
        counts = {}
        if frontend is not None:
            counts["map_revision"] = frontend.map.revision
        if mapper is not None:
            counts["keyframes"] = len(mapper.keyframe_seqs)
        if recent is not None:
            counts["inserts_kept"] = recent.kept()
        held = (frontend, told, waited, waiting, queryable)
        return Dropped(any(x is not None for x in held), counts)

    # -- match requests -------------------------------------------------------------------
    def _map_of(self, robot_id: str) -> MatchingMap | None:
        frontend = self.frontends.get(robot_id)
        return None if frontend is None else frontend.map

    def _on_match(self, query: zenoh.Query) -> None:
        payload = query.payload
        if payload is None:
            raise ValueError("a match query needs a MatchRequest payload")
        response = self.respond(MatchRequest.decode(payload.to_bytes()))
        self.shell.counters.add("match_requests")
        query.reply(query.key_expr, response.encode())

    def respond(self, request: MatchRequest) -> MatchResponse:
        """The answer to a match request. A search against a robot's map (csm, its exhaustive
        form, csm+plicp, global: seconds on a wide window) runs on a copy of the map (2 ms to
        take), so no robot's tracking waits for it; the quick methods read the live map under
        the lock; scan-to-scan needs no robot's state."""
        if isinstance(request.target, MapRef) and request.method not in LOCAL_METHODS:
            with self.lock:
                live = self._map_of(request.target.robot_id)
                snapshot = None if live is None else MatchingMap(copy.deepcopy(live.grid))
            return answer(request, lambda _robot_id: snapshot)
        if isinstance(request.target, MapRef):
            with self.lock:
                return answer(request, self._map_of)
        return answer(request, self._map_of)

    def run(self) -> None:
        """Warm up (if set, the match methods too), serve until stopped, then close."""
        with self.shell:
            if self.settings.warm_up:  # before the health token: the first scan at full speed
                warm_up(methods=True)
            self.shell.start()
            # A stop's drain waits for resume answers on their way (up to inbox_drain_s).
            self.shell.run(self.handle, pending=lambda: bool(self.resuming))
            self._count_waiting_at_stop()

    def _count_waiting_at_stop(self) -> None:
        """Scans still waiting for a map server's answer when the service stops are lost, as
        scans left in the inbox are: counted (`scans_awaiting_resume`) and logged."""
        waiting = sum(w.scans for w in self.resuming.values())
        if waiting:
            self.shell.counters.add("scans_awaiting_resume", waiting)
            self.shell.log.warning(
                "stopping: %d scans of %d robots were still waiting for the map server's map",
                waiting, len(self.resuming),
            )


def _run_token(seeded: tuple[Frontend, ResumeMessage] | None) -> int:
    """The token of a robot's run as its front end starts: the map server's for a resumed
    run, else (a first scan, a replay, a resume the map server could not give: the front
    end starts a map of its own, in its own frame) a new one. The map server keeps the map
    of a run it replaces beside the new one's (`<robot>.snapshot.npz.previous`)."""
    return (seeded[1].run if seeded is not None else 0) or new_run()


@dataclass(frozen=True)
class _ResumeAnswer:
    """The map server's answers to resume query number `ask`, and its errors: an inbox item."""

    robot_id: str
    ask: int
    payloads: list[bytes]
    errors: list[str]


class _NoMapServerYetError(Exception):
    """A robot met mid-stream waits for the map server's map: no map server answers yet."""


class _Held:
    """The robots a matcher holds a place for: those it tracks, those whose operator's pose
    waits for their first scan, those waiting for the map server's map or asking for it, and
    the one its scan in hand admitted (a robot can be in several at once: counted once)."""

    def __init__(self, service: MatcherService) -> None:
        self._service = service

    def __contains__(self, robot_id: object) -> bool:
        s = self._service
        return robot_id in s.frontends or robot_id in s.initial_poses or robot_id in s.awaiting \
            or robot_id in s.resuming or robot_id == s._entering

    def __len__(self) -> int:
        s = self._service
        entering = set() if s._entering is None else {s._entering}
        return len(set(s.frontends) | set(s.initial_poses) | set(s.awaiting) | set(s.resuming)
                   | entering)


def main() -> None:
    """Run a matcher (settings: SCANFLOW_MATCHER_*, SCANFLOW_FRONTEND_*, SCANFLOW_BACKEND_*,
    SCANFLOW_ZENOH_*)."""
    require_settings(
        "matcher", MatcherSettings, FrontendSettings, ZenohSettings, BackendSettings
    )
    settings = MatcherSettings()
    init_process(settings)
    try:  # a bad prior map: stop at start, naming it
        service = MatcherService(settings, FrontendSettings(), ZenohSettings(), BackendSettings())
    except ValueError as exc:
        raise SystemExit(f"matcher: {exc}") from exc
    service.run()
