"""POST /robots/{robot}/scans and /odometry: publish on the bus for clients without Zenoh."""

from __future__ import annotations

from dataclasses import replace

from fastapi import APIRouter, Depends, Request
from scanflow import keys
from scanflow.scan import ScanError
from scanflow.wire import MessageError, OdometryMessage, ScanMessage

from services.gateway.body import BODY_ANSWERS, body_doc, invalid, read_body
from services.gateway.deps import API_PREFIX, Backend, Robot, Settings, require_key
from services.gateway.models import IngestAck, OdometryIn, ScanIn

router = APIRouter(prefix=API_PREFIX, tags=["ingest"], dependencies=[Depends(require_key)])
ANSWERS = {
    **BODY_ANSWERS,
    409: {"description": "the seq does not move the robot's stream forward (0 starts a run)"},
    503: {"description": "the gateway tracks max_robots robots already"},
}


@router.post(
    "/robots/{robot}/scans", response_model=IngestAck, status_code=202, responses=ANSWERS,
    openapi_extra=body_doc(ScanIn, ScanMessage, "one scan (seq optional)"),
    summary="Publish a scan on the robot's raw scan key",
)
async def post_scan(
    request: Request, robot: Robot, backend: Backend, settings: Settings
) -> IngestAck:
    """Publish one scan (JSON or msgpack) for a client without Zenoh. The URL's robot id wins
    over the body's; with no seq the gateway numbers it. 422 names what is wrong with it."""
    body = await read_body(request, ScanIn, ScanMessage)
    given = body.scan.seq if isinstance(body, ScanMessage) else body.seq
    # Checked before it takes a seq: a corrected request may send the same seq again.
    message = _scan_message(body, robot, given or 0, settings.max_beams)
    key = keys.raw_scan(robot, backend.prefix)
    seq = await backend.apublish_numbered(
        robot, "scan", given, key, lambda seq: _renumbered(message, seq).encode()
    )
    backend.metrics.count("scanflow_gateway_ingested_total", kind="scan")
    return IngestAck(robot_id=robot, seq=seq, key=key)


@router.post(
    "/robots/{robot}/odometry", response_model=IngestAck, status_code=202, responses=ANSWERS,
    openapi_extra=body_doc(OdometryIn, OdometryMessage, "one odometry sample (seq optional)"),
    summary="Publish an odometry sample on the robot's odom key",
)
async def post_odometry(request: Request, robot: Robot, backend: Backend) -> IngestAck:
    """Publish one odometry sample (JSON or msgpack), numbered as scans are; 422 names what is
    wrong with it, 409 a seq that does not move the robot's stream forward."""
    body = await read_body(request, OdometryIn, OdometryMessage)
    given = body.odom.seq if isinstance(body, OdometryMessage) else body.seq
    message = _odometry_message(body, robot, given or 0)  # checked before it takes a seq
    key = keys.odom(robot, backend.prefix)
    seq = await backend.apublish_numbered(
        robot, "odom", given, key, lambda seq: _renumbered(message, seq).encode()
    )
    backend.metrics.count("scanflow_gateway_ingested_total", kind="odom")
    return IngestAck(robot_id=robot, seq=seq, key=key)


def _scan_message(
    body: ScanIn | ScanMessage, robot: str, seq: int, max_beams: int
) -> ScanMessage:
    """The scan to publish, under the path's robot id (the URL is authoritative) and `seq`;
    a 422 naming what is wrong with it."""
    try:
        scan = body.scan if isinstance(body, ScanMessage) else body.to_scan(robot, seq)
        if scan.beam_count > max_beams:
            raise invalid(
                ("body", "ranges_m"), f"{scan.beam_count} beams, over max_beams={max_beams}"
            )
        if scan.robot_id != robot or scan.seq != seq:
            scan = replace(scan, robot_id=robot, seq=seq)
        return ScanMessage(scan)
    except (ScanError, MessageError) as exc:
        raise invalid(("body",), str(exc)) from exc


def _renumbered(
    message: ScanMessage | OdometryMessage, seq: int
) -> ScanMessage | OdometryMessage:
    """The checked message under the seq it was given (built again only when the gateway
    numbered it); a 422 naming what is wrong (a seq past the wire's limit)."""
    if message.seq == seq:
        return message
    try:
        if isinstance(message, ScanMessage):
            return ScanMessage(replace(message.scan, seq=seq))
        return OdometryMessage(replace(message.odom, seq=seq))
    except (ScanError, MessageError) as exc:
        raise invalid(("body",), str(exc)) from exc


def _odometry_message(body: OdometryIn | OdometryMessage, robot: str, seq: int) -> OdometryMessage:
    """The odometry sample to publish, under the path's robot id and `seq`; a 422 naming what
    is wrong with it."""
    try:
        odom = body.odom if isinstance(body, OdometryMessage) else body.to_odometry(robot, seq)
        return OdometryMessage(replace(odom, robot_id=robot, seq=seq))
    except (ScanError, MessageError) as exc:
        raise invalid(("body",), str(exc)) from exc
