"""Likelihood field construction: the band splat equals a brute-force nearest-point field."""

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st
from scanflow.maps.field import field_from_means, field_values


def brute_force(shape, means, resolution_m, sigma_m, cutoff_m):
    rows, cols = np.mgrid[0 : shape[0], 0 : shape[1]]
    d_cells = np.hypot(rows[..., None] - means[:, 0], cols[..., None] - means[:, 1]).min(axis=-1)
    d = d_cells * resolution_m
    return np.where(d <= cutoff_m, np.exp(-0.5 * (d / sigma_m) ** 2), 0.0)


@settings(max_examples=40, deadline=None)
@given(
    seed=st.integers(0, 2**31),
    count=st.integers(1, 30),
    resolution_m=st.sampled_from([0.05, 0.1, 0.2]),
    sigma_cells=st.floats(0.5, 3.0),
    cutoff_sigmas=st.floats(1.0, 4.0),
)
def test_band_field_equals_brute_force(seed, count, resolution_m, sigma_cells, cutoff_sigmas):
    rng = np.random.default_rng(seed)
    shape = (25, 31)
    # Means anywhere, some off the grid: their band still reaches in.
    means = rng.uniform([-3, -3], [shape[0] + 2, shape[1] + 2], (count, 2))
    sigma_m = sigma_cells * resolution_m
    cutoff_m = cutoff_sigmas * sigma_m
    got = field_from_means(shape, means, resolution_m, sigma_m, cutoff_m)
    want = brute_force(shape, means, resolution_m, sigma_m, cutoff_m)
    # Only a mean exactly on the cut-off circle could differ (by rounding): tolerate none here.
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-12)


def test_integer_means_give_the_cell_centre_field():
    rng = np.random.default_rng(5)
    occupied = rng.random((40, 50)) < 0.02
    want = field_values(occupied, 0.05, 0.1, 0.4)
    got = field_from_means(occupied.shape, np.argwhere(occupied).astype(float), 0.05, 0.1, 0.4)
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-15)


def test_nothing_to_splat_gives_zeros():
    assert not field_from_means((4, 5), np.zeros((0, 2)), 0.05, 0.1, 0.4).any()
