"""Latest pose, pose at a time (SE(2) interpolation) and trajectory (JSON or TUM) of a robot;
PUT an operator's pose (ROS's /initialpose) to the robot's tracker.

Poses come from the gateway's bounded cache of the estimates on the bus; times and ranges the
cache no longer covers are answered from the map server's full trajectory.
"""

from __future__ import annotations

import math
from typing import Annotated, Literal

import numpy as np
from fastapi import APIRouter, Depends, HTTPException, Query
from fastapi.responses import PlainTextResponse, Response
from numpy.typing import NDArray
from scanflow import keys
from scanflow.frontend.trajectory import tum_text
from scanflow.geometry import Pose2D
from scanflow.wire import InitialPoseMessage, TrajectoryMessage
from starlette.concurrency import run_in_threadpool

from services.gateway.backend import BackendError, ZenohBackend
from services.gateway.deps import API_PREFIX, BAD_GATEWAY, Backend, Robot, require_key
from services.gateway.models import PoseIn, PoseOut, TimedPose, TrajectoryOut
from services.gateway.routers.match import ANSWERS
from services.gateway.tracks import estimate_arrays, pose_at

router = APIRouter(prefix=API_PREFIX, tags=["poses"])
TimeParam = Annotated[float | None, Query(ge=0.0, le=1e11, description="seconds")]
NOT_FOUND: dict[int | str, dict[str, str]] = {
    404: {"description": "unknown robot, or a time outside its trajectory"}, **BAD_GATEWAY
}
# A time before the gateway's cache: the map server's trajectory.
BEFORE_THE_CACHE: dict[int | str, dict[str, str]] = {
    503: {"description": "t is before the gateway's cache, and no map server answers"},
    504: {"description": "t is before the gateway's cache, and the map server timed out"},
}


def _unknown(robot: str, why: str = "") -> HTTPException:
    return HTTPException(404, f"robot {robot!r} has published no pose{why}")


@router.get(
    "/robots/{robot}/pose", response_model=PoseOut, responses={**NOT_FOUND, **BEFORE_THE_CACHE},
    summary="Latest pose, or the pose at time t (interpolated between estimates)",
)
async def get_pose(robot: Robot, backend: Backend, t: TimeParam = None) -> PoseOut:
    """The robot's latest pose, or with `t` its pose at that time: interpolated between the two
    estimates around it (the map server's whole trajectory for times before the gateway's cache,
    and for a robot whose poses this gateway has not seen: it started or restarted since)."""
    if t is None:
        latest = backend.tracks.latest(robot)
        if latest is not None:
            return PoseOut.from_estimate(latest)
        stamps, poses = await _trajectory_of_unseen(backend, robot)
        last = Pose2D.from_array(poses[-1])
        return PoseOut.from_trajectory(robot, last, float(stamps[-1]), interpolated=False)
    estimates = backend.tracks.estimates(robot)
    if estimates:
        stamps, poses = estimate_arrays(estimates)
        found = pose_at(stamps, poses, t)
        if found is not None:
            return PoseOut.from_estimate(estimates[found[1]], found[0], t)
        if t > stamps[-1]:
            raise HTTPException(404, f"t={t} is after the last pose of {robot!r} ({stamps[-1]})")
        stamps, poses = await _full_trajectory(backend, robot)
    else:
        stamps, poses = await _trajectory_of_unseen(backend, robot)
    found = pose_at(stamps, poses, t)
    if found is None:
        span = f"{stamps[0]}..{stamps[-1]}" if len(stamps) else "empty"
        raise HTTPException(404, f"t={t} is outside the trajectory of {robot!r} ({span})")
    return PoseOut.from_trajectory(robot, found[0], t)


@router.put(
    "/robots/{robot}/pose", response_model=PoseIn, responses=ANSWERS,
    dependencies=[Depends(require_key)],
    summary="Tell the robot's tracker where it is now (map frame): its next scan is matched "
    "from there (before its first scan: the start)",
)
async def put_pose(robot: Robot, body: PoseIn, backend: Backend) -> PoseIn:
    """Set where the robot is now (map frame): its tracker matches the next scan from there.
    Answers with the pose the tracker took."""
    message = InitialPoseMessage(robot, body.to_pose())
    replies = await backend.aquery(keys.initial_pose(robot, backend.prefix), message.encode())
    taken = InitialPoseMessage.decode(replies[0].payload)  # the tracker's echo
    return PoseIn(x_m=taken.pose.x, y_m=taken.pose.y, theta_rad=taken.pose.theta)


async def _trajectory_of_unseen(
    backend: ZenohBackend, robot: str
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """The map server's trajectory of a robot none of whose poses this gateway has: 404 (the
    robot unknown) when it has none either, or cannot be asked."""
    try:
        stamps, poses = await _full_trajectory(backend, robot)
    except BackendError as exc:
        if exc.status_code not in (404, 503, 504):
            raise
        raise _unknown(robot, f" (the map server's trajectory: {exc.reason})") from exc
    if not len(stamps):
        raise _unknown(robot)
    return stamps, poses


async def _full_trajectory(
    backend: ZenohBackend, robot: str
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    replies = await backend.aquery(keys.trajectory(robot, backend.prefix))
    message = TrajectoryMessage.decode(replies[0].payload)
    return message.stamps_s, message.poses


@router.get(
    "/robots/{robot}/trajectory", responses={
        **NOT_FOUND, 200: {"content": {"text/plain": {"example": "1.0 0.5 0.2 0 0 0 0.0998 0.995"}},
                           "description": "JSON, or TUM lines: stamp x y z qx qy qz qw"}},
    response_model=TrajectoryOut, summary="Trajectory over [start, end] as JSON or TUM text",
)
async def get_trajectory(
    robot: Robot,
    backend: Backend,
    start: TimeParam = None,
    end: TimeParam = None,
    format: Annotated[Literal["json", "tum"], Query(description="tum: for evo")] = "json",
) -> Response:
    """The robot's poses within [start, end], as JSON or TUM lines (for evo): the map server's
    trajectory, or the gateway's cache when the map server cannot give it (`X-Scanflow-Source`)."""
    source: Literal["mapserver", "cache"] = "mapserver"
    try:
        stamps, poses = await _full_trajectory(backend, robot)
    except BackendError as exc:
        if exc.status_code not in (404, 503, 504):
            raise
        estimates = backend.tracks.estimates(robot)
        if not estimates:
            raise _unknown(robot) from exc
        stamps, poses = estimate_arrays(estimates)
        source = "cache"
    keep = (stamps >= (-math.inf if start is None else start)) & (
        stamps <= (math.inf if end is None else end)
    )
    # Writing 10^5 poses out takes a second of CPU: off the event loop.
    return await run_in_threadpool(_written, robot, source, stamps[keep], poses[keep], format)


def _written(
    robot: str, source: Literal["mapserver", "cache"], stamps: NDArray[np.float64],
    poses: NDArray[np.float64], format: Literal["json", "tum"],
) -> Response:
    """The trajectory as TUM text, or as TrajectoryOut's JSON (written here, not by FastAPI
    on the event loop)."""
    if format == "tum":
        return PlainTextResponse(tum_text(stamps, poses), headers={"X-Scanflow-Source": source})
    out = TrajectoryOut(
        robot_id=robot,
        source=source,
        poses=[
            TimedPose(stamp_s=s, x_m=p[0], y_m=p[1], theta_rad=p[2])
            for s, p in zip(stamps.tolist(), poses.tolist(), strict=True)
        ],
    )
    return Response(out.model_dump_json(), media_type="application/json")

