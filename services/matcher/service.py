"""Matcher service: one `Frontend` per robot of this shard, fed deskewed scans and odometry.

Per scan it publishes the pose estimate; for each scan the front end put into its map it first
publishes that scan (no-return beams included) on `map/insert`, so the map server inserts
exactly the same scans. A robot first seen mid-stream (this matcher restarted) resumes from
the map server: its map snapshot and last pose seed the front end. Match requests are answered
on `<prefix>/match` (any scans) and `<prefix>/<robot>/match` (also against that robot's
current map).
"""

from __future__ import annotations

import tempfile
import threading
from collections import deque
from pathlib import Path

import zenoh
from scanflow import keys
from scanflow.config import FrontendSettings, MatcherSettings, ZenohSettings
from scanflow.frontend import Frontend, FrontendOutput
from scanflow.geometry import Pose2D
from scanflow.maps.export import load_npz
from scanflow.maps.matching_map import MatchingMap
from scanflow.pipeline import DeskewStage
from scanflow.scan import Odometry
from scanflow.wire import (
    DeskewedScanMessage,
    MapImageMessage,
    MatchRequest,
    OdometryMessage,
    PoseEstimateMessage,
    TrajectoryMessage,
    decode_any,
)

from services.common.logs import configure_logging
from services.common.shell import ServiceShell
from services.matcher.requests import answer
from services.matcher.shard import owns

SEED_TIMEOUT_S = 5.0
MAX_PENDING_ODOMETRY = 4096  # odometry samples held ahead of the scans


class Track:
    """One robot: its front end and its odometry (kept by the pipeline's deskew stage).

    Odometry may run far ahead of the deskewed scans (it skips the deskew hop), further than
    the stage's buffer window: samples wait in `pending` and enter the stage only up to the
    stamp of the scan being tracked (plus the next one, to bracket it), as in-process.
    """

    def __init__(self, frontend: Frontend, stage: DeskewStage | None = None) -> None:
        self.frontend = frontend
        self.stage = stage or DeskewStage()
        self.pending: deque[Odometry] = deque()

    def add_odometry(self, odom: Odometry) -> None:
        self.pending.append(odom)
        while len(self.pending) > MAX_PENDING_ODOMETRY:
            self.stage.add_odometry(self.pending.popleft())

    def odom_pose(self, stamp_s: float) -> Pose2D | None:
        """The odometry pose at `stamp_s` exactly as the in-process pipeline takes it."""
        while self.pending:
            odom = self.pending.popleft()
            self.stage.add_odometry(odom)
            if odom.stamp_s > stamp_s:
                break
        return self.stage.odometry_pose_at(stamp_s)


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
        self.shell = ServiceShell("matcher", settings.instance, zenoh_settings, settings.queue_size)
        self.tracks: dict[str, Track] = {}
        self.lock = threading.Lock()  # the worker updates maps that match requests read
        prefix = self.shell.prefix
        routes = [
            (keys.deskewed_scan("*", prefix), "scan", DeskewedScanMessage.decode),
            (keys.odom("*", prefix), "odom", OdometryMessage.decode),
        ]
        self.shell.subscribe_routes(keys.robot_streams("*", prefix), routes)
        self.shell.serve(keys.scan_match(prefix), self._on_match)
        self.shell.add_stats(lambda: {"robots": len(self.tracks)})

    def owns(self, robot_id: str) -> bool:
        return owns(robot_id, self.settings.shard, self.settings.robots)

    def handle(self, kind: str, message: DeskewedScanMessage | OdometryMessage) -> None:
        robot_id = message.robot_id
        if not self.owns(robot_id):
            self.shell.counters.add(f"other_shard.{kind}")
            return
        stream = f"{robot_id}/{kind}"
        restarted = self.shell.seqs.is_restart(stream, message.seq)
        self.shell.seqs.observe(stream, message.seq)
        if isinstance(message, OdometryMessage):
            track = self._track(robot_id, message.seq)
            if restarted:
                track.stage = DeskewStage()
                track.pending.clear()
            track.add_odometry(message.odom)
            return
        track = self._track(robot_id, message.seq, fresh=restarted)
        with self.lock:
            out = track.frontend.process(
                message.points,
                message.stamp_s,
                track.odom_pose(message.stamp_s),
                message.seq,
                message.no_return_points,
            )
        self._publish(robot_id, message, out)

    def _publish(self, robot_id: str, scan: DeskewedScanMessage, out: FrontendOutput) -> None:
        prefix = self.shell.prefix
        if out.inserted:
            self.shell.put(keys.map_key(robot_id, "insert", prefix), scan.encode())
        estimate = PoseEstimateMessage.from_result(out, robot_id, out.seq, out.stamp_s)
        self.shell.put(keys.pose(robot_id, prefix), estimate.encode())
        self.shell.counters.add(f"status.{out.status}")

    # -- robots ---------------------------------------------------------------------------
    def _track(self, robot_id: str, seq: int, fresh: bool = False) -> Track:
        """The robot's track; created on first sight (seeded from the map server when the
        stream is already under way), replaced by a fresh one when the stream restarts."""
        track = self.tracks.get(robot_id)
        if track is not None and not fresh:
            return track
        frontend = self._seeded(robot_id) if track is None and seq > 0 else None
        if frontend is None:
            frontend = Frontend(self.frontend_settings)
        new = Track(frontend, None if track is None else track.stage)
        if track is None:
            self.shell.serve(keys.robot_match(robot_id, self.shell.prefix), self._on_match)
        with self.lock:
            self.tracks[robot_id] = new
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
        with tempfile.TemporaryDirectory(prefix="scanflow-seed-") as tmp:
            path_npz = Path(tmp) / "map.npz"
            path_npz.write_bytes(image.data)
            grid = load_npz(path_npz)
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

    # -- match requests -------------------------------------------------------------------
    def _map_of(self, robot_id: str) -> MatchingMap | None:
        track = self.tracks.get(robot_id)
        return None if track is None else track.frontend.map

    def _on_match(self, query: zenoh.Query) -> None:
        payload = query.payload
        if payload is None:
            raise ValueError("a match query needs a MatchRequest payload")
        request = MatchRequest.decode(payload.to_bytes())
        with self.lock:
            response = answer(request, self._map_of)
        self.shell.counters.add("match_requests")
        query.reply(query.key_expr, response.encode())

    def run(self) -> None:
        self.shell.start()
        self.shell.run(self.handle)
        self.shell.close()


def main() -> None:
    """Run a matcher (settings: SCANFLOW_MATCHER_*, SCANFLOW_FRONTEND_*, SCANFLOW_ZENOH_*)."""
    settings = MatcherSettings()
    configure_logging(settings.log_level)
    MatcherService(settings, FrontendSettings(), ZenohSettings()).run()
