"""choose_source: the first pose source covering a sweep, and why the earlier ones did not."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import pytest
from scanflow.deskew import ConstantVelocityModel, DeskewError, OdometryBuffer, choose_source
from scanflow.geometry import Pose2D


@dataclass
class FakeSource:
    """A pose source whose coverage verdict is fixed, recording the intervals it was asked."""

    name: str
    gap: str | None
    asked: list[tuple[float, float]] = field(default_factory=list)

    def coverage_gap(self, start_s: float, end_s: float) -> str | None:
        self.asked.append((start_s, end_s))
        return self.gap


def test_no_sources_or_an_empty_list_chooses_none() -> None:
    assert choose_source(None, 0.0, 0.1) == (None, "no pose source given")
    assert choose_source([], 0.0, 0.1) == (None, "no pose source given")
    assert choose_source((), 0.0, 0.1) == (None, "no pose source given")


def test_a_single_covering_source_is_chosen_with_no_reasons() -> None:
    source = FakeSource("odometry", None)
    assert choose_source(source, 1.0, 1.1) == (source, "")
    assert source.asked == [(1.0, 1.1)]


def test_the_first_covering_source_wins_and_later_ones_are_not_asked() -> None:
    first, second, third = FakeSource("a", "too old"), FakeSource("b", None), FakeSource("c", None)
    for candidates in ([first, second, third], (first, second, third)):
        chosen, reasons = choose_source(candidates, 2.0, 2.5)
        assert chosen is second
        assert reasons == "a: too old"
    assert third.asked == []
    assert first.asked == second.asked == [(2.0, 2.5), (2.0, 2.5)]


def test_no_covering_source_gives_every_reason_in_order() -> None:
    sources = [FakeSource("odometry", "gap of 0.4 s"), FakeSource("constant_velocity", "has 1")]
    assert choose_source(sources, 0.0, 0.1) == (
        None,
        "odometry: gap of 0.4 s; constant_velocity: has 1",
    )
    assert choose_source(sources[0], 0.0, 0.1) == (None, "odometry: gap of 0.4 s")


def test_the_real_sources_fall_back_from_odometry_to_the_velocity_model() -> None:
    buffer = OdometryBuffer()
    model = ConstantVelocityModel()
    model.update(0.0, Pose2D())
    model.update(0.1, Pose2D(0.1, 0.0, 0.0))
    chosen, reasons = choose_source([buffer, model], 0.1, 0.2)
    assert chosen is model
    assert reasons == "odometry: needs at least two odometry samples, has 0"
    buffer.add(0.0, Pose2D())
    buffer.add(0.2, Pose2D(0.2, 0.0, 0.0))
    assert choose_source([buffer, model], 0.1, 0.2) == (buffer, "")
    x, _, _ = buffer.poses_at(np.array([0.15]))
    assert x[0] == pytest.approx(0.15)


def test_deskew_error_is_a_value_error() -> None:
    with pytest.raises(ValueError, match="max_gap_s"):
        OdometryBuffer(max_gap_s=math.inf)
    assert issubclass(DeskewError, ValueError)
