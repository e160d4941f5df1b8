"""The gateway process against the real router and map server processes."""

from __future__ import annotations

import io

import httpx
import numpy as np
import pytest
from PIL import Image
from scanflow import keys
from scanflow.geometry import Pose2D
from scanflow.wire import MapInsertMessage

from services.common.launch import free_port, wait_for_port

from .conftest import estimate, eventually

pytestmark = [pytest.mark.integration, pytest.mark.slow]


def test_gateway_serves_the_map_servers_map_and_trajectory(launcher, start, bus):
    start("mapserver", SCANFLOW_MAPSERVER_CHANGED_RATE_HZ="20")
    port = free_port()
    launcher.start("gateway", SCANFLOW_GATEWAY_PORT=str(port))
    wait_for_port(port, 30.0)
    angles = np.linspace(-np.pi, np.pi, 90, endpoint=False)
    points = np.column_stack((3 * np.cos(angles), 3 * np.sin(angles)))
    for seq in range(5):
        at = Pose2D(0.1 * seq, 0.0, 0.0)
        scan = MapInsertMessage("r1", seq, float(seq), at, points, np.zeros((0, 2)))
        bus.put(keys.map_key("r1", "insert"), scan.encode())  # what the matcher publishes
        bus.put(keys.pose("r1"), estimate("r1", seq, float(seq), 0.1 * seq, 0.0).encode())
    with httpx.Client(base_url=f"http://127.0.0.1:{port}", timeout=10.0) as http:
        eventually(lambda: http.get("/api/v1/robots/r1/pose").status_code == 200,
                   "the gateway to see the poses", 20.0)
        eventually(lambda: http.get("/api/v1/robots/r1/map").status_code == 200,
                   "the map server's map", 20.0)
        png = http.get("/api/v1/robots/r1/map.png")
        assert png.status_code == 200
        pixels = np.asarray(Image.open(io.BytesIO(png.content)))
        assert (pixels == 0).sum() > 20  # the ring of occupied cells
        trajectory = eventually(
            lambda: (r := http.get("/api/v1/robots/r1/trajectory").json())["poses"] and
            len(r["poses"]) == 5 and r, "the whole trajectory", 20.0)
        assert trajectory["source"] == "mapserver"
        health = http.get("/api/v1/health").json()
        assert {"router", "mapserver"} <= {s["service"] for s in health["services"]}
        assert "matcher" in health["missing"]
