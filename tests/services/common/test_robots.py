"""The robot limit: who is admitted, who is refused, and how often that is reported."""

from __future__ import annotations

import pytest

from services.common.robots import RobotLimit


def test_a_robot_limit_admits_the_known_and_the_first_n_and_reports_each_refused_once():
    refused: list[tuple[str, bool]] = []
    limit = RobotLimit(2, lambda robot_id, first: refused.append((robot_id, first)))
    held: dict[str, object] = {}
    for robot_id in ("a", "b", "c", "a", "c", "d"):
        if limit.admits(robot_id, held):
            held.setdefault(robot_id, object())
    assert sorted(held) == ["a", "b"]
    assert refused == [("c", True), ("c", False), ("d", True)]
    with pytest.raises(ValueError, match="max_robots"):
        RobotLimit(0, lambda *_: None)


def test_a_retired_robot_refused_again_is_reported_again():
    refused: list[tuple[str, bool]] = []
    limit = RobotLimit(1, lambda robot_id, first: refused.append((robot_id, first)))
    held = {"a": object()}
    assert not limit.admits("b", held) and not limit.admits("b", held)
    limit.forget("b")
    assert not limit.admits("b", held)
    assert refused == [("b", True), ("b", False), ("b", True)]
