"""Matcher service: one `Frontend` per robot of this shard, fed deskewed scans.

Each deskewed scan carries the odometry pose at its stamp (the deskewer's buffer, as the
in-process pipeline takes it), so the matcher subscribes to nothing else: one stream per robot
in publication order, and no other service's output on its link (a full inbox blocks that
link, and two matchers subscribed to each other's poses could wait on each other).
Per scan it publishes the pose estimate; for each scan the front end put into its map it first
publishes that scan (no-return beams included) with the pose it went in at on `map/insert`, so
the map server inserts exactly the same scans at the same poses. A new robot starts on the
prior map when SCANFLOW_FRONTEND_PRIOR_MAP names one (the map server starts from the same
file). A robot first seen mid-stream (this matcher restarted) resumes from the map server: its
map snapshot and last pose seed the front end. An operator's pose on `<prefix>/<robot>/
initial_pose` (InitialPoseMessage, echoed once taken) puts the robot there: its next scan is
matched from it, or, for a robot not seen yet, its first scan. Match requests are answered
on `<prefix>/match` (any scans) and `<prefix>/<robot>/match` (also against that robot's
current map).
"""

from __future__ import annotations

import copy
import io
import threading

import numpy as np
import zenoh
from scanflow import keys
from scanflow.config import BackendSettings, FrontendSettings, MatcherSettings, ZenohSettings
from scanflow.frontend import Frontend, FrontendOutput
from scanflow.frontend.prior import FrontendStart
from scanflow.geometry import Pose2D
from scanflow.maps.export import grid_from_npz
from scanflow.maps.matching_map import MatchingMap
from scanflow.matching.global_search import GLOBAL_METHOD
from scanflow.warmup import warm_up
from scanflow.wire import (
    DeskewedScanMessage,
    InitialPoseMessage,
    MapImageMessage,
    MapInsertMessage,
    MapRef,
    MatchRequest,
    PoseEstimateMessage,
    TrajectoryMessage,
    decode_any,
)

from services.common.process import init_process
from services.common.shell import ServiceShell
from services.matcher.requests import answer
from services.matcher.shard import owns

SEED_TIMEOUT_S = 5.0


class MatcherService:
    """Tracks the robots of its shard; answers match requests."""

    def __init__(
        self,
        settings: MatcherSettings,
        frontend_settings: FrontendSettings,
        zenoh_settings: ZenohSettings,
    ) -> None:
        self.settings = settings
        self.frontend_settings = frontend_settings
        self.start = FrontendStart(frontend_settings)  # a bad prior map stops the start here
        self.shell = ServiceShell("matcher", settings, zenoh_settings)
        self.frontends: dict[str, Frontend] = {}
        self.initial_poses: dict[str, Pose2D] = {}  # operators' poses for robots not seen yet
        self.lock = threading.Lock()  # the worker updates maps that match requests read
        prefix = self.shell.prefix
        self.shell.subscribe(
            keys.deskewed_scan("*", prefix), "scan", DeskewedScanMessage.decode
        )
        self.shell.serve(keys.scan_match(prefix), self._on_match)
        self.shell.serve(keys.initial_pose("*", prefix), self._on_initial_pose)
        self.shell.add_stats(lambda: {"robots": len(self.frontends)})

    def owns(self, robot_id: str) -> bool:
        return owns(robot_id, self.settings.shard, self.settings.robots)

    def handle(self, kind: str, message: DeskewedScanMessage) -> None:
        robot_id = message.robot_id
        if not self.owns(robot_id):
            self.shell.counters.add(f"other_shard.{kind}")
            return
        stream = f"{robot_id}/{kind}"
        restarted = self.shell.seqs.is_restart(stream, message.seq)
        self.shell.seqs.observe(stream, message.seq)
        frontend = self._frontend(robot_id, message.seq, fresh=restarted)
        with self.lock:
            out = frontend.process(
                message.points,
                message.stamp_s,
                message.odom_pose,
                message.seq,
                message.no_return_points,
                message.mount,
            )
        self._publish(robot_id, message, out)

    def _publish(self, robot_id: str, scan: DeskewedScanMessage, out: FrontendOutput) -> None:
        prefix = self.shell.prefix
        if out.inserted:
            insert = MapInsertMessage(
                robot_id, out.seq, out.stamp_s, out.pose, scan.points, scan.no_return_points,
                scan.mount,
            )
            self.shell.put(keys.map_key(robot_id, "insert", prefix), insert.encode())
        estimate = PoseEstimateMessage.from_result(out, robot_id, out.seq, out.stamp_s)
        self.shell.put(keys.pose(robot_id, prefix), estimate.encode())
        self.shell.counters.add(f"status.{out.status}")

    # -- robots ---------------------------------------------------------------------------
    def _frontend(self, robot_id: str, seq: int, fresh: bool = False) -> Frontend:
        """The robot's front end; created on first sight (seeded from the map server when the
        stream is already under way), replaced by a fresh one when the stream restarts. An
        operator's pose sent before it existed is applied as it is stored (one lock: a pose
        arriving meanwhile finds it)."""
        frontend = self.frontends.get(robot_id)
        if frontend is not None and not fresh:
            return frontend
        new = self._seeded(robot_id) if frontend is None and seq > 0 else None
        if new is None:
            new = Frontend(self.frontend_settings, self.start.pose, self.start.grid())
        if frontend is None:
            self.shell.serve(keys.robot_match(robot_id, self.shell.prefix), self._on_match)
        with self.lock:
            self.frontends[robot_id] = new
            told = self.initial_poses.pop(robot_id, None)
            if told is not None:
                new.set_pose(told)
        return new

    def _seeded(self, robot_id: str) -> Frontend | None:
        """A front end continuing the map server's map and last pose of `robot_id`, if any."""
        prefix = self.shell.prefix
        image = self._query(f"{keys.map_key(robot_id, 'image', prefix)}?format=npz")
        path = self._query(keys.trajectory(robot_id, prefix))
        if not isinstance(image, MapImageMessage) or not isinstance(path, TrajectoryMessage):
            self.shell.log.info("robot %s: no map to resume from, starting fresh", robot_id)
            return None
        if len(path.poses) == 0:
            return None
        with np.load(io.BytesIO(image.data), allow_pickle=False) as data:
            grid = grid_from_npz(data, f"the map server's map of {robot_id}")
        pose = Pose2D.from_array(path.poses[-1])
        self.shell.counters.add("resumed_robots")
        self.shell.log.info(
            "robot %s: resumed from the map server (revision %d, %d poses, last %s)",
            robot_id, image.revision, len(path.poses), pose,
        )
        return Frontend(self.frontend_settings, initial_pose=pose, grid=grid)

    def _query(self, selector: str) -> object | None:
        for reply in self.shell.session.get(selector, timeout=SEED_TIMEOUT_S):
            if reply.ok is not None:
                return decode_any(reply.ok.payload.to_bytes())
        return None

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
        with self.lock:
            frontend = self.frontends.get(robot_id)
            if frontend is None:
                self.initial_poses[robot_id] = message.pose
            else:
                frontend.set_pose(message.pose)
        self.shell.counters.add("initial_poses")
        self.shell.log.info("robot %s: placed at %s by request", robot_id, message.pose)
        query.reply(key, message.encode())

    # -- match requests -------------------------------------------------------------------
    def _map_of(self, robot_id: str) -> MatchingMap | None:
        frontend = self.frontends.get(robot_id)
        return None if frontend is None else frontend.map

    def _on_match(self, query: zenoh.Query) -> None:
        payload = query.payload
        if payload is None:
            raise ValueError("a match query needs a MatchRequest payload")
        request = MatchRequest.decode(payload.to_bytes())
        if request.method == GLOBAL_METHOD and isinstance(request.target, MapRef):
            # A whole-map search takes seconds: it runs on a copy of the map (2 ms to take),
            # so the robot's tracking goes on meanwhile instead of waiting for the lock.
            with self.lock:
                live = self._map_of(request.target.robot_id)
                snapshot = None if live is None else MatchingMap(copy.deepcopy(live.grid))
            response = answer(request, lambda _robot_id: snapshot)
        else:
            with self.lock:
                response = answer(request, self._map_of)
        self.shell.counters.add("match_requests")
        query.reply(query.key_expr, response.encode())

    def run(self) -> None:
        if self.settings.warm_up:  # before the health token: the first scan at full speed
            warm_up(methods=True)
        self.shell.start()
        self.shell.run(self.handle)
        self.shell.close()


def main() -> None:
    """Run a matcher (settings: SCANFLOW_MATCHER_*, SCANFLOW_FRONTEND_*, SCANFLOW_ZENOH_*)."""
    settings = MatcherSettings()
    init_process(settings)
    refusal = BackendSettings().refusal_for_services()
    if refusal:
        raise SystemExit(refusal)
    MatcherService(settings, FrontendSettings(), ZenohSettings()).run()
