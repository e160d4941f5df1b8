"""POST /match: JSON and msgpack bodies forwarded to a (test) matcher queryable; methods list."""

from __future__ import annotations

import math

import msgpack
import numpy as np
import pytest
from scanflow import keys
from scanflow.geometry import Pose2D
from scanflow.matching import match
from scanflow.scan import LaserScan
from scanflow.wire import MapRef, MatchRequest, MatchResponse

SCAN = {
    "ranges_m": [2.0, 2.1, None, 2.3, 2.2, 2.0, 1.9, 2.0],
    "angle_min_rad": -1.57,
    "angle_increment_rad": 0.39,
    "range_max_m": 30.0,
}


MSGPACK = {"Content-Type": "application/x-msgpack"}


def echo_matcher(seen: list[MatchRequest]):
    """A matcher that answers with the request's initial guess and records the request."""

    def reply(query) -> bytes:
        request = MatchRequest.decode(query.payload.to_bytes())
        seen.append(request)
        guess = request.initial_guess or Pose2D()
        return MatchResponse(guess, np.eye(3) * 1e-3, 0.8, 7, True, "ok", request.method,
                             time_s=0.002, inliers=6).encode()

    return reply


def test_scan_to_scan_json(client, peer, auth):
    seen: list[MatchRequest] = []
    peer.answer(keys.scan_match(), echo_matcher(seen))
    body = {"method": "icp", "source": SCAN, "target": SCAN,
            "initial_guess": {"x_m": 0.5, "y_m": 0.25, "theta_rad": 0.1}}
    r = client.post("/api/v1/match", json=body, headers=auth)
    assert r.status_code == 200, r.text
    out = r.json()
    assert out["pose"] == pytest.approx({"x_m": 0.5, "y_m": 0.25, "theta_rad": 0.1})
    assert (out["iterations"], out["converged"], out["status"]) == (7, True, "ok")
    assert out["inliers"] == 6
    assert out["time_s"] == 0.002 and out["round_trip_s"] > 0
    (request,) = seen
    assert isinstance(request.source, LaserScan) and math.isnan(request.source.ranges_m[2])
    assert request.source.valid_count == 7


def test_a_scans_mount_travels_with_it(client, peer, auth):
    """The lidar's place on the robot reaches the matcher (omitted: the robot's origin)."""
    seen: list[MatchRequest] = []
    peer.answer(keys.scan_match(), echo_matcher(seen))
    mounted = {**SCAN, "mount": {"x_m": 0.3, "y_m": -0.1, "theta_rad": 0.5}}
    r = client.post("/api/v1/match", json={"source": mounted, "target": SCAN}, headers=auth)
    assert r.status_code == 200, r.text
    (request,) = seen
    assert request.source.mount == Pose2D(0.3, -0.1, 0.5)
    assert request.target.mount == Pose2D()


def test_without_a_method_the_advertised_default_is_used(client, peer, auth):
    seen: list[MatchRequest] = []
    peer.answer(keys.scan_match(), echo_matcher(seen))
    default = client.get("/api/v1/match/methods").json()["default"]
    r = client.post("/api/v1/match", json={"source": SCAN, "target": SCAN}, headers=auth)
    assert r.status_code == 200, r.text
    assert seen[0].method == default == r.json()["method"]


def test_scan_to_map_goes_to_the_robots_matcher(client, peer, auth):
    seen: list[MatchRequest] = []
    peer.answer(keys.robot_match("r1"), echo_matcher(seen))
    r = client.post("/api/v1/match", json={"method": "gn", "source": SCAN, "robot_id": "r1"},
                    headers=auth)
    assert r.status_code == 200, r.text
    assert isinstance(seen[0].target, MapRef) and seen[0].target.robot_id == "r1"


def test_scan_to_map_for_an_unknown_robot_is_404_for_a_known_one_503(client, auth,
                                                                        publish_poses):
    body = {"method": "gn", "source": SCAN, "robot_id": "nobody"}
    r = client.post("/api/v1/match", json=body, headers=auth)
    assert r.status_code == 404 and "'nobody' is unknown" in r.text
    publish_poses("seen", [(1.0, 0.0, 0.0, 0.0)])
    r = client.post("/api/v1/match", json={**body, "robot_id": "seen"}, headers=auth)
    assert r.status_code == 503  # known, but its matcher does not answer: not the client's fault


@pytest.mark.parametrize("robot_id", ["*", "**", "a/b", "$*", ".."])
def test_a_msgpack_map_target_that_is_no_robot_id_is_422_not_500(client, auth, robot_id):
    fields = msgpack.unpackb(MatchRequest("gn", np.zeros((5, 2)), MapRef("r1")).encode())
    fields["target"]["robot_id"] = robot_id
    r = client.post("/api/v1/match", content=msgpack.packb(fields), headers={**auth, **MSGPACK})
    assert r.status_code == 422 and "robot id" in r.text, r.text


def test_msgpack_body_and_answer(client, peer, auth):
    peer.answer(keys.scan_match(), echo_matcher([]))
    points = np.random.default_rng(0).normal(size=(20, 2))
    request = MatchRequest("svd", points, points + 0.1, Pose2D(0.1, 0.0, 0.0))
    r = client.post("/api/v1/match", content=request.encode(),
                    headers={**auth, **MSGPACK, "Accept": "application/x-msgpack"})
    assert r.status_code == 200 and r.headers["content-type"] == "application/x-msgpack"
    assert MatchResponse.decode(r.content).pose.x == pytest.approx(0.1)


def test_every_library_method_is_offered(client):
    from scanflow.matching import available_methods

    assert client.get("/api/v1/match/methods").json()["methods"] == available_methods()


@pytest.mark.parametrize(("headers", "status"), [({}, 401), ({"X-API-Key": "wrong"}, 403)])
def test_match_needs_the_api_key(client, headers, status):
    body = {"source": SCAN, "target": SCAN}
    assert client.post("/api/v1/match", json=body, headers=headers).status_code == status


@pytest.mark.parametrize(
    ("body", "field"),
    [
        ({"method": "nope", "source": SCAN, "target": SCAN}, "method"),
        ({"source": SCAN}, "target"),
        ({"source": {**SCAN, "ranges_m": [1.0] * 1025}, "target": SCAN}, "ranges_m"),
        ({"source": {**SCAN, "angle_increment_rad": 5.0}, "target": SCAN}, "angle_increment_rad"),
        ({"source": SCAN, "target": SCAN, "initial_guess": {"x_m": 1e9}}, "x_m"),
        ({"source": {**SCAN, "mount": {"theta_rad": "left"}}, "target": SCAN}, "mount"),
        ({"source": {**SCAN, "range_max_m": 0.05, "range_min_m": 0.1}, "target": SCAN},
         "range_max_m"),
    ],
)
def test_bad_bodies_get_422_naming_the_field(client, auth, body, field):
    r = client.post("/api/v1/match", json=body, headers=auth)
    assert r.status_code == 422
    assert field in r.text


@pytest.mark.parametrize(
    ("options", "named"),
    [({"no_such_option": 1}, "unknown option 'no_such_option'"),
     ({"max_iterations": 2.5}, "max_iterations")],
)
def test_bad_option_names_and_types_are_refused_before_the_bus(client, auth, options, named):
    """No matcher answers here: the gateway itself refuses (with msgpack too)."""
    body = {"method": "plicp", "source": SCAN, "target": SCAN, "options": options}
    r = client.post("/api/v1/match", json=body, headers=auth)
    assert r.status_code == 422 and named in r.text and "options" in r.text, r.text
    request = MatchRequest("plicp", np.ones((5, 2)), np.ones((5, 2)), options=options)
    r = client.post("/api/v1/match", content=request.encode(), headers={**auth, **MSGPACK})
    assert r.status_code == 422 and named in r.text, r.text


def test_no_matcher_is_503(client, auth):
    r = client.post("/api/v1/match", json={"source": SCAN, "target": SCAN}, headers=auth)
    assert r.status_code == 503 and "match" in r.json()["detail"]


def test_silent_matcher_is_504_not_a_hang(client, peer, auth):
    peer.answer(keys.scan_match(), lambda q: None)
    r = client.post("/api/v1/match", json={"source": SCAN, "target": SCAN}, headers=auth)
    assert r.status_code == 504 and "within" in r.json()["detail"]


def test_matcher_error_is_forwarded(client, peer, auth):
    peer.answer(keys.robot_match("r1"),
                lambda q: MatchResponse.from_error("no map for robot 'r1'", "gn").encode())
    r = client.post("/api/v1/match", json={"source": SCAN, "robot_id": "r1"}, headers=auth)
    assert r.status_code == 422 and "no map" in r.json()["detail"]


def _room_scan() -> dict:
    """180 beams in a 6 m x 4 m room, the sensor in its middle: enough for plicp to run."""
    angles = np.linspace(-math.pi / 2, math.pi / 2, 180)
    with np.errstate(divide="ignore"):
        ranges = np.minimum(3.0 / np.abs(np.cos(angles)), 2.0 / np.abs(np.sin(angles)))
    return {"ranges_m": ranges.tolist(), "angle_min_rad": float(angles[0]),
            "angle_increment_rad": float(angles[1] - angles[0]), "range_max_m": 30.0}


def library_matcher(query) -> bytes:
    """The matcher service's own answer (services.matcher.requests) over scans: the library's
    `match` runs on the request, its refusals become error replies."""
    from services.matcher.requests import answer

    return answer(MatchRequest.decode(query.payload.to_bytes()), lambda _robot_id: None).encode()


@pytest.mark.parametrize(
    ("options", "named"),
    [
        ({"max_step_m": 0}, "max_step_m must be > 0"),
        ({"max_iterations": -1}, "max_iterations must be >= 1"),
        ({"normal_neighbours": 1}, "normal_neighbours must be in [2, 64]"),
    ],
)
def test_an_option_out_of_its_range_is_a_422_naming_it(client, peer, auth, options, named):
    """Ranges are the method's: the matcher refuses, the gateway passes its reason on."""
    peer.answer(keys.scan_match(), library_matcher)
    room = _room_scan()
    # The library's plicp once before the gateway's 1 s query timeout runs: on a cold numba
    # cache (this file alone, a changed kernel) its first call compiles for seconds.
    points = LaserScan(**{**room, "ranges_m": np.asarray(room["ranges_m"])}).robot_points()
    assert match(points, points, Pose2D(), method="plicp").ok
    ok = client.post("/api/v1/match", json={"method": "plicp", "source": room, "target": room},
                     headers=auth)
    assert ok.status_code == 200 and ok.json()["status"] == "ok", ok.text
    body = {"method": "plicp", "source": room, "target": room, "options": options}
    r = client.post("/api/v1/match", json=body, headers=auth)
    assert r.status_code == 422, r.text
    assert named in r.text and "MatchInputError" in r.text
