"""GET /robots: every robot seen on the bus, with its last pose and data times, and the services."""

from __future__ import annotations

import pytest
from scanflow import keys
from scanflow.wire import RetiredMessage, RetireMessage

from ..conftest import eventually, serve_retire


def test_no_robot_and_no_service_yet(client):
    assert client.get("/api/v1/robots").json() == {"robots": [], "services": []}


def test_robots_are_listed_in_id_order_with_their_last_pose(client, publish_poses):
    publish_poses("b", [(1.0, 0.0, 0.0, 0.0), (2.0, 3.0, 4.0, 0.5)])
    publish_poses("a", [(1.0, 1.0, 0.0, 0.0)])
    robots = client.get("/api/v1/robots").json()["robots"]
    assert [r["robot_id"] for r in robots] == ["a", "b"]
    b = robots[1]
    assert (b["last_pose"]["seq"], b["last_pose"]["x_m"], b["poses_cached"]) == (1, 3.0, 2)
    assert b["last_pose_received_s"] > 0 and b["last_scan_received_s"] is None
    assert (b["scans_seen"], b["map_revision"], b["restarts"]) == (0, None, 0)


def test_a_robot_posted_to_is_listed_with_its_scans(client, auth):
    scan = {"ranges_m": [1.0], "angle_min_rad": 0.0, "angle_increment_rad": 0.1}
    client.post("/api/v1/robots/posted/scans", json=scan, headers=auth)
    (robot,) = client.get("/api/v1/robots").json()["robots"]
    assert robot["robot_id"] == "posted" and robot["last_pose"] is None
    assert robot["scans_seen"] == 1 and robot["last_scan_received_s"] > 0


def test_live_services_are_listed(client, peer):
    peer.token(keys.health("matcher", "1"))
    peer.token(keys.health("deskew", "0"))
    eventually(lambda: len(client.get("/api/v1/robots").json()["services"]) == 2, "the tokens")
    services = client.get("/api/v1/robots").json()["services"]
    assert services == [{"service": "deskew", "instance": "0"},
                        {"service": "matcher", "instance": "1"}]


def test_a_robot_is_retired_from_each_service_in_the_datas_order_then_from_the_gateway(
    client, auth, peer, backend, publish_poses
):
    asked: list = []
    services = {"deskew": ["0"], "matcher": ["0", "1"], "mapserver": ["0"]}
    serve_retire(peer, backend, services, asked, {"map_revision": 7})
    publish_poses("r1", [(1.0, 0.0, 0.0, 0.0), (2.0, 1.0, 0.0, 0.0)])
    publish_poses("r2", [(1.0, 0.0, 0.0, 0.0)])
    r = client.delete("/api/v1/robots/r1", headers=auth)
    assert r.status_code == 200, r.text
    body = r.json()
    confirmed = [(s["service"], s["instance"]) for s in body["services"]]
    assert confirmed[0] == ("deskew", "0") and confirmed[-1] == ("mapserver", "0")
    assert sorted(confirmed[1:3]) == [("matcher", "0"), ("matcher", "1")]
    assert all(s["known"] and s["dropped"] == {"map_revision": 7} for s in body["services"])
    assert body["gateway"] == {"known": True, "dropped": {"poses_cached": 2, "scans_seen": 0}}
    assert [name.split("/")[0] for name, _ in asked] == [
        "deskew", "matcher", "matcher", "mapserver"]
    assert {request for _, request in asked} == {RetireMessage("r1")}
    robots = client.get("/api/v1/robots").json()["robots"]
    assert [r["robot_id"] for r in robots] == ["r2"]
    assert client.get("/api/v1/robots/r1/pose").status_code == 404


def test_a_robot_no_one_knew_is_404_and_a_bad_id_422_as_on_every_robot_route(
    client, auth, peer, backend
):
    class Unknown:  # every service answers: nothing held of it
        @staticmethod
        def answer(query):
            service = str(query.key_expr).split("/")[-1]
            return RetiredMessage("nobody", service, "0", False).encode()

    for service in ("deskew", "matcher", "mapserver"):
        peer.token(keys.health(service, "0"))
    peer.answer(keys.retire("*", "*"), Unknown.answer)
    eventually(lambda: len(backend.alive_services()) == 3, "the services' tokens")
    r = client.delete("/api/v1/robots/nobody", headers=auth)
    assert r.status_code == 404 and "'nobody' is unknown" in r.json()["detail"]
    for bad in ("stats", "a*b", "x" * 65):
        assert client.delete(f"/api/v1/robots/{bad}", headers=auth).status_code == 422
    assert client.delete("/api/v1/robots/nobody").status_code == 401


def test_without_a_running_map_server_nothing_is_retired_503(client, auth, peer, backend,
                                                             publish_poses):
    asked: list = []
    serve_retire(peer, backend, {"deskew": ["0"], "matcher": ["0"]}, asked)
    publish_poses("r1", [(1.0, 0.0, 0.0, 0.0)])
    r = client.delete("/api/v1/robots/r1", headers=auth)
    assert r.status_code == 503 and "no mapserver is running" in r.json()["detail"]
    assert asked == [] and backend.tracks.known("r1")


@pytest.mark.parametrize("silent", ["matcher/1", "mapserver/0"])
def test_a_service_alive_that_does_not_answer_is_504_naming_it_and_what_was_retired(
    client, auth, peer, backend, publish_poses, silent
):
    """matcher/1 holds a token but no queryable; mapserver/0 takes the query and never
    answers (the gateway's query times out). The retire stops there: the gateway keeps its
    own track, and asking again finishes it."""
    services = {"deskew": ["0"], "matcher": ["0"], "mapserver": ["0"]}
    if silent == "matcher/1":
        peer.token(keys.health("matcher", "1"))
        serve_retire(peer, backend, services)
        eventually(lambda: len(backend.alive_services()) == 4, "matcher/1's token")
    else:
        serve_retire(peer, backend, services, silent=silent)
    publish_poses("r1", [(1.0, 0.0, 0.0, 0.0)])
    r = client.delete("/api/v1/robots/r1", headers=auth)
    assert r.status_code == 504, r.text
    detail = r.json()["detail"]
    assert detail.startswith(f"{silent} is alive but did not answer the retire of robot 'r1'")
    assert "(retired from: deskew/0, matcher/0; ask again" in detail
    assert backend.tracks.known("r1")


@pytest.mark.parametrize(("error", "status"), [
    (RuntimeError("deskew/0 is busy: stopping"), 503),
    (OSError("deskew/0: [Errno 30] Read-only file system"), 502),
], ids=["busy", "failed"])
def test_an_error_answer_is_named_with_its_status(client, auth, peer, backend, error, status):
    def refuse(_query):
        raise error  # the peer answers "<type>: <text>", as the service shell does

    for service in ("deskew", "matcher", "mapserver"):
        peer.token(keys.health(service, "0"))
    peer.answer(keys.retire("*", "deskew"), refuse)
    eventually(lambda: len(backend.alive_services()) == 3, "the services' tokens")
    r = client.delete("/api/v1/robots/r1", headers=auth)
    detail = r.json()["detail"]
    assert r.status_code == status, r.text
    assert detail.startswith(f"deskew: {type(error).__name__}: {error}"), detail
