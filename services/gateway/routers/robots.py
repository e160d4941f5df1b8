"""GET /robots: every robot seen on the bus, with its last pose and data times; DELETE
/robots/{robot}: retire a robot from every service that keeps robot state, and the gateway."""

from __future__ import annotations

from fastapi import APIRouter, Depends, HTTPException

from services.gateway.deps import API_PREFIX, BAD_GATEWAY, KEY_ANSWERS, Backend, Robot, require_key
from services.gateway.models import (
    DroppedOut,
    PoseOut,
    RetiredOut,
    RetiredServiceOut,
    RobotOut,
    RobotsOut,
    ServiceOut,
)

router = APIRouter(prefix=API_PREFIX, tags=["robots"])
RETIRE_ANSWERS: dict[int | str, dict[str, str]] = {
    **KEY_ANSWERS,
    **BAD_GATEWAY,
    404: {"description": "neither the gateway nor any service held state of the robot"},
    422: {"description": "the robot id is no key chunk (or a reserved one)"},
    503: {"description": "deskew, matcher or map server is not running (nothing was retired), "
          "or one is stopping"},
    504: {"description": "a service that is alive did not answer in time (named; the services "
          "asked before it did drop the robot: ask again)"},
}


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


@router.delete(
    "/robots/{robot}", response_model=RetiredOut, responses=RETIRE_ANSWERS,
    dependencies=[Depends(require_key)],
    summary="Retire a robot: every service drops all of its state (map, snapshot, path, "
    "buffers) and its max_robots place is free",
)
async def retire_robot(robot: Robot, backend: Backend) -> RetiredOut:
    """Ask deskew, every matcher shard and the map server, in that order (the data's), to drop
    all they keep of the robot, then drop the gateway's own; answer with each confirmation and
    what it dropped. The map server deletes the robot's snapshot files too: download `map.zip`
    first to keep the map. A message of the robot that comes later starts it afresh, as a new
    robot (stop its source first). Asking again is harmless: it finishes a retire that failed
    part way (504)."""
    answers, gateway = await backend.aretire(robot)
    if gateway is None and not any(a.known for a in answers):
        raise HTTPException(
            404, f"robot {robot!r} is unknown: neither the gateway nor any service held state "
            "of it"
        )
    return RetiredOut(
        robot_id=robot,
        services=[
            RetiredServiceOut(service=a.service, instance=a.instance, known=a.known,
                              dropped=a.dropped)
            for a in answers
        ],
        gateway=DroppedOut(known=gateway is not None, dropped=gateway or {}),
    )
