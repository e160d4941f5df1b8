"""Rays must be exactly the cells of the textbook integer Bresenham line, and of the rounding
formula the grid traced with before."""

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st
from scanflow.maps.raycast import ray_length, trace_ray


def bresenham_reference(r0: int, c0: int, r1: int, c1: int) -> list[tuple[int, int]]:
    """Classic all-octant integer Bresenham (x = col, y = row), both ends included."""
    dx, sx = abs(c1 - c0), (1 if c0 < c1 else -1)
    dy, sy = -abs(r1 - r0), (1 if r0 < r1 else -1)
    err = dx + dy
    cells = []
    while True:
        cells.append((r0, c0))
        if r0 == r1 and c0 == c1:
            return cells
        e2 = 2 * err
        if e2 >= dy:
            err += dy
            c0 += sx
        if e2 <= dx:
            err += dx
            r0 += sy


coord = st.integers(-60, 60)
cell = st.tuples(coord, coord)


def rounded_cells(r0: int, c0: int, r1: int, c1: int) -> list[tuple[int, int]]:
    """The ray as the grid traced it until 2d18b1b: cell k of n = max(|dr|, |dc|) is
    a + round(k * (b - a) / n), halves rounded away from zero; both ends included."""
    dr, dc = r1 - r0, c1 - c0
    n = max(abs(dr), abs(dc))
    den = 2 * max(n, 1)
    cells = []
    for k in range(n + 1):
        a, b = k * dr, k * dc
        step_r, step_c = (2 * abs(a) + n) // den, (2 * abs(b) + n) // den
        cells.append((r0 + (-step_r if a < 0 else step_r), c0 + (-step_c if b < 0 else step_c)))
    return cells


def traced(r0: int, c0: int, r1: int, c1: int) -> list[tuple[int, int]]:
    cells = np.full((ray_length(r0, c0, r1, c1) + 1, 2), -999, dtype=np.int64)
    count = trace_ray(cells, r0, c0, r1, c1)
    assert count == ray_length(r0, c0, r1, c1) and (cells[count] == -999).all()
    return [tuple(c) for c in cells[:count].tolist()]


@settings(max_examples=300, deadline=None)
@given(start=cell, end=cell)
def test_a_ray_is_the_reference_bresenham_line(start, end):
    assert traced(*start, *end) == bresenham_reference(*start, *end)


def test_every_short_ray_is_the_one_the_grid_traced_before() -> None:
    """All rays from a cell to the 33 x 33 cells around it: the same cells as the rounding
    formula the grid used until 2d18b1b, so maps come out bit for bit as before."""
    for dr in range(-16, 17):
        for dc in range(-16, 17):
            assert traced(3, -2, 3 + dr, -2 + dc) == rounded_cells(3, -2, 3 + dr, -2 + dc)
