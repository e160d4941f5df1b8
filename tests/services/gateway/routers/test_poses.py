"""Pose queries: latest, interpolated at t, trajectory (cache and map server), TUM text; an
operator's pose PUT to the tracker."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
from scanflow import keys
from scanflow.geometry import Pose2D
from scanflow.wire import InitialPoseMessage, TrajectoryMessage

from services.common.robots import RobotLimitError

from ..conftest import estimate, eventually, off_the_loop


def test_latest_pose_comes_from_the_bus(client, publish_poses):
    publish_poses("r1", [(10.0, 0.0, 0.0, 0.0), (11.0, 1.0, 2.0, 0.5)])
    body = client.get("/api/v1/robots/r1/pose").json()
    assert (body["seq"], body["x_m"], body["y_m"], body["theta_rad"]) == (1, 1.0, 2.0, 0.5)
    assert body["covariance"][0][0] == pytest.approx(1e-4)
    assert body["status"] == "ok" and body["interpolated"] is False


def test_unknown_robot_is_404_naming_it(client, peer):
    r = client.get("/api/v1/robots/nobody/pose")  # no map server to ask either
    assert r.status_code == 404 and "nobody" in r.json()["detail"]
    peer.answer(keys.trajectory("*"), lambda q: TrajectoryMessage(
        "empty", np.zeros(0), np.zeros((0, 3))).encode())  # a map server with no pose of it
    for t in (None, 1.0):
        r = client.get("/api/v1/robots/nobody/pose", params={} if t is None else {"t": t})
        assert r.status_code == 404 and "nobody" in r.json()["detail"]


def test_a_robot_this_gateway_has_not_seen_is_answered_from_the_map_servers_path(client, peer):
    """A gateway started or restarted after the robot's last pose (a run that ended) has no
    pose of it cached: its latest pose and a pose at t come from the map server's trajectory."""
    stamps = np.array([0.0, 2.0, 10.0])
    poses = np.array([[0.0, 0.0, 0.0], [2.0, 0.0, 0.0], [5.0, 1.0, 0.5]])
    peer.answer(keys.trajectory("r4"), lambda q: TrajectoryMessage("r4", stamps, poses).encode())
    body = client.get("/api/v1/robots/r4/pose").json()
    assert (body["stamp_s"], body["x_m"], body["y_m"], body["theta_rad"]) == (10.0, 5.0, 1.0, 0.5)
    assert body["seq"] is None and body["status"] == "trajectory"
    assert body["interpolated"] is False and body["message"].startswith("the last pose of")
    body = client.get("/api/v1/robots/r4/pose", params={"t": 1.0}).json()
    assert body["x_m"] == pytest.approx(1.0) and body["interpolated"] is True
    assert client.get("/api/v1/robots/r4/pose", params={"t": 11.0}).status_code == 404


def test_pose_at_time_interpolates_in_se2(client, publish_poses):
    publish_poses("r1", [(10.0, 0.0, 0.0, 3.0), (12.0, 2.0, -2.0, -3.0)])
    body = client.get("/api/v1/robots/r1/pose", params={"t": 11.5}).json()
    assert body["interpolated"] is True and body["stamp_s"] == 11.5
    assert (body["x_m"], body["y_m"]) == pytest.approx((1.5, -1.5))
    # the short way across +-pi: 3.0 -> -3.0 passes through pi, not through 0
    expected = math.remainder(3.0 + 0.75 * (2 * math.pi - 6.0), 2 * math.pi)
    assert body["theta_rad"] == pytest.approx(expected)


def test_pose_outside_the_trajectory_is_404(client, publish_poses):
    publish_poses("r1", [(10.0, 0.0, 0.0, 0.0), (12.0, 2.0, 0.0, 0.0)])
    assert client.get("/api/v1/robots/r1/pose", params={"t": 13.0}).status_code == 404
    # before the cache, with no map server to ask: 503 says why
    r = client.get("/api/v1/robots/r1/pose", params={"t": 1.0})
    assert r.status_code == 503 and "trajectory" in r.json()["detail"]


def test_trajectory_falls_back_to_the_cache_and_filters(client, publish_poses):
    publish_poses("r1", [(float(t), float(t), 0.0, 0.0) for t in range(5)])
    body = client.get("/api/v1/robots/r1/trajectory", params={"start": 1, "end": 3}).json()
    assert body["source"] == "cache"
    assert [p["stamp_s"] for p in body["poses"]] == [1.0, 2.0, 3.0]


def test_trajectory_from_the_map_server_in_tum(client, peer):
    # epoch stamps keep their fractions of a second (evo pairs poses by stamp)
    stamps = np.array([1_700_000_000.125, 1_700_000_000.25])
    poses = np.array([[0.0, 0.0, 0.0], [1.0, 2.0, math.pi / 2]])
    peer.answer(keys.trajectory("r2"), lambda q: TrajectoryMessage("r2", stamps, poses).encode())
    r = client.get("/api/v1/robots/r2/trajectory", params={"format": "tum"})
    assert r.status_code == 200 and r.headers["x-scanflow-source"] == "mapserver"
    rows = [list(map(float, line.split())) for line in r.text.splitlines()]
    assert len(rows) == 2 and all(len(row) == 8 for row in rows)
    s, x, y, z, qx, qy, qz, qw = rows[1]
    assert rows[0][0] == 1_700_000_000.125
    assert (s, x, y, z, qx, qy) == (1_700_000_000.25, 1.0, 2.0, 0.0, 0.0, 0.0)
    assert (qz, qw) == pytest.approx((math.sin(math.pi / 4), math.cos(math.pi / 4)))


def test_pose_before_the_cache_uses_the_map_server(client, peer, publish_poses):
    publish_poses("r3", [(10.0, 5.0, 0.0, 0.0)])
    stamps = np.array([0.0, 2.0, 10.0])
    poses = np.array([[0.0, 0.0, 0.0], [2.0, 0.0, 0.0], [5.0, 0.0, 0.0]])
    peer.answer(keys.trajectory("r3"), lambda q: TrajectoryMessage("r3", stamps, poses).encode())
    body = client.get("/api/v1/robots/r3/pose", params={"t": 1.0}).json()
    assert body["x_m"] == pytest.approx(1.0) and body["status"] == "trajectory"


def test_an_operators_pose_reaches_the_tracker_and_comes_back_as_taken(client, peer, auth):
    seen: list[InitialPoseMessage] = []

    def tracker(query) -> bytes:
        seen.append(InitialPoseMessage.decode(query.payload.to_bytes()))
        return query.payload.to_bytes()

    peer.answer(keys.initial_pose("r1"), tracker)
    pose = {"x_m": 2.5, "y_m": -1.0, "theta_rad": 0.4}
    r = client.put("/api/v1/robots/r1/pose", json=pose, headers=auth)
    assert r.status_code == 200, r.text
    assert r.json() == pytest.approx(pose)
    (message,) = seen
    assert message.robot_id == "r1"
    assert message.pose.to_array() == pytest.approx([2.5, -1.0, 0.4])


def test_an_operators_pose_needs_the_key_a_tracker_and_a_valid_body(client, auth):
    pose = {"x_m": 1.0, "y_m": 0.0, "theta_rad": 0.0}
    assert client.put("/api/v1/robots/r1/pose", json=pose).status_code == 401
    r = client.put("/api/v1/robots/nobody/pose", json=pose, headers=auth)
    assert r.status_code == 503 and "initial_pose" in r.json()["detail"]
    r = client.put("/api/v1/robots/r1/pose", json={"x_m": "far"}, headers=auth)
    assert r.status_code == 422 and "x_m" in r.text


def test_an_operators_pose_for_a_robot_over_the_matchers_limit_is_a_503(client, peer, auth):
    def full(_query) -> bytes:
        raise RobotLimitError("robot 'r2' refused: this matcher keeps 1 robots already")

    peer.answer(keys.initial_pose("r2"), full)
    r = client.put("/api/v1/robots/r2/pose", json={"x_m": 1.0, "y_m": 0.0, "theta_rad": 0.0},
                   headers=auth)
    assert r.status_code == 503 and "robot 'r2' refused" in r.json()["detail"]


def test_a_map_redraw_drops_the_cached_poses_of_the_old_frame(client, peer, publish_poses):
    """Loop closure redrew the map at seq 3: poses before it are answered from the map
    server's corrected path, not from the cache's old-frame estimates."""
    publish_poses("r4", [(10.0 + k, float(k), 0.0, 0.0) for k in range(3)])
    redrawn = replace(estimate("r4", 3, 13.0, 3.5, 0.0), correction=Pose2D(0.5, 0.0, 0.0))
    peer.put(keys.pose("r4"), redrawn.encode())
    eventually(lambda: client.get("/api/v1/robots/r4/pose").json()["seq"] == 3, "the redraw")
    latest = client.get("/api/v1/robots/r4/pose").json()
    assert latest["map_correction"] == {"x_m": 0.5, "y_m": 0.0, "theta_rad": 0.0}
    stamps = np.array([10.0, 11.0, 12.0, 13.0])
    poses = np.array([[k + 0.5, 0.0, 0.0] for k in range(4)])
    peer.answer(keys.trajectory("r4"), lambda q: TrajectoryMessage("r4", stamps, poses).encode())
    body = client.get("/api/v1/robots/r4/pose", params={"t": 11.5}).json()
    assert body["status"] == "trajectory" and body["x_m"] == pytest.approx(2.0)
    robots = client.get("/api/v1/robots").json()["robots"]
    (r4,) = [r for r in robots if r["robot_id"] == "r4"]
    assert r4["poses_cached"] == 1 and r4["restarts"] == 0


@pytest.mark.parametrize("fmt", ["json", "tum"])
def test_a_trajectory_is_written_off_the_event_loop(client, peer, monkeypatch, fmt):
    """A day's path is 10^5 poses or more: its JSON or TUM text, written on the event loop,
    held up every other request for a second."""
    calls = off_the_loop(monkeypatch, "services.gateway.routers.poses._written")
    n = 1000
    path = TrajectoryMessage("r1", np.arange(n) * 0.1, np.zeros((n, 3))).encode()
    peer.answer(keys.trajectory("r1"), lambda q: path)
    r = client.get(f"/api/v1/robots/r1/trajectory?format={fmt}")
    assert r.status_code == 200
    assert len(r.json()["poses"] if fmt == "json" else r.text.splitlines()) == n
    assert calls == [True]
