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


def test_the_transposed_smoothing_is_the_adjoint_and_differs_at_the_edges():
    """<S x, y> = <x, S^T y> to rounding for a smoothing whose nearest-node edges make S
    unsymmetric (a gradient carried back through S needs S^T); S^T y differs from S y by
    more than rounding there."""
    rng = np.random.default_rng(3)
    shape, sigma = (9, 12, 7), (1.5, 3.0, 0.8)
    x, y = rng.normal(size=shape), rng.normal(size=shape)
    lhs = float(np.sum(gaussian_nodes(x, sigma) * y))
    rhs = float(np.sum(x * gaussian_nodes(y, sigma, transpose=True)))
    assert abs(lhs - rhs) <= 1e-12 * np.sum(np.abs(x)) * np.sum(np.abs(y)) / x.size
    assert np.abs(gaussian_nodes(y, sigma, True) - gaussian_nodes(y, sigma)).max() > 1e-3


def test_the_quasi_newton_preconditioner_is_s_and_carries_gradients_by_s_transposed():
    """The finish moves the grid by S z (fit/quasi_newton.py): its octaves run from the
    finest scale to a third of the box, each weighted so that S S^T g holds each octave
    at one largest magnitude, and `transposed` is S's adjoint."""
    from clrefract.fit.quasi_newton import Preconditioner, octaves

    assert octaves(2.0, 100.0) == [2.0, 4.0, 8.0, 16.0, 32.0]
    assert octaves(8.0, 20.0) == [8.0]
    rng = np.random.default_rng(5)
    shape = (10, 11, 12)
    g = rng.normal(size=np.prod(shape))
    s = Preconditioner(shape, (2.0, 2.0, 2.0), [2.0, 4.0, 8.0], g)
    assert s.weights.max() == 1.0 and np.all(s.weights > 0)
    x, y = rng.normal(size=g.size), rng.normal(size=g.size)
    assert float(s(x) @ y) == pytest.approx(float(x @ s.transposed(y)), rel=1e-12)
    tops = [
        w * w * np.abs(gaussian_nodes(gaussian_nodes(g.reshape(shape), sig, True), sig)).max()
        for w, sig in zip(s.weights, s.sigmas)
    ]
    assert np.allclose(tops, tops[0], rtol=1e-12), tops
