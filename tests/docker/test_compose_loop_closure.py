"""Loop closure in the compose deployment: SCANFLOW_BACKEND_LOOP_CLOSURE from the shell turns it
on for the matcher and the map server. A lap of the simulator's ring corridor with poor wheel
odometry through the containers must equal the in-process pipeline with the back end: the
corrected path and the map over HTTP, and the redraws counted by both services. The front end
comes round within centimetres, so the matcher redraws at any shift
(SCANFLOW_BACKEND_REDRAW_SHIFT_M / _DEG from the shell, as `REDRAW` in test_backend_services). The
matcher culls keyframes (SCANFLOW_BACKEND_CULL_M from the shell reaches it): about half the
inserts hang from earlier keyframes, and the served map holds them all the same.
"""

from __future__ import annotations

import tempfile
from pathlib import Path

import httpx
import numpy as np
import pytest
from scanflow.maps.export import save_map_server

from .test_compose import SERVICES, metric, poll, services_test, wait_exited

pytestmark = [pytest.mark.docker, pytest.mark.slow, pytest.mark.timeout(900)]
CULL_M = 0.3
BACKEND = services_test("test_backend_services")


@pytest.fixture(scope="module")
def ring(compose_projects, harness):
    """The stack with loop closure, the ring lap ingested; (project, client)."""
    port = harness.free_port()
    project = compose_projects("sflc", env={
        "SCANFLOW_GATEWAY_PUBLISH": str(port),
        "SCANFLOW_BACKEND_LOOP_CLOSURE": "true",
        "SCANFLOW_BACKEND_CULL_M": str(CULL_M),
        "SCANFLOW_INGEST_RATE": "0",
        "SCANFLOW_INGEST_SIM_DURATION_S": "80",
        "SCANFLOW_INGEST_SIM_SEED": "1",
        "SCANFLOW_INGEST_SIM_WORLD": "loop",
        "SCANFLOW_INGEST_SIM_ODOM_SCALE_ERROR": "0.03",
        "SCANFLOW_DESKEW_ODOM_WAIT_S": "3",  # as in test_compose: a budget never reached
        **BACKEND.REDRAW_ENV,
    })
    project.up()
    project.wait_healthy(SERVICES, timeout_s=240.0)
    wait_exited(project, "ingest", timeout_s=300.0)
    with httpx.Client(base_url=f"http://127.0.0.1:{port}", timeout=30.0) as client:
        yield project, client


def test_a_ring_lap_with_loop_closure_equals_the_in_process_pipeline(ring):
    project, client = ring
    pipeline, outputs, redraws = BACKEND.ring_in_process(CULL_M)
    assert len(redraws) >= 1
    seq, _, at_redraw, _ = redraws[-1]
    want = np.vstack([at_redraw, *[o.pose.to_array() for o in outputs[seq + 1:]]])
    latest = client.get("/api/v1/robots/robot/pose").json()
    assert latest["seq"] == outputs[-1].seq, latest
    path = poll(lambda: (p := trajectory(client)) and len(p) == len(want) and p, 30.0,
                "the map server's path to hold every pose")
    got = np.array([[p["x_m"], p["y_m"], p["theta_rad"]] for p in path])
    np.testing.assert_array_equal(got, want)

    with tempfile.TemporaryDirectory() as tmp:
        yaml_path = save_map_server(pipeline.frontend.map.grid, Path(tmp) / "map")
        want_pgm = yaml_path.with_suffix(".pgm").read_bytes()
    poll(lambda: client.get("/api/v1/robots/robot/map.pgm").content == want_pgm, 30.0,
         "the served map to equal the in-process one")

    text = client.get("/metrics").text
    assert metric(text, "scanflow_service_events_total", event="backend.redraws") == len(redraws)
    assert metric(text, "scanflow_service_events_total", event="redrawn") == len(redraws)
    culled = metric(text, "scanflow_service_events_total", event="backend.culled")
    assert culled == len(pipeline.mapper.culled_seqs) > 0
    for service in SERVICES:
        assert project.restarts(service) == 0, project.describe(service)


def trajectory(client: httpx.Client) -> list[dict]:
    return client.get("/api/v1/robots/robot/trajectory").json()["poses"]
