"""GET /robots: every robot seen on the bus, with its last pose and data times."""

from __future__ import annotations

from fastapi import APIRouter

from services.gateway.deps import API_PREFIX, Backend
from services.gateway.models import PoseOut, RobotOut, RobotsOut, ServiceOut

router = APIRouter(prefix=API_PREFIX, tags=["robots"])


@router.get("/robots", response_model=RobotsOut, summary="Robots seen and live services")
def list_robots(backend: Backend) -> RobotsOut:
    """Every robot seen on the bus (last pose, data times, map revision, restarts) and every
    service alive now."""
    robots = [
        RobotOut(
            robot_id=r.robot_id,
            last_pose=None if r.latest is None else PoseOut.from_estimate(r.latest),
            poses_cached=r.poses_cached,
            last_pose_received_s=r.last_pose_received_s,
            last_scan_received_s=r.last_scan_received_s,
            scans_seen=r.scans_seen,
            map_revision=r.map_revision,
            restarts=r.restarts,
        )
        for r in backend.tracks.robots()
    ]
    services = [ServiceOut(service=s, instance=i) for s, i in backend.alive_services()]
    return RobotsOut(robots=robots, services=services)
