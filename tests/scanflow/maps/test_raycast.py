"""Ray marking must give exactly the cells of the textbook integer Bresenham line."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scanflow.maps.grid import CellBox
from scanflow.maps.raycast import mark_rays


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
ray = st.tuples(coord, coord, coord, coord)


@settings(max_examples=200, deadline=None)
@given(rays=st.lists(ray, min_size=1, max_size=12), include_end=st.booleans())
def test_mark_rays_equals_reference_bresenham(rays, include_end):
    box = CellBox(-61, -61, 62, 62)
    mask = np.zeros(box.shape, dtype=bool)
    arr = np.array(rays, dtype=np.int64)
    mark_rays(mask, box, arr[:, :2], arr[:, 2:], include_end=include_end)
    expected = np.zeros(box.shape, dtype=bool)
    for r0, c0, r1, c1 in rays:
        cells = bresenham_reference(r0, c0, r1, c1)
        if not include_end:
            cells = cells[:-1]
        for r, c in cells:
            expected[r - box.row0, c - box.col0] = True
    np.testing.assert_array_equal(mask, expected)


def test_mark_rays_rejects_cells_outside_box():
    box = CellBox(0, 0, 10, 10)
    mask = np.zeros(box.shape, dtype=bool)
    with pytest.raises(ValueError, match="end_cells"):
        mark_rays(mask, box, np.array([[1, 1]]), np.array([[1, 10]]))
    assert not mask.any()


def test_mark_rays_rejects_wrong_mask_shape():
    with pytest.raises(ValueError, match="mask"):
        mark_rays(np.zeros((3, 3), bool), CellBox(0, 0, 4, 4), np.zeros((1, 2)), np.ones((1, 2)))
