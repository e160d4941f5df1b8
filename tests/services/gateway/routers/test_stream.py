"""GET /robots/{robot}/poses/stream and /poses/stream: live poses as server-sent events."""

from __future__ import annotations

import threading

import pytest
from scanflow import keys

from ..conftest import estimate, eventually


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
