"""Deskew's compiled kernels against plain numpy and loop re-computations of their promises."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from numpy.typing import NDArray
from scanflow.deskew import kernels

STEP_S = 0.05  # stamps and query times on a grid, so that times hit stamps exactly

# Strictly increasing stamps (as OdometryBuffer holds them), in whole grid steps.
stamp_steps = st.lists(st.integers(1, 6), min_size=0, max_size=12)


def _stamps(first: int, steps: list[int]) -> NDArray[np.float64]:
    return STEP_S * (first + np.concatenate(([0], np.cumsum(steps, dtype=np.int64))))


def _expected_coverage(
    stamps: NDArray[np.float64], start_s: float, end_s: float, margin_s: float, max_gap_s: float
) -> tuple[int, float, int]:
    """The coverage verdict by a linear scan over every segment of `stamps`.

    Interpolating over [start_s, end_s] bridges every segment (s_i, s_i+1) whose inside meets
    it (the end segments extend outwards): each of those must be short.
    """
    n = stamps.size
    if n < 2:
        return kernels.TOO_FEW, float(n), 0
    if start_s < stamps[0] - margin_s:
        return kernels.BEFORE_OLDEST, stamps[0] - start_s, 0
    if end_s > stamps[-1] + margin_s:
        return kernels.AFTER_NEWEST, end_s - stamps[-1], n - 1
    for i in range(n - 1):
        left = -math.inf if i == 0 else stamps[i]
        right = math.inf if i == n - 2 else stamps[i + 1]
        bridged = left < end_s and right > start_s
        if bridged and stamps[i + 1] - stamps[i] > max_gap_s:
            return kernels.GAP, stamps[i + 1] - stamps[i], i
    return kernels.COVERED, 0.0, 0


@settings(max_examples=300, deadline=None)
@given(
    first=st.integers(-5, 5),
    steps=stamp_steps,
    start=st.integers(-12, 60),
    length=st.integers(0, 20),
    margin=st.integers(0, 2),
    max_gap=st.integers(1, 5),
    pad=st.tuples(st.integers(0, 3), st.integers(0, 3)),
)
def test_coverage_matches_a_scan_over_every_segment(
    first: int,
    steps: list[int],
    start: int,
    length: int,
    margin: int,
    max_gap: int,
    pad: tuple[int, int],
) -> None:
    stamps = _stamps(first, steps)
    # The window [lo, hi) sits inside a larger array whose other cells must not be read.
    data = np.concatenate((np.full(pad[0], -1e9), stamps, np.full(pad[1], 1e9)))
    lo, hi = pad[0], pad[0] + stamps.size
    start_s, end_s = STEP_S * start, STEP_S * (start + length)
    margin_s, max_gap_s = STEP_S * margin, STEP_S * max_gap + 1e-9
    status, value, index = kernels.coverage(data, lo, hi, start_s, end_s, margin_s, max_gap_s)
    want_status, want_value, want_index = _expected_coverage(
        stamps, start_s, end_s, margin_s, max_gap_s
    )
    assert status == want_status
    assert value == pytest.approx(want_value, abs=1e-12)
    assert index - lo == want_index


def test_coverage_reports_the_first_gap_that_the_sweep_crosses() -> None:
    stamps = np.array([0.0, 0.1, 0.5, 0.6, 1.2, 1.3])
    assert kernels.coverage(stamps, 0, 6, 0.0, 0.09, 0.0, 0.2) == (kernels.COVERED, 0.0, 0)
    status, value, index = kernels.coverage(stamps, 0, 6, 0.05, 1.25, 0.0, 0.2)
    assert (status, index) == (kernels.GAP, 1)
    assert value == pytest.approx(0.4)
    status, value, index = kernels.coverage(stamps, 2, 6, 0.55, 1.25, 0.0, 0.2)
    assert (status, index) == (kernels.GAP, 3)
    assert value == pytest.approx(0.6)
    assert kernels.coverage(stamps, 3, 4, 0.6, 0.6, 0.0, 0.2) == (kernels.TOO_FEW, 1.0, 3)


def _track(stamps: NDArray[np.float64], seed: int) -> NDArray[np.float64]:
    """Rows (stamp, x, y, theta wrapped, theta unwrapped) as OdometryBuffer lays them out."""
    rng = np.random.default_rng(seed)
    x, y = rng.normal(size=(2, stamps.size)).cumsum(axis=1)
    theta = rng.uniform(-2.5, 2.5, stamps.size).cumsum()
    wrapped = (theta + np.pi) % (2 * np.pi) - np.pi
    return np.vstack((stamps, x, y, wrapped, theta))


@settings(max_examples=150, deadline=None)
@given(
    first=st.integers(-5, 5),
    steps=st.lists(st.integers(1, 6), min_size=1, max_size=12),
    fractions=st.lists(st.floats(0.0, 1.0), min_size=1, max_size=20),
    sort=st.booleans(),
    seed=st.integers(0, 2**16),
    pad=st.tuples(st.integers(0, 3), st.integers(0, 3)),
)
def test_interpolate_poses_matches_np_interp_inside_the_span(
    first: int,
    steps: list[int],
    fractions: list[float],
    sort: bool,
    seed: int,
    pad: tuple[int, int],
) -> None:
    stamps = _stamps(first, steps)
    track = _track(stamps, seed)
    data = np.hstack((np.full((5, pad[0]), np.nan), track, np.full((5, pad[1]), np.nan)))
    times = stamps[0] + np.asarray(fractions) * (stamps[-1] - stamps[0])
    if sort:
        times.sort()
    lo, hi = pad[0], pad[0] + stamps.size
    out = kernels.interpolate_poses(data, lo, hi, times, 0.0, False)
    want = [np.interp(times, stamps, track[row]) for row in (1, 2, 4)]
    np.testing.assert_allclose(out, np.array(want), atol=1e-9)


def test_interpolate_poses_extrapolates_the_end_segments_along_their_lines() -> None:
    data = _track(np.array([1.0, 1.5, 2.0, 2.25]), seed=3)
    times = np.array([0.9, 2.3, 0.95])  # unsorted on purpose: each time finds its segment
    out = kernels.interpolate_poses(data, 0, 4, times, 0.0, False)
    for k, (a, b) in enumerate(((0, 1), (2, 3), (0, 1))):
        f = (times[k] - data[0, a]) / (data[0, b] - data[0, a])
        want = data[[1, 2, 4], a] + f * (data[[1, 2, 4], b] - data[[1, 2, 4], a])
        np.testing.assert_allclose(out[:, k], want, atol=1e-12)


@settings(max_examples=100, deadline=None)
@given(
    steps=st.lists(st.integers(1, 6), min_size=1, max_size=10),
    fractions=st.lists(st.floats(0.0, 1.0), min_size=1, max_size=10),
    reference_fraction=st.floats(0.0, 1.0),
    seed=st.integers(0, 2**16),
)
def test_relative_poses_are_the_interpolated_poses_seen_from_the_reference_pose(
    steps: list[int], fractions: list[float], reference_fraction: float, seed: int
) -> None:
    stamps = _stamps(0, steps)
    data = _track(stamps, seed)
    span = stamps[-1] - stamps[0]
    times = np.sort(stamps[0] + np.asarray(fractions) * span)
    reference_s = stamps[0] + reference_fraction * span
    out = kernels.interpolate_poses(data, 0, stamps.size, times, reference_s, True)
    x, y, theta = (np.interp(times, stamps, data[row]) for row in (1, 2, 4))
    xr, yr, thr = (np.interp(reference_s, stamps, data[row]) for row in (1, 2, 4))
    # T_ref^-1 * T_t as homogeneous matrices
    def matrix(px: float, py: float, th: float) -> NDArray[np.float64]:
        c, s = math.cos(th), math.sin(th)
        return np.array([[c, -s, px], [s, c, py], [0.0, 0.0, 1.0]])

    ref_inverse = np.linalg.inv(matrix(xr, yr, thr))
    for k in range(times.size):
        rel = ref_inverse @ matrix(x[k], y[k], theta[k])
        np.testing.assert_allclose(out[:2, k], rel[:2, 2], atol=1e-9)
        assert out[2, k] == pytest.approx(theta[k] - thr, abs=1e-9)
        assert math.atan2(rel[1, 0], rel[0, 0]) == pytest.approx(
            (out[2, k] + math.pi) % (2 * math.pi) - math.pi, abs=1e-9
        )


@settings(max_examples=100, deadline=None)
@given(n=st.integers(0, 40), seed=st.integers(0, 2**16))
def test_beams_in_reference_moves_each_beam_by_its_own_pose(n: int, seed: int) -> None:
    rng = np.random.default_rng(seed)
    ranges = rng.uniform(0.1, 20.0, n).astype(np.float32)
    angles = np.linspace(-math.pi, math.pi, n, endpoint=False)
    kind = rng.integers(0, 3, n)  # 0 valid, 1 no return, 2 neither (e.g. too close)
    valid, no_return = kind == 0, kind == 1
    x, y, theta = rng.normal(size=(3, n))
    points, missed = kernels.beams_in_reference(
        ranges, angles, valid, no_return, 30.0, x, y, theta
    )
    assert points.shape == (int(valid.sum()), 2)
    assert missed.shape == (int(no_return.sum()), 2)
    want = []
    want_missed = []
    for i in range(n):
        c, s = math.cos(theta[i]), math.sin(theta[i])
        for mask, r, out in ((valid, float(ranges[i]), want), (no_return, 30.0, want_missed)):
            if mask[i]:
                u = np.array([math.cos(angles[i]), math.sin(angles[i])])
                out.append([x[i] + r * (c * u[0] - s * u[1]), y[i] + r * (s * u[0] + c * u[1])])
    np.testing.assert_allclose(points, np.reshape(want, (-1, 2)), atol=1e-9)
    np.testing.assert_allclose(missed, np.reshape(want_missed, (-1, 2)), atol=1e-9)
