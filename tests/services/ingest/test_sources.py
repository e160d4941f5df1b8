"""What ingest publishes: numbering, limits and the declared lidar mount, on real sources."""

from __future__ import annotations

import math

from scanflow.geometry import Pose2D
from scanflow.scan import LaserScan, Odometry

from services.ingest.sources import source_events

MOUNT = Pose2D(0.2, 0.0, math.radians(-10.0))


def scans_of(events) -> list[LaserScan]:
    return [e for e in events if isinstance(e, LaserScan)]


def test_a_log_keeps_its_own_mount_unless_one_is_declared(data_file) -> None:
    log = str(data_file("aces-corrected.log.gz"))
    plain = list(source_events(log, "r", 1.0, 0, 5))
    declared = list(source_events(log, "r", 1.0, 0, 5, MOUNT))
    assert {s.mount for s in scans_of(plain)} == {Pose2D()}
    assert {s.mount for s in scans_of(declared)} == {MOUNT}
    # Only the mount changes: same beams, stamps, seqs and odometry.
    for a, b in zip(plain, declared, strict=True):
        assert type(a) is type(b) and a.seq == b.seq and a.stamp_s == b.stamp_s
        if isinstance(a, Odometry):
            assert a == b
        else:
            assert a.ranges_m.tobytes() == b.ranges_m.tobytes()


def test_the_simulator_mounts_its_lidar_where_declared() -> None:
    scans = scans_of(source_events(None, "r", 0.5, 3, None, MOUNT))
    plain = scans_of(source_events(None, "r", 0.5, 3, None))
    assert len(scans) == len(plain) == 5 and [s.seq for s in scans] == list(range(5))
    assert {s.mount for s in scans} == {MOUNT}
    # The lidar sits elsewhere, so it measures other ranges (not just another label).
    assert scans[0].ranges_m.tobytes() != plain[0].ranges_m.tobytes()
