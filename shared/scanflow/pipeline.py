"""The in-process pipeline for one robot: the deskew stage, then the scan-to-map front end.

It is what `scanflow run` and the benchmarks use, and the reference the distributed services
equal bit for bit: the deskew service runs the same `DeskewStage` (points travel as float64),
the matcher the same `Frontend` with odometry from `DeskewStage.odometry_pose_at`, the map
server the front end's own `insert_scan`. No-return beams travel alongside the valid ones
(`DeskewResult.no_return_points`) and clear free space wherever the scan is inserted.
(The deskew service may wait for odometry that arrives after a scan; in-process, a scan is
deskewed with the odometry that came before it.)

    pipeline = Pipeline(settings)              # FrontendSettings; deskew on by default
    pipeline.add_odometry(sample)              # every Odometry sample, in any order
    out = pipeline.process(scan)               # -> PipelineOutput (deskew result + estimate)
    Pipeline(settings, backend=BackendSettings(loop_closure=True))   # + loop closure:
    pipeline.finish(); pipeline.mapper.trajectory(), pipeline.mapper.draw_map()  # optimised
"""

from __future__ import annotations

import time
from collections import OrderedDict
from dataclasses import dataclass

from scanflow.backend import Mapper, MapperStep
from scanflow.config import BackendSettings, FrontendSettings
from scanflow.deskew import (
    DEFAULT_REFERENCE,
    ConstantVelocityModel,
    DeskewResult,
    OdometryBuffer,
    PoseSource,
    Reference,
    deskew,
)
from scanflow.frontend import Frontend, FrontendOutput
from scanflow.geometry import Pose2D
from scanflow.maps.occupancy import OccupancyGrid
from scanflow.scan import LaserScan, Odometry

MEASURED_POSES_KEPT = 256  # recent odometry samples looked up by exact stamp


class DeskewStage:
    """Per robot: buffer odometry, deskew each scan with it (else with the constant-velocity
    prior fed by `observe_pose`, else not at all), and give the odometry pose at a stamp."""

    def __init__(
        self,
        reference: Reference = DEFAULT_REFERENCE,
        odometry: OdometryBuffer | None = None,
        enabled: bool = True,
    ) -> None:
        self.reference = reference
        self.odometry = odometry if odometry is not None else OdometryBuffer()
        self.velocity = ConstantVelocityModel()
        self.enabled = enabled
        self._measured: OrderedDict[float, Pose2D] = OrderedDict()

    def add_odometry(self, sample: Odometry) -> bool:
        """Buffer one sample; False when it was older than the buffer's window."""
        self._measured[sample.stamp_s] = sample.pose
        self._measured.move_to_end(sample.stamp_s)
        if len(self._measured) > MEASURED_POSES_KEPT:
            self._measured.popitem(last=False)
        return self.odometry.add_odometry(sample)

    def observe_pose(self, stamp_s: float, pose: Pose2D) -> None:
        """Feed an estimated pose to the constant-velocity prior (used without odometry)."""
        self.velocity.update(stamp_s, pose)

    def process(self, scan: LaserScan) -> DeskewResult:
        """The scan's valid and no-return endpoints in the robot's frame at the reference pose
        (see scanflow.deskew)."""
        sources: list[PoseSource] = [self.odometry, self.velocity] if self.enabled else []
        return deskew(scan, sources, self.reference)

    def odometry_pose_at(self, stamp_s: float) -> Pose2D | None:
        """The odometry pose measured at `stamp_s` when a recent sample has exactly that stamp
        (logs with one odometry pose per scan), else the buffer's interpolation, else None."""
        measured = self._measured.get(stamp_s)
        if measured is not None:
            return measured
        if self.odometry.coverage_gap(stamp_s, stamp_s) is not None:
            return None
        x, y, theta = self.odometry.poses_at([stamp_s])
        return Pose2D(float(x[0]), float(y[0]), float(theta[0]))


@dataclass(frozen=True, eq=False)
class PipelineOutput:
    """One scan through the pipeline: what deskewing did and what the front end estimated."""

    deskew: DeskewResult
    estimate: FrontendOutput
    deskew_time_s: float
    backend: MapperStep | None = None  # what loop closure did (None: it is off)


class Pipeline:
    """Deskew stage + front end for one robot, in one process."""

    def __init__(
        self,
        settings: FrontendSettings | None = None,
        *,
        deskew_enabled: bool = True,
        reference: Reference = DEFAULT_REFERENCE,
        initial_pose: Pose2D | None = None,
        grid: OccupancyGrid | None = None,
        backend: BackendSettings | None = None,
    ) -> None:
        """`grid`: a prior map to track against (and extend), else a new empty one;
        `backend` with loop_closure on: keyframes, loop closures and a pose graph as well
        (drawn on the prior map, and closing loops on it too)."""
        self.deskew_stage = DeskewStage(reference, enabled=deskew_enabled)
        self.frontend = Frontend(settings, initial_pose, grid)
        self.mapper = (
            Mapper(self.frontend, backend, prior=grid)
            if backend is not None and backend.loop_closure else None
        )

    def add_odometry(self, sample: Odometry) -> None:
        """Buffer one odometry sample: it deskews scans and gives the front end odometry poses."""
        self.deskew_stage.add_odometry(sample)

    def process(self, scan: LaserScan, odom_pose: Pose2D | None = None) -> PipelineOutput:
        """Deskew and track one scan. `odom_pose` overrides the buffered odometry at the
        reference stamp (logs that carry one odometry pose per scan, e.g. CARMEN keyframes)."""
        t0 = time.perf_counter()
        result = self.deskew_stage.process(scan)
        deskew_time_s = time.perf_counter() - t0
        stamp_s = result.reference_stamp_s
        if odom_pose is None:
            odom_pose = self.deskew_stage.odometry_pose_at(stamp_s)
        estimate = self.frontend.process(
            result.points, stamp_s, odom_pose, scan.seq, result.no_return_points, result.mount
        )
        step = None
        if self.mapper is not None:
            step = self.mapper.add(
                estimate, result.points, result.no_return_points, result.mount
            )
            if step.correction is not None:  # the front end's map frame moved: follow it
                self.deskew_stage.velocity.move_frame(step.correction)
                estimate = estimate.in_frame(step.correction)
        if estimate.accepted:
            self.deskew_stage.observe_pose(stamp_s, estimate.pose)
        return PipelineOutput(result, estimate, deskew_time_s, step)

    def finish(self) -> MapperStep | None:
        """End of the log: the back end's last optimisation (None without loop closure)."""
        if self.mapper is None:
            return None
        step = self.mapper.finish()
        if step.correction is not None:
            self.deskew_stage.velocity.move_frame(step.correction)
        return step
