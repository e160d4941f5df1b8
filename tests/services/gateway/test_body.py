"""body.py: JSON or msgpack request bodies, 415 for any other type, 422 naming the field."""

from __future__ import annotations

import asyncio

import msgpack
import pytest
from fastapi import HTTPException
from fastapi.exceptions import RequestValidationError
from scanflow.geometry import Pose2D
from scanflow.scan import Odometry
from scanflow.wire import SCHEMA_VERSION, OdometryMessage
from starlette.requests import Request

from services.gateway.body import (
    JSON,
    body_doc,
    content_type,
    invalid,
    read_body,
)
from services.gateway.body import MSGPACK as MSGPACK_TYPE
from services.gateway.models import OdometryIn

MSGPACK = {"Content-Type": "application/x-msgpack"}


def request(body: bytes = b"", kind: str | None = None) -> Request:
    """A POST request carrying `body` with Content-Type `kind` (none: no header)."""
    headers = [] if kind is None else [(b"content-type", kind.encode())]
    sent = [{"type": "http.request", "body": body, "more_body": False}]

    async def receive() -> dict:
        return sent.pop(0)

    return Request({"type": "http", "method": "POST", "headers": headers}, receive)


def read(body: bytes, kind: str | None) -> OdometryIn | OdometryMessage:
    return asyncio.run(read_body(request(body, kind), OdometryIn, OdometryMessage))


@pytest.mark.parametrize(
    ("header", "kind"),
    [(None, JSON), ("application/json; charset=utf-8", JSON),
     ("Application/X-Msgpack", MSGPACK_TYPE), (" text/plain ;q=1", "text/plain")],
)
def test_the_content_type_is_the_bare_lowercased_media_type(header, kind):
    assert content_type(request(kind=header)) == kind


def test_json_is_validated_by_the_model():
    body = read(b'{"stamp_s": 2.0, "pose": {"x_m": 1.0}}', None)
    assert isinstance(body, OdometryIn) and body.pose.x_m == 1.0


def test_a_bad_json_body_is_a_validation_error_located_in_the_body():
    with pytest.raises(RequestValidationError) as info:
        read(b'{"stamp_s": "soon", "pose": {}}', JSON)
    (error,) = info.value.errors()
    assert error["loc"] == ("body", "stamp_s") and "url" not in error


def test_msgpack_is_decoded_as_the_wire_message():
    sample = OdometryMessage(Odometry(2.0, Pose2D(1.0, 0.0, 0.0), None, "r1", 3))
    body = read(sample.encode(), f"{MSGPACK_TYPE}; v=1")
    assert isinstance(body, OdometryMessage) and body.odom.seq == 3


def test_bad_msgpack_is_a_422_naming_the_message_type():
    with pytest.raises(HTTPException) as info:
        read(b"\xc1", MSGPACK_TYPE)
    assert info.value.status_code == 422 and OdometryMessage.TYPE in info.value.detail


def test_any_other_content_type_is_a_415_naming_the_accepted_ones():
    with pytest.raises(HTTPException) as info:
        read(b"stamp_s=1", "application/x-www-form-urlencoded")
    assert info.value.status_code == 415
    assert JSON in info.value.detail and MSGPACK_TYPE in info.value.detail


def test_invalid_is_a_422_in_fastapis_format():
    error = invalid(("body", "ranges_m"), "too many beams")
    assert error.errors() == [
        {"loc": ("body", "ranges_m"), "msg": "too many beams", "type": "value_error"}
    ]


def test_the_body_doc_lists_both_encodings():
    doc = body_doc(OdometryIn, OdometryMessage, "one sample")["requestBody"]
    assert doc["required"] is True and doc["description"] == "one sample"
    assert doc["content"][JSON]["schema"] == {"$ref": "#/components/schemas/OdometryIn"}
    binary = doc["content"][MSGPACK_TYPE]["schema"]
    assert binary["format"] == "binary" and OdometryMessage.TYPE in binary["description"]

def test_bad_msgpack_gets_422(client, auth):
    payload = msgpack.packb({"type": "match_request", "v": SCHEMA_VERSION})
    r = client.post("/api/v1/match", content=payload, headers={**auth, **MSGPACK})
    assert r.status_code == 422 and "method" in r.json()["detail"]


def test_other_content_types_are_415(client, auth):
    r = client.post("/api/v1/match", content=b"x", headers={**auth, "Content-Type": "text/plain"})
    assert r.status_code == 415
