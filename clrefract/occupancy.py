"""Where a field bends light: a coarse grid of the cells where eta varies, as a distance
(in cells, Chebyshev) to the nearest such cell, for empty-space skipping in the tracer.

A ray in a cell at distance k >= 1 can fly straight (eta is constant there, so x'' = 0) to
the cell's far side and k - 1 cells further, in one move instead of steps. Built from the
field's NumPy reference: eta sampled on a lattice `sub` samples per cell (the cells'
corner samples shared with their neighbours, so that any change of eta between two adjacent
samples falls in a cell), a cell is occupied where its samples differ, and the occupancy is
dilated by `dilate` cells against features narrower than the sample spacing.
"""

from __future__ import annotations

import numpy as np
from scipy.ndimage import binary_dilation, distance_transform_cdt

from .fields.base import Box, Field


def occupied_cells(field: Field, box: Box, res: int = 32, sub: int = 4, dilate: int = 1):
    """Boolean (res, res, res): cells where eta is not constant, dilated."""
    n = res * sub + 1
    axes = [np.linspace(lo, hi, n) for lo, hi in zip(box.lo, box.hi)]
    occ = np.zeros((res, res, res), bool)
    # one slab of cells along x at a time: bounded memory for fine lattices
    for i in range(res):
        xs = axes[0][i * sub : (i + 1) * sub + 1]
        pts = np.stack(np.meshgrid(xs, axes[1], axes[2], indexing="ij"), -1).reshape(-1, 3)
        eta = field.eval(pts)[0].reshape(len(xs), n, n)
        hi = eta.max(0)
        lo = eta.min(0)
        # per cell in y and z: the samples from its lower to its upper corner
        for j in range(res):
            sl = slice(j * sub, (j + 1) * sub + 1)
            h = hi[sl].reshape(sub + 1, res * sub + 1)
            lw = lo[sl].reshape(sub + 1, res * sub + 1)
            hmax, lmin = h.max(0), lw.min(0)
            for k in range(res):
                kk = slice(k * sub, (k + 1) * sub + 1)
                occ[i, j, k] = hmax[kk].max() > lmin[kk].min()
    if dilate > 0:
        occ = binary_dilation(occ, iterations=dilate)
    return occ


def empty_distance(field: Field, box: Box, res: int = 32, sub: int = 4, dilate: int = 1):
    """int32 (res, res, res): 0 in occupied cells, else the Chebyshev distance in cells to
    the nearest occupied one (res + 1 where nothing is occupied)."""
    occ = occupied_cells(field, box, res, sub, dilate)
    if not occ.any():
        return np.full(occ.shape, res + 1, np.int32)
    return distance_transform_cdt(~occ, metric="chessboard").astype(np.int32)
