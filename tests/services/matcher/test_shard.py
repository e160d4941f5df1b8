"""Shards: how robots are split among matchers."""

from __future__ import annotations

from services.matcher.shard import owns


def test_shards_split_robots_and_a_robot_list_wins():
    robots = [f"robot{i}" for i in range(40)]
    first = {r for r in robots if owns(r, "0/2", [])}
    second = {r for r in robots if owns(r, "1/2", [])}
    assert first | second == set(robots) and not first & second and first and second
    assert owns("x", "1/2", ["x"]) and not owns("y", "0/1", ["x"])
