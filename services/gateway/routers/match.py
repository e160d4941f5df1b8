"""POST /match: forwarded to the matcher's queryable (scan-to-scan or scan-to-map)."""

from __future__ import annotations

import time

from fastapi import APIRouter, Depends, Request
from fastapi.responses import Response
from scanflow import keys
from scanflow.matching import DEFAULT_METHOD, MatchInputError, available_methods
from scanflow.matching.api import check_options
from scanflow.scan import LaserScan, ScanError
from scanflow.wire import MapRef, MatchRequest, MatchResponse, MessageError

from services.gateway.backend import BackendError
from services.gateway.body import BODY_ANSWERS, MSGPACK, body_doc, invalid, read_body
from services.gateway.deps import API_PREFIX, BAD_GATEWAY, Backend, Settings, require_key
from services.gateway.models import MatchIn, MatchOut, MethodsOut, ScanIn

router = APIRouter(prefix=API_PREFIX, tags=["match"])
ANSWERS = {
    **BODY_ANSWERS,
    **BAD_GATEWAY,
    404: {"description": "scan-to-map: the robot is unknown (no matcher, no pose of it)"},
    503: {"description": "no matcher answers"},
    504: {"description": "the matcher did not answer in time"},
}


@router.get("/match/methods", response_model=MethodsOut,
            summary="Every matching method the library has")
def methods() -> MethodsOut:
    """The names `method` accepts in POST /match, and the default one."""
    return MethodsOut(methods=available_methods(), default=DEFAULT_METHOD)


@router.post(
    "/match",
    response_model=MatchOut,
    responses={**ANSWERS, 200: {"content": {MSGPACK: {}}, "description": "JSON, or a "
               "MatchResponse message when the request accepts application/x-msgpack"}},
    dependencies=[Depends(require_key)],
    openapi_extra=body_doc(MatchIn, MatchRequest, "two scans, or one scan and a robot_id"),
    summary="Match a scan against another scan or a robot's map",
)
async def post_match(
    request: Request, backend: Backend, settings: Settings
) -> MatchOut | Response:
    """Match a scan against a second scan or against a robot's map (`robot_id`) on the matcher's
    queryable: pose, covariance, status and timing; msgpack in and out on request."""
    body = await read_body(request, MatchIn, MatchRequest)
    wire = body if isinstance(body, MatchRequest) else to_request(body, settings.max_beams)
    check_request(wire, settings.max_beams)
    if isinstance(wire.target, MapRef):
        selector = keys.robot_match(keys.check_robot_id(wire.target.robot_id), backend.prefix)
        kind = "scan_to_map"
    else:
        selector, kind = keys.scan_match(backend.prefix), "scan_to_scan"
    t0 = time.perf_counter()
    try:
        replies = await backend.aquery(selector, wire.encode())
    except BackendError as exc:
        robot_id = wire.target.robot_id if isinstance(wire.target, MapRef) else None
        if exc.status_code == 503 and robot_id is not None and not backend.tracks.known(robot_id):
            raise BackendError(404, f"robot {robot_id!r} is unknown: no matcher tracks it, and "
                               "it has published no pose") from exc
        raise
    round_trip_s = time.perf_counter() - t0
    answer = MatchResponse.decode(replies[0].payload)
    if answer.error:
        raise BackendError(422, f"the matcher refused the request: {answer.error}")
    metrics = request.app.state.metrics
    metrics.observe("scanflow_match_duration_seconds", answer.time_s, method=wire.method, kind=kind)
    metrics.observe("scanflow_match_round_trip_seconds", round_trip_s, kind=kind)
    if MSGPACK in request.headers.get("accept", ""):
        return Response(answer.encode(), media_type=MSGPACK)
    return MatchOut.from_response(answer, round_trip_s)


def to_request(body: MatchIn, max_beams: int) -> MatchRequest:
    """The wire MatchRequest of a JSON body (scans numbered 0 and 1)."""
    source = _scan(body.source, "source", "request", 0, max_beams)
    target: MapRef | LaserScan
    if body.robot_id is not None:
        target = MapRef(body.robot_id)
    elif body.target is not None:
        target = _scan(body.target, "target", "request", 1, max_beams)
    else:  # MatchIn's own check refuses such a body first
        raise invalid(("body",), "give exactly one of target or robot_id")
    guess = None if body.initial_guess is None else body.initial_guess.to_pose()
    try:
        return MatchRequest(body.method, source, target, guess, dict(body.options))
    except MessageError as exc:
        raise invalid(("body",), str(exc)) from exc


def _scan(scan: ScanIn, field: str, robot_id: str, seq: int, max_beams: int) -> LaserScan:
    if len(scan.ranges_m) > max_beams:
        raise invalid(
            ("body", field, "ranges_m"), f"{len(scan.ranges_m)} beams, over max_beams={max_beams}"
        )
    try:
        return scan.to_scan(robot_id, seq)
    except ScanError as exc:
        raise invalid(("body", field), str(exc)) from exc


def check_request(request: MatchRequest, max_beams: int) -> None:
    """Method known, its options' names, types and finiteness right (their ranges are the
    matcher's to check), operands within max_beams (also for msgpack bodies)."""
    methods = available_methods()
    if request.method not in methods:
        raise invalid(("body", "method"), f"unknown method {request.method!r}; one of {methods}")
    try:
        check_options(request.method, request.options)
    except MatchInputError as exc:
        raise invalid(("body", "options"), str(exc)) from exc
    for field in ("source", "target"):
        operand = getattr(request, field)
        if isinstance(operand, MapRef):
            continue
        n = operand.beam_count if isinstance(operand, LaserScan) else len(operand)
        if n > max_beams:
            raise invalid(("body", field), f"{n} beams or points, over max_beams={max_beams}")

