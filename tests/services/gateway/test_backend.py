"""ZenohBackend: numbering posts past every source's seqs, bus subscriptions that count and
refuse bad or surplus messages."""

from __future__ import annotations

import threading
import time
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import pytest
from scanflow import keys
from scanflow.config import GatewaySettings
from scanflow.geometry import Pose2D
from scanflow.scan import LaserScan, Odometry
from scanflow.wire import OdometryMessage, ScanMessage, ServiceStatsMessage

from .conftest import INGEST_SCAN as SCAN
from .conftest import estimate, eventually, serve_retire


def test_concurrent_posts_reach_the_bus_in_the_order_of_their_seqs(peer, backend):
    """Posts on parallel connections: each is numbered and put before the next is numbered, so
    seq n never reaches the bus after n + 1 (every service would take n for a replay and start
    the robot's map afresh). Building the message takes a while here, as a body's check does."""
    scans = peer.subscribe(keys.raw_scan("par"))
    rng = np.random.default_rng(3)
    delays = iter(rng.uniform(0.0, 0.004, 80).tolist())
    lock = threading.Lock()

    def encode(seq: int) -> bytes:
        with lock:
            delay = next(delays)
        time.sleep(delay)
        return ScanMessage(LaserScan(np.ones(3, np.float32), 0.0, 0.1, robot_id="par",
                                     seq=seq)).encode()

    def post() -> int:
        return backend.publish_numbered("par", "scan", None, keys.raw_scan("par"), encode)

    with ThreadPoolExecutor(8) as pool:
        seqs = list(pool.map(lambda _: post(), range(80)))
    assert sorted(seqs) == list(range(80))
    try:
        eventually(lambda: len(scans) >= 80, "every post on the bus", 30.0)
    except AssertionError as exc:  # say which went missing (a CI run once saw fewer than 80)
        got = [ScanMessage.decode(b).seq for b in list(scans)]
        raise AssertionError(f"{exc}: {len(got)} of 80 arrived, in this order: {got}") from exc
    assert [ScanMessage.decode(b).seq for b in scans] == list(range(80))


def test_a_refused_put_is_a_503_and_its_seq_goes_to_the_next_post(client, peer, auth, backend):
    """Zenoh refuses a post's put (here: its publisher undeclared under it): the client gets a
    503 naming the key, the seq is not used up (the services would count a gap), and the next
    post goes out on a freshly declared publisher with that seq."""
    scans = peer.subscribe(keys.raw_scan("pf"))
    post = lambda: client.post("/api/v1/robots/pf/scans", json=SCAN, headers=auth)  # noqa: E731
    assert post().json()["seq"] == 0
    backend._publishers[keys.raw_scan("pf", backend.prefix)].undeclare()
    refused = post()
    assert refused.status_code == 503
    assert "could not publish on" in refused.json()["detail"] and "pf/scan/raw" in refused.text
    assert post().json()["seq"] == 1
    eventually(lambda: len(scans) >= 2, "both scans that went out on the bus")
    assert [ScanMessage.decode(b).seq for b in scans] == [0, 1]
    metrics = client.get("/metrics").text
    assert "scanflow_gateway_publish_failed_total 1" in metrics


def test_numbering_follows_the_scans_and_odometry_other_sources_put(client, peer, auth,
                                                                    backend):
    """Another source (a robot's own Zenoh client) feeds the robot: the gateway numbers past
    what it sees on the bus, and refuses a seq behind it."""
    for seq in range(4):
        scan = LaserScan(np.ones(3, np.float32), 0.0, 0.1, robot_id="fed2", seq=seq)
        peer.put(keys.raw_scan("fed2"), ScanMessage(scan).encode())
        odom = Odometry(float(seq), Pose2D(), None, "fed2", 10 + seq)
        peer.put(keys.odom("fed2"), OdometryMessage(odom).encode())
    eventually(lambda: backend.tracks.next_seq("fed2", "odom", None) == 14, "the odometry seen")
    eventually(lambda: [r["scans_seen"] for r in client.get("/api/v1/robots").json()["robots"]
                        if r["robot_id"] == "fed2"] == [4], "the scans seen")
    assert client.post("/api/v1/robots/fed2/scans", json=SCAN, headers=auth).json()["seq"] == 4
    r = client.post("/api/v1/robots/fed2/scans", json={**SCAN, "seq": 2}, headers=auth)
    assert r.status_code == 409 and "its last is 4" in r.json()["detail"]
    odom = {"stamp_s": 9.0, "pose": {"x_m": 1.0}}
    assert client.post("/api/v1/robots/fed2/odometry", json=odom, headers=auth).json()["seq"] == 14


@pytest.mark.parametrize("settings", [GatewaySettings(api_key="test-key", query_timeout_s=10.0)])
def test_a_restarted_gateway_numbers_past_what_the_services_saw_before_it(client, peer, auth):
    """The gateway restarted: it has seen none of the robot's scans, odometry or poses yet. It
    asks the services' stats for the streams' last seqs rather than start from 0 again (an
    audit saw acks 58, 59, then 0 after a restart, and the robot's map wiped everywhere)."""
    gauges = {
        "deskew": {"seq.r7/scan.last": 57.0, "seq.r7/odom.last": 299.0},
        "mapserver": {"seq.r7/pose.last": 59.0, "seq.r8/pose.last": 4.0},
    }
    for service, values in gauges.items():
        stats = ServiceStatsMessage(service, "0", 1.0, {}, values)
        peer.answer(keys.stats(service, "0"), lambda q, stats=stats: stats.encode())
    post = lambda what, body: client.post(  # noqa: E731
        f"/api/v1/robots/r7/{what}", json=body, headers=auth)
    odom = {"stamp_s": 1.0, "pose": {"x_m": 1.0}}
    assert post("scans", SCAN).json()["seq"] == 60
    assert post("odometry", odom).json()["seq"] == 300
    r = post("scans", {**SCAN, "seq": 59})
    assert r.status_code == 409 and "its last is 60" in r.json()["detail"]
    assert client.post("/api/v1/robots/new/scans", json=SCAN, headers=auth).json()["seq"] == 0


def test_malformed_scans_on_the_bus_are_counted_and_logged_sparingly(client, peer, backend,
                                                                     caplog):
    """The gateway reads every raw scan: a faulty source's stream is counted in full but
    logged only at first, then every 100th, as the services do."""
    caplog.set_level("WARNING", logger="scanflow.gateway")
    for _ in range(15):
        peer.put(keys.raw_scan("bad"), b"not msgpack")
    eventually(lambda: 'scanflow_gateway_malformed_total{kind="scan"} 15'
               in client.get("/metrics").text, "15 malformed scans counted")
    logged = [r.getMessage() for r in caplog.records if "malformed scan" in r.getMessage()]
    assert len(logged) == 10 and logged[0].startswith("malformed scan #1 on ")


def test_a_pose_on_another_robots_key_is_refused(client, peer, backend, publish_poses):
    publish_poses("victim", [(1.0, 0.0, 0.0, 0.0), (2.0, 0.1, 0.0, 0.0)], seq0=30)
    peer.put(keys.pose("other"), estimate("victim", 0, 3.0, 5.0, 5.0, 0.0).encode())
    eventually(lambda: "scanflow_gateway_malformed_total" in client.get("/metrics").text,
               "the refused pose counted")
    assert 'kind="pose"' in client.get("/metrics").text
    assert backend.tracks.latest("victim").seq == 31  # its cache kept, not reset by seq 0
    assert backend.tracks.latest("other") is None


@pytest.mark.parametrize("settings", [GatewaySettings(api_key="k", max_robots=2)])
def test_poses_of_more_robots_than_max_robots_are_dropped_and_counted(client, peer, backend,
                                                                     publish_poses):
    publish_poses("one", [(1.0, 0.0, 0.0, 0.0)])
    publish_poses("two", [(1.0, 0.0, 0.0, 0.0)])
    for seq in range(3):
        peer.put(keys.pose("three"), estimate("three", seq, 1.0 + seq, 0.0, 0.0, 0.0).encode())
    eventually(lambda: "scanflow_gateway_robots_refused_total 3" in client.get("/metrics").text,
               "three refused poses counted")
    assert not backend.tracks.known("three")
    assert client.get("/api/v1/robots/three/pose").status_code == 404
    publish_poses("one", [(2.0, 0.1, 0.0, 0.0)], seq0=1)  # the known ones go on
    assert [r["robot_id"] for r in client.get("/api/v1/robots").json()["robots"]] == ["one", "two"]


@pytest.mark.parametrize("settings", [GatewaySettings(api_key="k", max_robots=1)])
def test_a_retired_robot_frees_the_gateways_place_and_its_posts_start_afresh(
    client, peer, backend
):
    """SCANFLOW_GATEWAY_MAX_ROBOTS=1: a second robot's post is refused until the first is
    retired; the retire drops the first's track and publishers, and its next post is numbered
    from 0, a new robot's run (the services, which retired it too, report no seq of it)."""
    serve_retire(peer, backend, {"deskew": ["0"], "matcher": ["0"], "mapserver": ["0"]})
    auth = {"X-API-Key": "k"}
    post = lambda robot, body: client.post(  # noqa: E731
        f"/api/v1/robots/{robot}/scans", json=body, headers=auth)
    assert post("one", SCAN).json()["seq"] == 0
    assert post("one", SCAN).json()["seq"] == 1
    assert post("two", SCAN).status_code == 503
    assert keys.raw_scan("one", backend.prefix) in backend._publishers
    r = client.delete("/api/v1/robots/one", headers=auth)
    assert r.status_code == 200 and r.json()["gateway"]["dropped"]["scans_seen"] == 2
    assert keys.raw_scan("one", backend.prefix) not in backend._publishers
    assert post("two", SCAN).json()["seq"] == 0
    assert client.delete("/api/v1/robots/two", headers=auth).status_code == 200
    assert post("one", SCAN).json()["seq"] == 0
