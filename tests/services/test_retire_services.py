"""Retiring a robot across real processes through a real router: every service holds one robot
at most (SCANFLOW_<SERVICE>_MAX_ROBOTS=1), so a second robot is refused until the first is
retired over HTTP (DELETE /api/v1/robots/{robot}); then the second one is tracked and mapped."""

from __future__ import annotations

import httpx
import numpy as np
import pytest
from scanflow import keys
from scanflow.scan import LaserScan
from scanflow.wire import OdometryMessage, ScanMessage

from services.common.launch import free_port, wait_for_port
from services.ingest.sources import source_events

# `make test` runs it beside the rest (tools/run-tests.sh), with the container tests: balance.
pytestmark = [pytest.mark.integration, pytest.mark.slow, pytest.mark.second_lane]

ONE_ROBOT = {f"SCANFLOW_{name}_MAX_ROBOTS": "1"
             for name in ("DESKEW", "MATCHER", "MAPSERVER", "GATEWAY")}
MSGPACK = {"Content-Type": "application/x-msgpack"}


def post_run(http: httpx.Client, robot: str) -> int:
    """Post a simulated run of `robot` (odometry and scans, in order) to the gateway; the last
    scan's seq."""
    last = -1
    for event in source_events(None, robot, 2.0, 7, None):
        scan = isinstance(event, LaserScan)
        message = ScanMessage(event) if scan else OdometryMessage(event)
        r = http.post(f"/robots/{robot}/{'scans' if scan else 'odometry'}",
                      content=message.encode(), headers=MSGPACK)
        assert r.status_code == 202, r.text
        last = event.seq if scan else last
    return last


def tracked_and_mapped(bus, http: httpx.Client, robot: str, last_seq: int) -> None:
    """Wait until the gateway has the pose of the robot's last scan and the map server its map."""
    bus.wait_until(lambda: (r := http.get(f"/robots/{robot}/pose")).status_code == 200
                   and r.json()["seq"] == last_seq, 60.0, f"the pose of {robot}'s last scan")
    bus.wait_until(lambda: http.get(f"/robots/{robot}/map").status_code == 200, 30.0,
                   f"{robot}'s map")


def test_a_retired_robot_frees_every_services_place_for_another(launcher, bus, start, tmp_path):
    for name in ("deskew", "matcher", "mapserver"):
        start(name, SCANFLOW_DESKEW_ODOM_WAIT_S="3", SCANFLOW_MAPSERVER_SNAPSHOT_INTERVAL_S="0.2",
              **ONE_ROBOT)
    port = free_port()
    launcher.start("gateway", SCANFLOW_GATEWAY_PORT=str(port), **ONE_ROBOT)
    wait_for_port(port, 30.0)
    snapshot = tmp_path / "data" / "alpha.snapshot.npz"  # the launcher's data directory
    with httpx.Client(base_url=f"http://127.0.0.1:{port}/api/v1", timeout=30.0) as http:
        bus.wait_until(lambda: http.get("/health").json()["missing"] == [], 30.0,
                       "the gateway to see every service")
        tracked_and_mapped(bus, http, "alpha", post_run(http, "alpha"))
        bus.wait_until(snapshot.is_file, 30.0, "alpha's snapshot")

        # beta is refused: by the gateway over HTTP, by deskew on the bus.
        r = http.post("/robots/beta/scans", content=ScanMessage(LaserScan(
            np.ones(90), -np.pi, 0.07, robot_id="beta")).encode(), headers=MSGPACK)
        assert r.status_code == 503 and "refused" in r.json()["detail"], r.text
        bus.put(keys.raw_scan("beta"), ScanMessage(LaserScan(
            np.ones(90), -np.pi, 0.07, robot_id="beta")).encode())
        bus.wait_until(lambda: bus.stats("deskew").counters.get("robots_refused"), 30.0,
                       "deskew to refuse beta")

        r = http.delete("/robots/alpha")
        assert r.status_code == 200, r.text
        retired = r.json()
        confirmed = {s["service"]: s for s in retired["services"]}
        assert [s["service"] for s in retired["services"]] == ["deskew", "matcher", "mapserver"]
        assert all(s["known"] for s in retired["services"]) and retired["gateway"]["known"]
        assert confirmed["matcher"]["dropped"]["map_revision"] > 0
        mapserver = confirmed["mapserver"]["dropped"]
        assert mapserver["map_revision"] > 0 and mapserver["poses"] > 0
        assert mapserver["snapshot_files"] >= 1 and not snapshot.exists()
        assert [r["robot_id"] for r in http.get("/robots").json()["robots"]] == []
        assert http.get("/robots/alpha/map").status_code == 404
        assert http.get("/robots/alpha/pose").status_code == 404
        assert http.delete("/robots/alpha").status_code == 404  # gone everywhere

        tracked_and_mapped(bus, http, "beta", post_run(http, "beta"))
        robots = http.get("/robots").json()["robots"]
    assert [r["robot_id"] for r in robots] == ["beta"]
    for service in ("deskew", "matcher", "mapserver"):
        stats = bus.stats(service)
        assert stats.gauges["robots"] == 1, (service, stats.gauges)
        assert stats.counters.get("robots_retired") == 1, (service, stats.counters)
