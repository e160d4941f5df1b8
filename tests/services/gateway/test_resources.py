"""Maps, ingest, health, metrics and the live stream, against a real Zenoh peer."""

from __future__ import annotations

import io
import threading
import time
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import pytest
from PIL import Image
from scanflow import keys
from scanflow.config import GatewaySettings
from scanflow.geometry import Pose2D
from scanflow.maps.grid import GridSpec
from scanflow.scan import LaserScan, Odometry
from scanflow.wire import (
    MapImageMessage,
    MapMetaMessage,
    MapRegionMessage,
    OdometryMessage,
    ScanMessage,
    ServiceStatsMessage,
)

from .conftest import estimate, eventually

META = MapMetaMessage.from_spec("r1", GridSpec(-1.0, -2.0, 0.5, 4, 6), revision=3, stamp_s=5.0)


def test_map_meta_and_png(client, peer):
    png = io.BytesIO()
    Image.new("L", (6, 4), 254).save(png, format="PNG")
    peer.answer(keys.map_key("r1", "meta"), lambda q: META.encode())
    peer.answer(keys.map_key("r1", "image"), lambda q: MapImageMessage(
        "r1", 3, q.parameters.get("format"), png.getvalue()).encode())
    meta = client.get("/api/v1/robots/r1/map").json()
    assert (meta["rows"], meta["cols"], meta["width_m"], meta["revision"]) == (4, 6, 3.0, 3)
    r = client.get("/api/v1/robots/r1/map.png")
    assert r.headers["content-type"] == "image/png" and r.content == png.getvalue()
    assert r.headers["x-map-revision"] == "3"


def test_map_region_is_exported_by_the_library(client, peer):
    occupancy = np.full((2, 3), -1, np.int8)
    occupancy[0, 0] = 100
    occupancy[1, :] = 0
    seen = []

    def region(query):
        seen.append(dict(query.parameters))
        return MapRegionMessage(META, 1, 2, occupancy).encode()

    peer.answer(keys.map_key("r1", "region"), region)
    r = client.get("/api/v1/robots/r1/map.pgm", params={"x0": 0, "y0": -1.5, "x1": 1, "y1": -1})
    assert r.status_code == 200 and r.content.startswith(b"P5")
    assert seen[0] == {"x0": "0.0", "y0": "-1.5", "x1": "1.0", "y1": "-1.0"}
    yaml = client.get("/api/v1/robots/r1/map.yaml", params={"x0": 0, "y0": -1.5, "x1": 1, "y1": -1})
    assert "origin: [0.0, -1.5, 0.0]" in yaml.text and "resolution: 0.5" in yaml.text
    png = client.get("/api/v1/robots/r1/map.png", params={"x0": 0, "y0": -1.5, "x1": 1, "y1": -1})
    pixels = np.asarray(Image.open(io.BytesIO(png.content)))
    assert pixels.shape == (2, 3) and pixels[1, 0] == 0 and pixels[0, 2] == 254  # y up


def test_partial_region_and_missing_map(client, peer):
    r = client.get("/api/v1/robots/r1/map.png", params={"x0": 0})
    assert r.status_code == 422 and "x0, y0, x1, y1" in r.json()["detail"]
    peer.answer(keys.map_key("r9", "meta"), lambda q: (_ for _ in ()).throw(
        LookupError("no map for robot 'r9'")))
    r = client.get("/api/v1/robots/r9/map")
    assert r.status_code == 404 and "r9" in r.json()["detail"]


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


SCAN = {"ranges_m": [1.0, 2.0], "angle_min_rad": 0.0, "angle_increment_rad": 0.1}


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
    eventually(lambda: len(scans) >= 80, "every post on the bus", 30.0)
    assert [ScanMessage.decode(b).seq for b in scans] == list(range(80))


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
    assert client.post("/api/v1/robots/fed2/odometry", json=odom, headers=auth).json()["seq"] == 15


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


@pytest.mark.parametrize("settings", [GatewaySettings(api_key="test-key", max_robots=1)])
def test_ingest_for_a_robot_over_max_robots_is_refused(client, peer, auth):
    scans = peer.subscribe(keys.raw_scan("*"))
    assert client.post("/api/v1/robots/one/scans", json=SCAN, headers=auth).status_code == 202
    r = client.post("/api/v1/robots/two/scans", json=SCAN, headers=auth)
    assert r.status_code == 503 and "SCANFLOW_GATEWAY_MAX_ROBOTS" in r.json()["detail"]
    eventually(lambda: scans, "robot one's scan on the bus")
    assert [ScanMessage.decode(b).robot_id for b in scans] == ["one"]


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


def test_health_lists_liveliness_tokens(client, peer):
    body = client.get("/api/v1/health").json()
    assert body["status"] == "degraded" and "matcher" in body["missing"]
    assert body["zenoh"]["open"] and body["zenoh"]["peers"]
    for service in ("router", "deskew", "matcher", "mapserver"):
        peer.token(keys.health(service, "0"))
    eventually(lambda: client.get("/api/v1/health").json()["status"] == "ok", "all services up")


def test_metrics_aggregate_service_stats(client, peer, auth):
    stats = ServiceStatsMessage("deskew", "0", 1.0, {
        "received.scan": 12, "seq.r1/scan.missed": 2, "malformed.scan": 1, "queries.busy": 3,
    }, {"inbox_depth": 0.0, "limit": float("inf")})
    peer.answer(keys.stats("deskew", "0"), lambda q: stats.encode())
    client.get("/api/v1/robots")
    text = client.get("/metrics").text
    assert 'scanflow_scans_processed_total{instance="0",service="deskew"} 12' in text
    assert 'scanflow_seq_gaps_total{instance="0",service="deskew",stream="r1/scan"} 2' in text
    assert 'scanflow_malformed_total{instance="0",kind="scan",service="deskew"} 1' in text
    assert 'name="limit",service="deskew"} +Inf' in text
    assert 'scanflow_http_request_duration_seconds_count{method="GET",route="/api/v1/robots"' \
           in text
    assert text.count("# TYPE scanflow_service_gauge gauge") == 1


@pytest.mark.parametrize("path", ["/api/v1/robots/r1/poses/stream", "/api/v1/poses/stream"])
def test_stream_sends_live_poses(client, peer, backend, path):
    def publish_when_subscribed() -> None:
        eventually(lambda: backend.events.clients > 0, "the stream client")
        for seq in range(3):
            peer.put(keys.pose("r1"), estimate("r1", seq, 1.0 + seq, float(seq), 0.0).encode())

    thread = threading.Thread(target=publish_when_subscribed)
    thread.start()
    r = client.get(path, params={"limit": 3})
    thread.join()
    assert r.headers["content-type"].startswith("text/event-stream")
    events = [line for line in r.text.splitlines() if line.startswith("event:")]
    assert events == ["event: pose"] * 3
    assert '"x_m": 2.0' in r.text and '"robot_id": "r1"' in r.text


def test_guard_reads_puts_the_key_on_every_endpoint(backend, settings, auth):
    from fastapi.testclient import TestClient

    from services.gateway.app import create_app

    guarded = settings.model_copy(update={"guard_reads": True})
    with TestClient(create_app(guarded, backend)) as c:
        assert c.get("/api/v1/robots").status_code == 401
        assert c.get("/metrics").status_code == 401
        assert c.get("/api/v1/robots", headers=auth).status_code == 200
        operation = c.get("/openapi.json").json()["paths"]["/api/v1/robots"]["get"]
        assert operation["security"] == [{"APIKeyHeader": []}]
