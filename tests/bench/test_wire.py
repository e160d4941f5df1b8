"""bench.wire: the scan both codecs carry, their sizes and round trips, and the timed figures."""

from __future__ import annotations

import json
import math
from types import SimpleNamespace

import numpy as np
import pytest
from scanflow.scan import LaserScan
from scanflow.wire import ScanMessage

from bench import wire
from bench.wire import BEAMS, json_decode, json_encode, main, make_scan, median_us, run

FIELDS = ("angle_min_rad", "angle_increment_rad", "range_min_m", "range_max_m", "stamp_s",
          "scan_duration_s", "robot_id", "frame_id", "seq")


def assert_same_scan(back: LaserScan, scan: LaserScan) -> None:
    for name in FIELDS:
        assert getattr(back, name) == getattr(scan, name), name
    assert np.array_equal(back.ranges_m, scan.ranges_m, equal_nan=True)
    assert np.array_equal(back.intensities, scan.intensities)
    assert np.array_equal(back.beam_time_offsets_s, scan.beam_time_offsets_s)


def test_the_scan_is_a_1081_beam_270_deg_sweep_with_dropouts_intensities_and_times() -> None:
    scan = make_scan(0)
    assert scan.beam_count == BEAMS == 1081
    last = scan.angle_min_rad + (scan.beam_count - 1) * scan.angle_increment_rad
    assert math.degrees(last - scan.angle_min_rad) == pytest.approx(270.0)
    assert last == pytest.approx(-scan.angle_min_rad)
    dropped = np.isnan(scan.ranges_m)
    assert 0.03 < dropped.mean() < 0.07  # 5 % dropouts
    assert np.all((scan.ranges_m[~dropped] >= 0.1) & (scan.ranges_m[~dropped] <= 30.0))
    assert scan.intensities is not None and scan.intensities.shape == (BEAMS,)
    offsets = scan.beam_time_offsets_s
    assert offsets is not None and offsets[0] == 0.0 and offsets[-1] < scan.scan_duration_s
    assert np.all(np.diff(offsets) > 0)
    assert not np.array_equal(make_scan(1).ranges_m, scan.ranges_m, equal_nan=True)


def test_both_codecs_carry_every_field_of_the_scan_back() -> None:
    scan = make_scan(3)
    assert_same_scan(json_decode(json_encode(scan)), scan)
    assert_same_scan(ScanMessage.decode(ScanMessage(scan).encode()).scan, scan)
    assert json.loads(json_encode(scan))["type"] == "scan"


def test_the_report_gives_the_encoded_sizes_and_the_ratios_of_its_own_figures(
    capsys: pytest.CaptureFixture[str],
) -> None:
    result = run(3, 5)
    scan = make_scan(5)
    assert (result["beams"], result["runs"]) == (BEAMS, 3)
    assert result["msgpack"]["bytes"] == len(ScanMessage(scan).encode())
    assert result["json"]["bytes"] == len(json_encode(scan))
    # msgpack carries the raw arrays: float32 ranges and intensities, float64 beam times.
    assert BEAMS * (4 + 4 + 8) < result["msgpack"]["bytes"] < result["json"]["bytes"]
    for key in ("encode_us", "decode_us", "bytes"):
        assert result["msgpack"][key] > 0 and result["json"][key] > 0
        ratio = result["json"][key] / result["msgpack"][key]
        assert result["json_over_msgpack"][key] == pytest.approx(ratio, rel=1e-12)
    main(["--runs", "2", "--seed", "5", "--json"])
    printed = json.loads(capsys.readouterr().out)
    assert printed["runs"] == 2 and printed["msgpack"]["bytes"] == result["msgpack"]["bytes"]
    assert printed["json"]["bytes"] == result["json"]["bytes"]


def test_a_codec_that_does_not_give_the_ranges_back_is_an_error(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    def lossy(data: bytes) -> LaserScan:
        scan = json_decode(data)
        return scan.with_ranges(np.round(scan.ranges_m, 2))

    monkeypatch.setattr(wire, "json_decode", lossy)
    with pytest.raises(RuntimeError, match="did not reproduce"):
        run(1, 0)


def test_median_us_is_the_median_of_the_timed_calls_in_microseconds(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """A fake clock: each call takes the next of the given durations (ns), warm-up included."""
    durations = iter([10**9] * 5 + [4_000, 1_000, 9_000_000, 2_500, 3_000])
    now = [0]

    def call() -> None:
        now[0] += next(durations)

    monkeypatch.setattr(wire, "time", SimpleNamespace(perf_counter_ns=lambda: now[0]))
    assert median_us(call, 5) == 3.0  # median of 4, 1, 9000, 2.5, 3 us; warm-up not counted
    assert next(durations, None) is None  # 5 warm-up calls (min(50, runs)), then 5 timed


def test_the_command_line_refuses_fewer_than_one_run(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exit_info:
        main(["--runs", "0"])
    assert exit_info.value.code == 2
    assert "--runs must be >= 1" in capsys.readouterr().err
