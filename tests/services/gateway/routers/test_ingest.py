"""POST /robots/{robot}/scans and /odometry: published on the bus, numbered, refused with 409,
422 or 503 and guarded by the API key."""

from __future__ import annotations

import numpy as np
import pytest
from scanflow import keys
from scanflow.config import GatewaySettings
from scanflow.scan import LaserScan
from scanflow.wire import OdometryMessage, ScanMessage

from ..conftest import INGEST_SCAN as SCAN
from ..conftest import eventually


def test_ingest_scan_and_odometry_publish_with_seqs(client, peer, auth):
    scans = peer.subscribe(keys.raw_scan("r1"))
    odoms = peer.subscribe(keys.odom("r1"))
    scan = {"ranges_m": [1.0, None, 2.0], "angle_min_rad": 0.0, "angle_increment_rad": 0.1}
    acks = [client.post("/api/v1/robots/r1/scans", json=scan, headers=auth) for _ in range(2)]
    assert [a.status_code for a in acks] == [202, 202]
    assert [a.json()["seq"] for a in acks] == [0, 1]
    odom = {"stamp_s": 3.0, "pose": {"x_m": 1.0}, "velocity": {"vx_mps": 0.5}, "seq": 7}
    assert client.post("/api/v1/robots/r1/odometry", json=odom, headers=auth).json()["seq"] == 7
    eventually(lambda: len(scans) == 2 and len(odoms) == 1, "ingested messages on the bus")
    got = [ScanMessage.decode(b).scan for b in scans]
    assert [(s.robot_id, s.seq, s.valid_count) for s in got] == [("r1", 0, 2), ("r1", 1, 2)]
    sample = OdometryMessage.decode(odoms[0]).odom
    assert (sample.seq, sample.pose.x, sample.velocity) == (7, 1.0, (0.5, 0.0, 0.0))


def test_a_scan_without_seq_follows_the_robots_last_pose(client, peer, auth, publish_poses):
    """Numbered from 0, a scan for a robot another source feeds would restart its stream (the
    services would start its map afresh)."""
    publish_poses("fed", [(1.0, 0.0, 0.0, 0.0), (2.0, 0.1, 0.0, 0.0)], seq0=40)
    scan = {"ranges_m": [1.0, 2.0], "angle_min_rad": 0.0, "angle_increment_rad": 0.1}
    acks = [client.post("/api/v1/robots/fed/scans", json=scan, headers=auth) for _ in range(2)]
    assert [a.json()["seq"] for a in acks] == [42, 43]


def test_a_seq_that_would_restart_the_map_is_refused(client, peer, auth):
    """A retried or reordered request with a seq at or below the stream's last would read, in
    every service, as a replay and start the robot's map afresh: 409, and nothing published.
    Seq 0 starts a new run on purpose; a request refused for its body takes no seq."""
    scans = peer.subscribe(keys.raw_scan("r5"))
    post = lambda seq, **extra: client.post(  # noqa: E731
        "/api/v1/robots/r5/scans", json={**SCAN, **extra, "seq": seq}, headers=auth)
    assert [post(s).status_code for s in (3, 4)] == [202, 202]
    for stale in (4, 2):
        r = post(stale)
        assert r.status_code == 409, r.text
        assert f"seq {stale} does not move the scan stream of robot 'r5'" in r.json()["detail"]
        assert "its last is 4" in r.json()["detail"]
    assert post(5, range_min_m=9.0, range_max_m=1.0).status_code == 422
    assert post(5).status_code == 202  # the corrected request keeps its seq
    assert post(0).status_code == 202  # a new run, then numbered from it
    assert client.post("/api/v1/robots/r5/scans", json=SCAN, headers=auth).json()["seq"] == 1
    eventually(lambda: len(scans) == 5, "the accepted scans on the bus")
    assert [ScanMessage.decode(b).seq for b in scans] == [3, 4, 5, 0, 1]
    odom = {"stamp_s": 1.0, "pose": {"x_m": 1.0}, "seq": 7}
    url = "/api/v1/robots/r5/odometry"
    assert client.post(url, json=odom, headers=auth).status_code == 202
    r = client.post(url, json=odom, headers=auth)
    assert r.status_code == 409 and "the odom stream of robot 'r5'" in r.json()["detail"]


@pytest.mark.parametrize("settings", [GatewaySettings(api_key="test-key", max_robots=1)])
def test_ingest_for_a_robot_over_max_robots_is_refused(client, peer, auth):
    scans = peer.subscribe(keys.raw_scan("*"))
    assert client.post("/api/v1/robots/one/scans", json=SCAN, headers=auth).status_code == 202
    r = client.post("/api/v1/robots/two/scans", json=SCAN, headers=auth)
    assert r.status_code == 503 and "SCANFLOW_GATEWAY_MAX_ROBOTS" in r.json()["detail"]
    eventually(lambda: scans, "robot one's scan on the bus")
    assert [ScanMessage.decode(b).robot_id for b in scans] == ["one"]


def test_ingest_msgpack_is_retagged_to_the_url_robot(client, peer, auth):
    scans = peer.subscribe(keys.raw_scan("r2"))
    message = ScanMessage(LaserScan(np.ones(5, np.float32), 0.0, 0.1, robot_id="other", seq=4))
    r = client.post("/api/v1/robots/r2/scans", content=message.encode(),
                    headers={**auth, "Content-Type": "application/x-msgpack"})
    assert r.status_code == 202 and r.json()["seq"] == 4
    eventually(lambda: scans, "the scan on the bus")
    assert ScanMessage.decode(scans[0]).scan.robot_id == "r2"


def test_ingest_needs_the_key(client):
    assert client.post("/api/v1/robots/r1/odometry", json={}).status_code == 401
