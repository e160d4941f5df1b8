"""POST /robots/{robot}/scans and /odometry: publish on the bus for clients without Zenoh."""

from __future__ import annotations

from dataclasses import replace

from fastapi import APIRouter, Depends, Request
from scanflow import keys
from scanflow.scan import LaserScan, Odometry, ScanError
from scanflow.wire import MessageError, OdometryMessage, ScanMessage

from services.gateway.body import body_doc, invalid, read_body
from services.gateway.deps import API_PREFIX, Backend, Robot, Settings, require_key
from services.gateway.models import IngestAck, OdometryIn, ScanIn
from services.gateway.routers.match import ANSWERS

router = APIRouter(prefix=API_PREFIX, tags=["ingest"], dependencies=[Depends(require_key)])


@router.post(
    "/robots/{robot}/scans", response_model=IngestAck, status_code=202, responses=ANSWERS,
    openapi_extra=body_doc(ScanIn, ScanMessage, "one scan (seq optional)"),
    summary="Publish a scan on the robot's raw scan key",
)
async def post_scan(
    request: Request, robot: Robot, backend: Backend, settings: Settings
) -> IngestAck:
    body = await read_body(request, ScanIn, ScanMessage)
    given = body.scan.seq if isinstance(body, ScanMessage) else body.seq
    seq = backend.next_seq(robot, "scan", given)
    try:
        scan = body.scan if isinstance(body, ScanMessage) else body.to_scan(robot, seq)
        if scan.beam_count > settings.max_beams:
            raise invalid(("body", "ranges_m"),
                          f"{scan.beam_count} beams, over max_beams={settings.max_beams}")
        message = ScanMessage(_retag_scan(scan, robot, seq))
    except (ScanError, MessageError) as exc:
        raise invalid(("body",), str(exc)) from exc
    key = keys.raw_scan(robot, backend.prefix)
    await backend.apublish(key, message.encode())
    backend.metrics.count("scanflow_gateway_ingested_total", kind="scan")
    return IngestAck(robot_id=robot, seq=seq, key=key)


@router.post(
    "/robots/{robot}/odometry", response_model=IngestAck, status_code=202, responses=ANSWERS,
    openapi_extra=body_doc(OdometryIn, OdometryMessage, "one odometry sample (seq optional)"),
    summary="Publish an odometry sample on the robot's odom key",
)
async def post_odometry(request: Request, robot: Robot, backend: Backend) -> IngestAck:
    body = await read_body(request, OdometryIn, OdometryMessage)
    given = body.odom.seq if isinstance(body, OdometryMessage) else body.seq
    seq = backend.next_seq(robot, "odom", given)
    try:
        odom = body.odom if isinstance(body, OdometryMessage) else body.to_odometry(robot, seq)
        message = OdometryMessage(Odometry(odom.stamp_s, odom.pose, odom.velocity, robot, seq))
    except (ScanError, MessageError) as exc:
        raise invalid(("body",), str(exc)) from exc
    key = keys.odom(robot, backend.prefix)
    await backend.apublish(key, message.encode())
    backend.metrics.count("scanflow_gateway_ingested_total", kind="odom")
    return IngestAck(robot_id=robot, seq=seq, key=key)


def _retag_scan(scan: LaserScan, robot: str, seq: int) -> LaserScan:
    """The scan under the path's robot id and the published seq (the URL is authoritative)."""
    if scan.robot_id == robot and scan.seq == seq:
        return scan
    return replace(scan, robot_id=robot, seq=seq)
