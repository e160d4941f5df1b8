"""The correlative search on its own: every candidate's score against a plain numpy count, the
window's reach, Olson's covariance floor, and kernels that let other threads run."""

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scanflow.geometry import Pose2D
from scanflow.maps.grid import GridSpec
from scanflow.maps.maxpool import SCORE_SCALE, MaxPoolStack
from scanflow.matching.csm_search import (
    build_candidates,
    default_angular_step_rad,
    olson_covariance,
    reach_m,
    search_top,
    stack_depth,
    window_steps,
)

SPEC = GridSpec(origin_x_m=-1.0, origin_y_m=-0.8, resolution_m=0.1, rows=16, cols=20)


def numpy_scores(values: np.ndarray, source: np.ndarray, guess: Pose2D, half_cells: int,
                 angles: np.ndarray) -> dict[tuple[int, int, int], int]:
    """Every candidate's score, (k, ix, iy) -> sum of the quantised values under its points,
    computed point by point in plain numpy (off the grid scores 0)."""
    quantised = np.rint(values * SCORE_SCALE).astype(np.int64)
    res = SPEC.resolution_m
    out = {}
    for k, a in enumerate(angles):
        c, s = math.cos(a), math.sin(a)
        x = c * source[:, 0] - s * source[:, 1] + guess.x
        y = s * source[:, 0] + c * source[:, 1] + guess.y
        for iy in range(-half_cells, half_cells + 1):
            for ix in range(-half_cells, half_cells + 1):
                cols = np.floor((x - SPEC.origin_x_m) / res).astype(int) + ix
                rows = np.floor((y - SPEC.origin_y_m) / res).astype(int) + iy
                inside = (rows >= 0) & (rows < SPEC.rows) & (cols >= 0) & (cols < SPEC.cols)
                out[(k, ix, iy)] = int(quantised[rows[inside], cols[inside]].sum())
    return out


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), exhaustive=st.booleans())
def test_the_best_candidate_has_the_highest_plain_numpy_score(seed: int, exhaustive: bool) -> None:
    rng = np.random.default_rng(seed)
    values = np.where(rng.random(SPEC.shape) < 0.15, rng.random(SPEC.shape), 0.0)
    source = rng.uniform(-0.6, 0.6, size=(int(rng.integers(3, 15)), 2))
    guess = Pose2D(rng.uniform(-0.2, 0.2), rng.uniform(-0.2, 0.2), rng.uniform(-1, 1))
    step = math.radians(5.0)
    half_cells, _ = window_steps(SPEC.resolution_m, 0.3, math.radians(10.0), step)
    stack = MaxPoolStack.from_values(SPEC, values, stack_depth(half_cells))
    cand = build_candidates(source, stack, guess, 0.3, math.radians(10.0), step)
    scores = numpy_scores(values, source, guess, half_cells, cand.angles_rad)

    (k, ix, iy, score), = search_top(cand, exhaustive, 1, 0, 0)
    assert score == scores[(k, ix, iy)] == max(scores.values())
    tied = [key for key, v in scores.items() if v == score]
    assert min(ix * ix + iy * iy for _, ix, iy in tied) == ix * ix + iy * iy  # nearest the guess


def test_the_window_is_whole_cells_and_steps_each_side_and_at_most_a_full_turn() -> None:
    assert window_steps(0.05, 1.0, math.radians(30), math.radians(0.5)) == (20, 60)
    assert window_steps(0.05, 0.049, 0.0, 0.1) == (0, 0)
    half_steps = window_steps(0.05, 0.1, 100.0, 0.01)[1]
    assert half_steps == math.floor(math.pi / 0.01 + 1e-9)


def test_the_top_level_blocks_are_about_half_the_window() -> None:
    assert [stack_depth(w) for w in (0, 1, 2, 10, 20, 64)] == [0, 0, 1, 3, 4, 6]


@settings(max_examples=200, deadline=None)
@given(
    cx=st.floats(-5, 5), cy=st.floats(-5, 5), half=st.floats(0, 2),
    ux=st.floats(-1, 1), uy=st.floats(-1, 1), bearing=st.floats(-math.pi, math.pi),
    beyond=st.floats(1.0001, 3),
)
def test_a_point_beyond_the_reach_lands_off_the_grid_under_every_candidate(
    cx: float, cy: float, half: float, ux: float, uy: float, bearing: float, beyond: float
) -> None:
    centre = Pose2D(cx, cy, 0.0)
    far = reach_m(SPEC, centre, half) * beyond
    x = cx + ux * half + far * math.cos(bearing)  # any translation in the window, any heading
    y = cy + uy * half + far * math.sin(bearing)
    on_x = SPEC.origin_x_m <= x <= SPEC.origin_x_m + SPEC.width_m
    on_y = SPEC.origin_y_m <= y <= SPEC.origin_y_m + SPEC.height_m
    assert not (on_x and on_y)


def test_olsons_covariance_is_at_least_the_discretisation_floor_and_wider_on_a_flat_map() -> None:
    step = math.radians(2.0)
    source = np.random.default_rng(5).uniform(-0.6, 0.6, size=(40, 2))

    def covariance_on(values: np.ndarray) -> np.ndarray:
        stack = MaxPoolStack.from_values(SPEC, values, 2)
        cand = build_candidates(source, stack, Pose2D(), 0.3, math.radians(6), step)
        return olson_covariance(cand, cand.half_steps, 0, 0, step)

    probe = build_candidates(source, MaxPoolStack.from_values(SPEC, np.zeros(SPEC.shape), 2),
                             Pose2D(), 0.3, math.radians(6), step)
    peaked = np.zeros(SPEC.shape)  # 1 under the points of the middle candidate, 0 elsewhere
    peaked[probe.rows[probe.half_steps], probe.cols[probe.half_steps]] = 1.0
    floor = np.array([SPEC.resolution_m**2, SPEC.resolution_m**2, step**2]) / 12
    sharp, flat = covariance_on(peaked), covariance_on(np.full(SPEC.shape, 0.5))
    for cov in (sharp, flat):
        assert np.all(np.linalg.eigvalsh(cov) > 0)
        assert np.all(np.diag(cov) >= floor - 1e-15)
    assert np.all(np.diag(flat)[:2] > 5 * np.diag(sharp)[:2])  # a flat map says nothing
    assert np.diag(flat)[2] > np.diag(sharp)[2]


def test_the_search_kernels_let_other_threads_run() -> None:
    """A wide search is seconds in one compiled call: it must not hold the GIL meanwhile (the
    matcher answers a match request on one thread while another tracks every robot)."""
    from scanflow.maps import maxpool
    from scanflow.matching import csm_search

    kernels = (csm_search._exhaustive, csm_search._branch_and_bound, maxpool._quantise_into,
               maxpool._pool)
    for kernel in kernels:
        assert kernel.targetoptions.get("nogil") is True, kernel.py_func.__name__


@given(st.floats(0.01, 0.2), st.floats(-9.0, 9.0))
def test_the_angular_step_moves_the_farthest_point_one_cell_at_any_distance(
    resolution_m: float, log10_far: float
) -> None:
    """The chord at the farthest point is one cell, even where 1 - cos underflows (a point
    1e7 cells out once gave a zero step, then a division by zero)."""
    far_m = max(10.0**log10_far, resolution_m)
    step = default_angular_step_rad(np.array([[far_m, 0.0]]), resolution_m)
    assert step > 0.0
    assert 2.0 * far_m * math.sin(step / 2.0) == pytest.approx(resolution_m, rel=1e-9)
