"""The surface rule of a scan seen from its origin: which gaps one surface bridges, and the
points `densify_scan` adds along them."""

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scanflow.matching.surface import GAP_BASE_M, GAP_PER_RANGE, densify_scan, surface_gap_m


def arc(range_m: float, step_deg: float, beams: int) -> np.ndarray:
    """Points `step_deg` apart on a circle of `range_m` around the origin (a wall seen head-on)."""
    a = np.radians(np.arange(beams) * step_deg)
    return range_m * np.column_stack((np.cos(a), np.sin(a)))


def test_the_gap_one_surface_bridges_grows_with_range() -> None:
    np.testing.assert_allclose(surface_gap_m(np.array([0.0, 10.0, 80.0])),
                               [GAP_BASE_M, GAP_BASE_M + 10 * GAP_PER_RANGE, 4.85])
    # 1 deg steps stay within it at any range; 5 deg steps are an occlusion edge.
    for r in (5.0, 40.0, 80.0):
        assert 2 * r * math.sin(math.radians(0.5)) < surface_gap_m(r)
        assert 2 * r * math.sin(math.radians(2.5)) > surface_gap_m(r)


def test_a_far_wall_is_filled_and_an_occlusion_edge_left_open() -> None:
    far = arc(40.0, 1.0, 5)  # 0.7 m apart
    dense = densify_scan(far, 0.1)
    assert len(dense) == 5 + 4 * 6
    np.testing.assert_array_equal(dense[:5], far)
    edge = np.array([[5.0, 0.0], [5.0, 0.1], [6.5, 0.2]])  # a 1.5 m jump at 5 m range
    assert len(densify_scan(edge, 0.02)) == 3 + 4


@settings(max_examples=60, deadline=None)
@given(
    ranges=st.lists(st.floats(0.5, 80.0), min_size=2, max_size=40),
    step_deg=st.floats(0.1, 5.0),
    step_m=st.floats(0.01, 0.5),
)
def test_added_points_lie_between_bridged_neighbours_step_m_apart(
    ranges: list[float], step_deg: float, step_m: float
) -> None:
    a = np.radians(np.arange(len(ranges)) * step_deg)
    points = np.asarray(ranges)[:, None] * np.column_stack((np.cos(a), np.sin(a)))
    dense = densify_scan(points, step_m)
    np.testing.assert_array_equal(dense[: len(points)], points)
    added = dense[len(points):]
    gaps = np.hypot(*np.diff(points, axis=0).T)
    bridged = gaps < surface_gap_m(np.minimum(ranges[:-1], ranges[1:]))
    want = np.where(bridged, np.maximum(np.ceil(gaps / step_m) - 1, 0), 0)
    assert len(added) == int(want.sum())
    # Each added point lies on a bridged segment, within step_m of the points beside it.
    offset = 0
    for k in np.flatnonzero(want):
        n = int(want[k])
        run = np.vstack((points[k], added[offset:offset + n], points[k + 1]))
        spacing = np.hypot(*np.diff(run, axis=0).T)
        assert np.all(spacing <= step_m + 1e-9)
        np.testing.assert_allclose(spacing.sum(), gaps[k], rtol=1e-9)
        offset += n


def test_a_step_that_would_add_too_many_points_is_a_match_input_error() -> None:
    """icp's `surface_step_m=1e-12` asked numpy for 198 TiB (docs/matching.md, bad input: a
    MatchInputError naming the option, not a MemoryError)."""
    from scanflow.matching import MatchInputError, match

    scan = arc(5.0, 1.0, 360)
    with pytest.raises(MatchInputError, match=r"too large"):
        densify_scan(scan, 1e-12)
    with pytest.raises(MatchInputError, match=r"surface_step_m"):
        match(scan, scan, method="icp", surface_step_m=1e-12)
    assert len(densify_scan(scan, 0.01)) > len(scan)
