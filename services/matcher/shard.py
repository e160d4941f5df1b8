"""Which robots a matcher instance tracks: a configured set, or a stable hash over N instances."""

from __future__ import annotations

import zlib


def owns(robot_id: str, shard: str, robots: list[str]) -> bool:
    """True when this instance tracks `robot_id`: listed in `robots`, or (no list) the robot's
    CRC-32 falls on this shard. CRC-32 is the same in every process (unlike `hash`)."""
    if robots:
        return robot_id in robots
    index, count = (int(part) for part in shard.split("/"))  # validated by MatcherSettings
    return zlib.crc32(robot_id.encode("utf-8")) % count == index
