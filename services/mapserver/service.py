"""Map server: inserts the scans the matcher inserted, at the poses it inserted them, with the
library's map update; keeps the matcher's poses as each robot's trajectory; serves the maps on
queryables, publishes rate-limited change notices and snapshots every robot atomically to the
data directory (a restart resumes from there). With loop closure on (SCANFLOW_BACKEND_*, as the
matchers) it keeps every keyframe's scan (each insert not flagged as culled) and repeats the
matcher's map redraws. An insert or a redraw that shows inserts missing before it (a link that
dropped, a restart from a snapshot) gets them from the matcher again first, so the map stays
the matcher's. A robot retired (`<prefix>/<robot>/retire/mapserver`) loses its map, path and
keyframes, and its snapshot files are deleted, so that a restart does not bring it back.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from pathlib import Path

import zenoh
from scanflow import keys
from scanflow.config import BackendSettings, FrontendSettings, MapServerSettings, ZenohSettings
from scanflow.frontend import default_settings, occupancy_params
from scanflow.frontend.prior import FrontendStart, PriorMapError
from scanflow.maps.export import grid_from_npz_bytes
from scanflow.maps.occupancy import OccupancyGrid
from scanflow.warmup import warm_up
from scanflow.wire import (
    MapInsertMessage,
    MapRedrawMessage,
    MapStateMessage,
    Message,
    PoseEstimateMessage,
    SchemaError,
    decode_any,
)

from services.common.process import init_process, require_settings
from services.common.resend import FIRST, resend_selector
from services.common.retire import Dropped
from services.common.shell import ServiceShell
from services.mapserver import replies
from services.mapserver.robot import RobotMap
from services.mapserver.snapshot import (
    keep_previous,
    load_snapshots,
    remove_snapshot,
    save_snapshot,
)

Builder = Callable[[RobotMap, zenoh.Parameters], Message]
Update = MapInsertMessage | MapRedrawMessage | PoseEstimateMessage


def _map_update(data: bytes) -> MapInsertMessage | MapRedrawMessage:
    """A message on a robot's inserts key: an insert, or a redraw between two inserts."""
    message = decode_any(data)
    if not isinstance(message, MapInsertMessage | MapRedrawMessage):
        raise SchemaError(f"message.type: expected map_insert or map_redraw, got {message.TYPE!r}")
    return message


class MapServer:
    """Per-robot maps built from the bus, served on queryables, persisted as snapshots."""

    def __init__(
        self,
        settings: MapServerSettings,
        zenoh_settings: ZenohSettings,
        frontend_settings: FrontendSettings | None = None,
        backend_settings: BackendSettings | None = None,
    ) -> None:
        """`frontend_settings`: the matchers' (their map resolution), default the documented;
        `backend_settings`: the matchers' too (with loop closure, keyframes are kept)."""
        self.settings = settings
        backend = backend_settings if backend_settings is not None else BackendSettings()
        self.keep_keyframes = backend.loop_closure
        frontend = frontend_settings if frontend_settings is not None else default_settings()
        self.params = occupancy_params(frontend)
        self.start = FrontendStart(frontend)  # a bad prior map stops the start here
        self.data_dir = Path(settings.data_dir)
        self.shell = ServiceShell("mapserver", settings, zenoh_settings)
        self.robots: dict[str, RobotMap] = {}
        self.lock = threading.Lock()  # the worker inserts while the query thread reads
        snapshots, skipped = load_snapshots(self.data_dir)
        for reason in skipped:
            self.shell.log.warning("%s; starting that robot afresh", reason)
        for snap in snapshots:
            self.robots[snap.robot_id] = RobotMap(
                snap.robot_id, self.new_grid, snap, self.keep_keyframes
            )
            self.shell.seqs.resume(f"{snap.robot_id}/pose", snap.last_seq)
            self.shell.log.info("robot %s: resumed at seq %d", snap.robot_id, snap.last_seq)
        self._last_notice_s = 0.0
        self._last_snapshot_s = time.monotonic()
        prefix = self.shell.prefix
        self.shell.subscribe(keys.map_key("*", "insert", prefix), "insert", _map_update)
        self.shell.subscribe(keys.pose("*", prefix), "pose", PoseEstimateMessage.decode)
        self._serve(lambda r: keys.map_key(r, "meta", prefix), lambda r, _p: replies.meta(r))
        self._serve(lambda r: keys.map_key(r, "image", prefix), _image)
        self._serve(lambda r: keys.map_key(r, "region", prefix), _region)
        self._serve(lambda r: keys.trajectory(r, prefix), lambda r, _p: replies.trajectory(r))
        self._serve(
            lambda r: keys.map_key(r, "resume", prefix), lambda r, _p: replies.resume(r)
        )
        self.shell.add_stats(self._gauges)
        self.shell.serve_retire(self.retire)

    # -- bus ------------------------------------------------------------------------------
    def handle(self, kind: str, message: Update) -> None:
        """Apply an insert, redraw or pose under the lock the queries take, then the idle work
        (change notices, snapshots) when due."""
        with self.lock:
            self._apply(kind, message)
        self.idle()

    def _apply(self, kind: str, message: Update) -> None:
        robot_id = message.robot_id
        robot = self.robots.get(robot_id)
        if robot is None:
            if not self.shell.admits(robot_id, self.robots):
                return
            robot = self.robots[robot_id] = RobotMap(
                robot_id, self.new_grid, keep_keyframes=self.keep_keyframes
            )
        if not self._of_the_run(robot, message):
            return
        if self._held(robot, message):  # in the tracker's map taken before
            return
        if isinstance(message, MapRedrawMessage):  # follows the insert of its own scan
            if len(message.keyframe_seqs):
                self._catch_up(robot, int(message.keyframe_seqs[-1]))
            if self._held(robot, message):  # the catch-up took the tracker's map, redrawn
                return
            robot.redraw(message, self.params)
            self.shell.counters.add("redrawn")
            return
        if isinstance(message, MapInsertMessage):  # sparse seqs: gaps are not misses
            restarted = message.seq <= robot.last_insert_seq
        else:
            restarted = self.shell.seqs.is_restart(f"{robot_id}/pose", message.seq)
            self.shell.seqs.observe(f"{robot_id}/pose", message.seq)
        if restarted and kind in robot.streams:
            # A replay: start afresh. The other stream's restart, seen later, finds this run
            # without it and keeps it.
            self.shell.log.info("robot %s: %ss restarted at seq %d", robot_id, kind, message.seq)
            self._keep_previous(robot)
            robot.reset()
        robot.streams.add(kind)
        if isinstance(message, MapInsertMessage):
            if message.previous_seq is not None:
                self._catch_up(robot, message.previous_seq)
            if self._held(robot, message):  # the catch-up took the tracker's map: it has it
                return
            robot.insert(message)
            self.shell.counters.add("inserted")
        else:
            robot.apply(message)

    def _of_the_run(self, robot: RobotMap, message: Update) -> bool:
        """Whether to apply the message now, by its tracker run (0: any). Of the map's run (or
        the first run a map hears of): yes. Of a run it replaced: no (late; counted). An
        insert or redraw of another run starts a new run: the map and path start afresh
        (logged; seqs alone miss a new run whose first scans this server never saw) and that
        run's poses held so far go in. A pose of another run is held (`RobotMap.hold`), unless
        the map's run put nothing in the map: then it starts the new run too."""
        run = message.run
        if not run or run == robot.run:
            return True
        if run in robot.ended_runs:
            self.shell.counters.add("ended_run_dropped")
            return False
        if not robot.run:  # a new robot, or a snapshot older than run tokens
            robot.run = run
            return True
        if isinstance(message, PoseEstimateMessage) and robot.last_insert_seq >= 0:
            self.shell.counters.add("poses_held")
            if not robot.hold(message):
                self.shell.counters.add("held_poses_dropped")
            return False
        # An insert or redraw of another run, or a pose where the map's run put nothing in
        # the map (a robot localising on a prior map): a new run.
        self.shell.log.info("robot %s: a new run of its tracker at seq %d: its map and path "
                            "start afresh", robot.robot_id, message.seq)
        self.shell.counters.add("runs_replaced")
        self._keep_previous(robot)
        for pose in robot.start_run(run):
            self._apply("pose", pose)
        return True

    def _keep_previous(self, robot: RobotMap) -> None:
        """Before a new run replaces the robot's map: its snapshot is kept aside (logged), or,
        failing that, the failure is logged and counted; the new run goes on either way."""
        try:
            kept = keep_previous(self.data_dir, robot.robot_id)
        except OSError as exc:
            self.shell.counters.add("snapshots_failed")
            self.shell.log.error("robot %s: the replaced run's snapshot not kept aside: %s",
                                 robot.robot_id, exc)
            return
        if kept is not None:
            self.shell.log.info("robot %s: the replaced run's map and path kept as %s",
                                robot.robot_id, kept.name)

    def _held(self, robot: RobotMap, message: Update) -> bool:
        """Whether the robot's map holds the insert or redraw already (counted)."""
        if not robot.holds(message):
            return False
        held = "redraws_held" if isinstance(message, MapRedrawMessage) else "inserts_held"
        self.shell.counters.add(held)
        return True

    def _catch_up(self, robot: RobotMap, through: int) -> None:
        """Insert what the matcher inserted after this robot's last insert here, through seq
        `through`, asked for again; logged and counted (`inserts_lost`) when it cannot send
        them all: the map then lacks those scans. A matcher past its recent inserts sends the
        back end's keyframes when they are all of them, else its whole map and path
        (MapStateMessage), which replace this robot's. Called under the lock, which it lets go
        while it asks."""
        after = robot.last_insert_seq
        if through <= after:
            return
        key = keys.map_key(robot.robot_id, "resend", self.shell.prefix)
        # The worker alone changes the maps, and they are whole here: the queries that read
        # them go on while it waits for the matcher (up to resend_timeout_s).
        self.lock.release()
        try:  # the message that showed the gap goes in whatever happens here
            payloads, errors = self.shell.get(
                resend_selector(key, after, through), self.settings.resend_timeout_s
            )
        except (zenoh.ZError, RuntimeError) as exc:  # no side session, a refused query
            payloads, errors = [], [f"the query failed: {exc}"]
        finally:
            self.lock.acquire()
        try:
            messages = [decode_any(p) for p in payloads]
            if messages and isinstance(messages[0], MapStateMessage):
                self._take_state(robot, messages[0], after, through)
                return
            inserts = [m for m in messages if isinstance(m, MapInsertMessage)]
            if len(inserts) != len(messages):
                raise SchemaError(f"the answers are {sorted({m.TYPE for m in messages})}")
            inserts.sort(key=lambda m: m.seq)
            other = {m.run for m in inserts} - {0, robot.run}
            if other:  # the tracker started another run meanwhile: its messages will say so
                raise LookupError("the matcher's inserts are of another run of its tracker")
            chained = [m.previous_seq for m in inserts] == [
                None if after == FIRST else after, *(m.seq for m in inserts[:-1])
            ]
            if not inserts or not chained or inserts[-1].seq != through:
                raise LookupError("; ".join(errors) or f"{len(inserts)} came, not the chain")
        except (ValueError, LookupError) as exc:  # DecodeError, a broken map, a short chain
            n = self.shell.counters.add("inserts_lost")
            self.shell.log.warning(
                "robot %s: inserts after seq %d through %d never came, and the matcher did not "
                "send them again (%s); the map lacks them (%d such gaps)",
                robot.robot_id, after, through, exc, n,
            )
            return
        for insert in inserts:
            robot.insert(insert)
        self.shell.counters.add("inserts_resent", len(inserts))
        self.shell.log.info("robot %s: inserts after seq %d through %d came again (%d)",
                            robot.robot_id, after, through, len(inserts))

    def _take_state(
        self, robot: RobotMap, state: MapStateMessage, after: int, through: int
    ) -> None:
        """The matcher's whole map and path in place of the inserts after seq `after` through
        `through`; ValueError, changing nothing, when it is not that robot's or ends short."""
        if state.run not in (0, robot.run):
            raise ValueError(f"the matcher's map of {robot.robot_id} is of another run")
        if state.robot_id != robot.robot_id or state.insert_seq < through:
            raise ValueError(
                f"a map of robot {state.robot_id!r} through insert {state.insert_seq} came, "
                f"not one of {robot.robot_id!r} through {through}"
            )
        grid = grid_from_npz_bytes(state.map_npz, f"the matcher's map of {robot.robot_id}")
        robot.take_state(state, grid, after)
        self.shell.counters.add("map_states_taken")
        self.shell.log.warning(
            "robot %s: inserts after seq %d through %d are no longer kept by the matcher; took "
            "its whole map (every insert through seq %d) and path (%d poses) instead",
            robot.robot_id, after, through, state.insert_seq, len(state.poses),
        )

    def new_grid(self) -> OccupancyGrid:
        """A new robot's map: the prior map the matchers start on, else an empty grid."""
        prior = self.start.grid()
        return prior if prior is not None else OccupancyGrid(self.params)

    def idle(self) -> None:
        """Publish change notices at the configured rate; snapshot at the configured interval."""
        now = time.monotonic()
        if now - self._last_notice_s >= 1.0 / self.settings.changed_rate_hz:
            self._publish_changes()
            self._last_notice_s = now
        if now - self._last_snapshot_s >= self.settings.snapshot_interval_s:
            self.snapshot()

    def _publish_changes(self) -> None:
        for robot in self.robots.values():
            notice = robot.take_change(time.time())
            if notice is not None:
                key = keys.map_key(robot.robot_id, "changed", self.shell.prefix)
                self.shell.put(key, notice.encode())
                self.shell.counters.add("notices")

    def snapshot(self) -> None:
        """Persist every robot whose map or trajectory moved since its last snapshot. One that
        cannot be written (a full disk) is logged and tried again at the next interval; the
        others are still written."""
        self._last_snapshot_s = time.monotonic()
        for robot in self.robots.values():
            if robot.last_seq >= 0 and robot.saved != robot.state:
                try:
                    save_snapshot(
                        self.data_dir, robot.snapshot(), self.settings.keyframes_per_file
                    )
                except (OSError, ValueError, OverflowError) as exc:
                    self.shell.counters.add("snapshots_failed")
                    self.shell.log.error("robot %s: snapshot not written: %s: %s",
                                         robot.robot_id, type(exc).__name__, exc)
                    continue
                robot.saved = robot.state
                self.shell.counters.add("snapshots")

    def retire(self, robot_id: str) -> Dropped:
        """Let go of the robot (on the worker, between two messages, where snapshots are
        written too; under the lock the map queries take): its map, path and keyframes, then
        its snapshot files (OSError when one cannot be deleted: asked again, the retire deletes
        what is left). What went is counted (`map_revision`, `poses`, `keyframes`,
        `snapshot_files`)."""
        with self.lock:
            robot = self.robots.pop(robot_id, None)
        counts = {}
        if robot is not None:
            counts["map_revision"] = robot.map.revision
            counts["poses"] = len(robot.trajectory.stamps_s)
            if robot.keyframes is not None:
                counts["keyframes"] = len(robot.keyframes)
        counts["snapshot_files"] = remove_snapshot(self.data_dir, robot_id)
        return Dropped(robot is not None or counts["snapshot_files"] > 0, counts)

    # -- queries --------------------------------------------------------------------------
    def _serve(self, key_of: Callable[[str], str], build: Builder) -> None:
        """Serve `key_of("*")`: one reply per robot the query names (or every robot)."""

        def handler(query: zenoh.Query) -> None:
            asked = query.key_expr
            with self.lock:
                wanted = [r for r in self.robots.values() if asked.intersects(key_of(r.robot_id))]
                if not wanted and "*" not in str(asked):
                    raise LookupError(f"no map for {asked} (robots: {sorted(self.robots)})")
                replies_ = [(key_of(r.robot_id), build(r, query.parameters)) for r in wanted]
            for key, message in replies_:
                query.reply(key, message.encode())

        self.shell.serve(key_of("*"), handler)

    def _gauges(self) -> dict[str, float]:
        robots = list(self.robots.values())  # a copy: the worker may admit a robot meanwhile
        gauges: dict[str, float] = {"robots": len(robots)}
        for robot in robots:
            r = robot.robot_id
            gauges.update({
                f"{r}.revision": robot.map.revision,
                f"{r}.map_bytes": robot.map.grid.nbytes,
                f"{r}.last_insert_seq": robot.last_insert_seq,
            })
            if robot.keyframes is not None:
                gauges[f"{r}.keyframes"] = len(robot.keyframes)
        return gauges

    def run(self) -> None:
        """Warm up (if set), serve until stopped, then publish the last change notices, snapshot
        every robot and close."""
        with self.shell:
            if self.settings.warm_up:  # before the health token: the first scan at full speed
                warm_up()
            self.shell.start()
            self.shell.run(self.handle, self.idle)
            self._publish_changes()
            self.snapshot()


def _image(robot: RobotMap, params: zenoh.Parameters) -> Message:
    return replies.image(robot, params.get("format", "png") or "png")


def _region(robot: RobotMap, params: zenoh.Parameters) -> Message:
    """The whole map, or the world box given as parameters x0, y0, x1, y1 (metres)."""
    names = ("x0", "y0", "x1", "y1")
    given = [params.get(n) for n in names]
    values = [v for v in given if v is not None]
    if not values:
        return replies.region(robot, None)
    if len(values) != len(names):
        got = dict(zip(names, given, strict=True))
        raise ValueError(f"region needs all of x0, y0, x1, y1 or none, got {got}")
    x0, y0, x1, y1 = (float(v) for v in values)
    return replies.region(robot, (x0, y0, x1, y1))


def main() -> None:
    """Run the map server (settings: SCANFLOW_MAPSERVER_*, SCANFLOW_ZENOH_*, and the map
    resolution from SCANFLOW_FRONTEND_*, so its maps have the matchers' lattice, and
    SCANFLOW_BACKEND_LOOP_CLOSURE as the matchers have it)."""
    require_settings(
        "mapserver", MapServerSettings, ZenohSettings, FrontendSettings, BackendSettings
    )
    settings = MapServerSettings()
    init_process(settings)
    try:  # a bad prior map: stop at start, naming it
        server = MapServer(settings, ZenohSettings(), FrontendSettings(), BackendSettings())
    except PriorMapError as exc:
        raise SystemExit(f"mapserver: {exc}") from exc
    server.run()
