"""The descent's node smoothing against SciPy's own Gaussian filter."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.ndimage import gaussian_filter

from clrefract.smoothing import gaussian_nodes


@pytest.mark.parametrize(
    "shape, sigma",
    [((64, 64, 64), 5.0), ((17, 9, 30), (2.5, 0.7, 11.0)), ((8, 12, 5), (0.0, 3.0, 40.0))],
)
def test_the_node_smoothing_is_scipys_gaussian_filter(shape, sigma):
    """Anisotropic grids and sigmas, an axis left unsmoothed (sigma 0), and a sigma wider
    than its axis (the nearest-node edges carry the whole kernel): equal to
    gaussian_filter(mode="nearest") to 1e-12 of the largest value."""
    rng = np.random.default_rng(len(shape) + int(np.sum(sigma)))
    grid = rng.normal(size=shape)
    grid[np.abs(grid) < 1.0] = 0.0  # sparse, as a batch's gradient is
    want = gaussian_filter(grid, sigma, mode="nearest")
    got = gaussian_nodes(grid, sigma)
    assert got.shape == shape
    assert np.abs(got - want).max() <= 1e-12 * np.abs(want).max()


def test_the_node_smoothing_leaves_its_input_and_a_constant_alone():
    grid = np.full((6, 7, 8), 2.5)
    before = grid.copy()
    assert np.allclose(gaussian_nodes(grid, 3.0), 2.5, rtol=0, atol=1e-12)
    assert np.array_equal(grid, before)
