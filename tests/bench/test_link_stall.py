"""bench.link_stall: what a stalled reader gets, on a scripted bus and a real router."""

from __future__ import annotations

import json
import sys
from collections.abc import Callable
from types import SimpleNamespace
from typing import Any

import pytest
from scanflow.config import ZenohSettings

from bench import link_stall
from bench.link_stall import ZENOH_DEFAULT_S, run


class ScriptedBus:
    """Stands in for the router and the sessions: keeps every put and, on the last, hands the
    reader the messages in `order` (indices of the puts; repeats and gaps allowed)."""

    def __init__(self, order: Callable[[int], list[int]]) -> None:
        self.order = order
        self.settings: list[ZenohSettings] = []
        self.callbacks: list[Callable[[Any], None]] = []
        self.puts: list[bytes] = []
        self.closed = 0

    def open_session(self, settings: ZenohSettings) -> Any:
        self.settings.append(settings)
        undeclare = SimpleNamespace(undeclare=lambda: None)

        def subscribe(key: str, callback: Callable[[Any], None]) -> Any:
            self.callbacks.append(callback)
            return undeclare

        def publisher(key: str, **qos: Any) -> Any:
            return SimpleNamespace(put=self.put, undeclare=lambda: None)

        return SimpleNamespace(declare_subscriber=subscribe, declare_publisher=publisher,
                               close=self.close)

    def put(self, payload: bytes) -> None:
        self.puts.append(payload)
        if int(payload[:8]) == self.messages - 1:
            for i in self.order(len(self.puts)):
                data = self.puts[i]
                for callback in self.callbacks:
                    callback(SimpleNamespace(payload=SimpleNamespace(to_bytes=lambda d=data: d)))

    def close(self) -> None:
        self.closed += 1

    def run(self, monkeypatch: pytest.MonkeyPatch, messages: int, **kwargs: Any) -> dict:
        self.messages = messages
        sleeps: list[float] = []
        monkeypatch.setattr(link_stall, "open_session", self.open_session)
        monkeypatch.setattr(link_stall, "time", SimpleNamespace(sleep=sleeps.append,
                                                                 perf_counter=lambda: 0.0))
        report = run(messages=messages, **kwargs)
        self.sleeps = sleeps
        return report


def test_every_message_once_in_order_is_nothing_lost(monkeypatch: pytest.MonkeyPatch) -> None:
    bus = ScriptedBus(lambda n: list(range(n)))
    report = bus.run(monkeypatch, 50, block_close_s=12.5, stall_s=7.0, size=100)
    assert report == {"block_close_s": 12.5, "received": 50, "lost": 0, "in_order": True,
                      "writer_held_s": 0.0}
    # Three sessions (router, reader, writer), all with the block_close_s under test, all closed.
    assert [s.block_close_s for s in bus.settings] == [12.5] * 3 and bus.closed == 3
    assert bus.settings[0].mode == "router"
    endpoint = bus.settings[0].listen[0]
    assert all(s.connect == [endpoint] for s in bus.settings[1:])
    assert bus.sleeps.count(7.0) == 1  # the reader stalls on its first message only
    assert {len(p) for p in bus.puts} == {100}


def test_gaps_repeats_and_reordering_are_counted_as_such(monkeypatch: pytest.MonkeyPatch) -> None:
    def order(n: int) -> list[int]:  # 3 and 7 never come, 5 comes twice, 9 before 8
        return [0, 1, 2, 4, 5, 5, 6, 9, 8, *range(10, n)]

    report = ScriptedBus(order).run(monkeypatch, 20, block_close_s=5.0, stall_s=0.0, size=8)
    assert (report["received"], report["lost"], report["in_order"]) == (18, 2, False)
    repeat = ScriptedBus(lambda n: [0, 1, 1, *range(2, n)])
    report = repeat.run(monkeypatch, 20, block_close_s=5.0, stall_s=0.0, size=8)
    assert (report["received"], report["lost"], report["in_order"]) == (20, 0, True)


def test_the_command_line_runs_zenohs_default_and_scanflows_setting(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    bus = ScriptedBus(lambda n: list(range(n)))
    bus.messages = 30
    monkeypatch.setattr(link_stall, "open_session", bus.open_session)
    monkeypatch.setattr(link_stall, "time", SimpleNamespace(sleep=lambda s: None,
                                                             perf_counter=lambda: 0.0))
    monkeypatch.setattr(sys, "argv", ["bench.link_stall", "--stall-s", "3", "--messages", "30",
                                      "--size", "64", "--json"])
    link_stall.main()
    report = json.loads(capsys.readouterr().out)
    assert (report["stall_s"], report["messages"], report["size"]) == (3.0, 30, 64)
    closes = [r["block_close_s"] for r in report["runs"]]
    assert closes == [ZENOH_DEFAULT_S, ZenohSettings().block_close_s] == [5.0, 60.0]
    assert [r["received"] for r in report["runs"]] == [30, 30]
    assert sorted({s.block_close_s for s in bus.settings}) == [5.0, 60.0]


@pytest.mark.integration
def test_a_reader_stalled_for_less_than_block_close_gets_every_message() -> None:
    report = run(block_close_s=5.0, stall_s=0.3, messages=500, size=8000)
    assert report["received"] == 500 and report["lost"] == 0 and report["in_order"]


@pytest.mark.integration
def test_a_reader_stalled_past_block_close_loses_what_was_sent_after_its_link_closed() -> None:
    """80 MB through the router while the reader sleeps 1.5 s, its link closed after 0.2 s; the
    last message never comes, so the count is read 1 s past the stall."""
    report = run(block_close_s=0.2, stall_s=1.5, messages=10_000, size=8000, drain_s=1.0)
    assert 0 < report["received"] < 10_000
    assert report["lost"] == 10_000 - report["received"]
