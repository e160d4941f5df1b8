"""bench.resume: a run of keyframes repeated from a few scans goes through every resume step,
and one over the wire's limit is reported as refused, not raised."""

from __future__ import annotations

import pytest
from scanflow.io.carmen import Keyframe
from scanflow.wire import codec

from bench.resume import run


def test_every_keyframe_is_resumed_and_timed(frames: list[Keyframe]) -> None:
    row = run(frames, 25, 3)
    assert row["keyframes"] == row["resumed_keyframes"] == 25
    assert row["points"] == 25 * 180
    for step in ("build_encode_ms", "router_ms", "decode_nodes_ms", "mapper_ms"):
        assert row[step] >= 0.0
    assert "refused" not in row


def test_a_run_over_the_wire_limit_is_reported_refused(
    frames: list[Keyframe], monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(codec, "MAX_BULK_BYTES", 50_000)
    row = run(frames, 25, 3)
    assert "over MAX_BULK_BYTES" in row["refused"]
    assert "resumed_keyframes" not in row
