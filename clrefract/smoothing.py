"""Gaussian smoothing of a node grid (a descent's gradient), applied as one small matrix per
axis: SciPy's 1-D filter (mode "nearest") written out as an n x n matrix once, then BLAS.
On a 64^3 grid at 5 nodes this is 4 times faster than `scipy.ndimage.gaussian_filter`, whose
41-tap loops were a quarter of an interface step's time; the results agree to rounding."""

from __future__ import annotations

from functools import lru_cache

import numpy as np


@lru_cache(maxsize=32)
def _axis_matrix(n: int, sigma: float) -> np.ndarray:
    from scipy.ndimage import gaussian_filter1d

    m = np.ascontiguousarray(gaussian_filter1d(np.eye(n), sigma, axis=0, mode="nearest"))
    m.setflags(write=False)  # shared by every call of this size and sigma
    return m


def gaussian_nodes(grid: np.ndarray, sigma_cells, transpose: bool = False) -> np.ndarray:
    """`grid` (3-D) smoothed by a Gaussian of sigma_cells nodes (a number, or one per axis),
    its edges extended by their nearest node: `gaussian_filter(grid, sigma_cells,
    mode="nearest")`. An axis of sigma 0 is left as it is. transpose: the smoothing's
    transpose (the edges make it differ), which carries a gradient back through it."""
    sig = np.broadcast_to(np.asarray(sigma_cells, np.float64), (grid.ndim,))
    out = np.asarray(grid, np.float64)
    for axis in range(grid.ndim):
        if sig[axis] > 1e-15:  # as SciPy: no smoothing along an axis of sigma 0
            m = _axis_matrix(out.shape[axis], round(float(sig[axis]), 12))
            m = m.T if transpose else m
            out = np.moveaxis(np.tensordot(m, out, axes=([1], [axis])), 0, axis)
    return np.ascontiguousarray(out)
