"""GET /robots: every robot seen on the bus, with its last pose and data times, and the services."""

from __future__ import annotations

from scanflow import keys

from ..conftest import eventually


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
