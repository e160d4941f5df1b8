"""What ingest publishes: numbering, limits and the declared lidar mount, on real sources."""

from __future__ import annotations

import math

from scanflow.geometry import Pose2D, angle_diff
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


def test_the_simulators_odometry_drifts_in_heading_as_set() -> None:
    """sim_odom_yaw_noise reaches the simulator: the same run with its wheel odometry's heading
    drifting; the scans are the same."""
    def run(yaw_noise: float) -> list:
        return list(source_events(None, "r", 3.0, 1, None, sim_odom_scale_error=0.0,
                                  sim_odom_yaw_noise=yaw_noise))

    quiet, drifting = run(0.0), run(0.05)
    assert [type(e) for e in quiet] == [type(e) for e in drifting]
    for a, b in zip(scans_of(quiet), scans_of(drifting), strict=True):
        assert a.ranges_m.tobytes() == b.ranges_m.tobytes()
    odom_quiet = [e.pose for e in quiet if isinstance(e, Odometry)]
    odom_drifting = [e.pose for e in drifting if isinstance(e, Odometry)]
    assert odom_quiet[0] == odom_drifting[0]
    assert abs(angle_diff(odom_quiet[-1].theta, odom_drifting[-1].theta)) > math.radians(0.1)
