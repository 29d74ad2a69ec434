"""Where a field bends light: a coarse grid of the cells where eta varies, as a distance
(in cells, Chebyshev) to the nearest such cell, for empty-space skipping in the tracer.

A ray in a cell at distance k >= 1 can fly straight (eta is constant there, so x'' = 0) to
the cell's far side and k - 1 cells further, in one move instead of steps. Built from eta
(the field's NumPy reference, or a tracer's device kernel: Tracer.field_occupancy) sampled
on a lattice `sub` samples per cell (the cells' corner samples shared with their
neighbours, so that any change of eta between two adjacent samples falls in a cell), a cell
is occupied where its samples differ, and the occupancy is dilated by `dilate` cells
against features narrower than the sample spacing.
"""

from __future__ import annotations

import numpy as np
from scipy.ndimage import binary_dilation, distance_transform_cdt

from .fields.base import Box, Field


def occupied_cells(
    field: Field, box: Box, res: int = 32, sub: int = 4, dilate: int = 1, eval_fn=None
):
    """Boolean (res, res, res): cells where eta is not constant, dilated. `eval_fn`: pts ->
    (eta, grad eta) in place of the field's NumPy reference (a tracer's device kernel: a
    hash grid's 129^3 samples take 31 s in NumPy, 2 s on the 2-core CPU device)."""
    evaluate = eval_fn or field.eval
    n = res * sub + 1
    axes = [np.linspace(lo, hi, n) for lo, hi in zip(box.lo, box.hi)]
    occ = np.zeros((res, res, res), bool)
    # one slab of cells along x at a time: bounded memory for fine lattices
    for i in range(res):
        xs = axes[0][i * sub : (i + 1) * sub + 1]
        pts = np.stack(np.meshgrid(xs, axes[1], axes[2], indexing="ij"), -1).reshape(-1, 3)
        eta = evaluate(pts)[0].reshape(len(xs), n, n)
        hi = _cell_extreme(_cell_extreme(eta.max(0), sub, 0, np.maximum), sub, 1, np.maximum)
        lo = _cell_extreme(_cell_extreme(eta.min(0), sub, 0, np.minimum), sub, 1, np.minimum)
        occ[i] = hi > lo
    if dilate > 0:
        occ = binary_dilation(occ, iterations=dilate)
    return occ


def _cell_extreme(a: np.ndarray, sub: int, axis: int, op) -> np.ndarray:
    """op over each cell's samples along `axis`: samples k sub .. (k + 1) sub, both corners
    included (a corner belongs to the cells on either side of it)."""
    a = np.moveaxis(a, axis, 0)
    cells = (a.shape[0] - 1) // sub
    inner = op.reduce(a[:-1].reshape(cells, sub, *a.shape[1:]), axis=1)
    return np.moveaxis(op(inner, a[sub::sub]), 0, axis)


def empty_distance(
    field: Field, box: Box, res: int = 32, sub: int = 4, dilate: int = 1, eval_fn=None
):
    """int32 (res, res, res): 0 in occupied cells, else the Chebyshev distance in cells to
    the nearest occupied one (res + 1 where nothing is occupied)."""
    return distance_of(occupied_cells(field, box, res, sub, dilate, eval_fn))


def distance_of(occ: np.ndarray) -> np.ndarray:
    """The tracer's grid for a boolean occupancy (see empty_distance)."""
    if not occ.any():
        return np.full(occ.shape, occ.shape[0] + 1, np.int32)
    return distance_transform_cdt(~occ, metric="chessboard").astype(np.int32)


# --- what may vary while a field trains ------------------------------------------------------
# Node grids (voxel, level set) are interpolated from the nodes within `reach` node spacings
# of a point: the tricubic B-spline's support is 2 spacings, the others' 1. A cell's values
# are therefore bounded by the nodes whose supports overlap it, which gives an occupancy
# that holds for any change of the nodes that the bound allows, with no sampling.
REACH = {"bspline": 2, "trilinear": 1, "smoothstep": 1}


def cell_reduce(nodes: np.ndarray, node_box: Box, box: Box, res: int, reach: int, op):
    """(res, res, res): op (np.min, np.max) of the node values whose interpolation support
    reaches each cell of a res^3 grid over box; separable, one axis at a time. A cell's
    window of w nodes is the op of two overlapping blocks of 2^floor(log2 w) nodes (a
    sparse table): at 128^3 cells over 64^3 nodes, 4x faster than a loop over the cells."""
    ufunc = {np.min: np.minimum, np.max: np.maximum}[op]
    out = np.asarray(nodes)
    for ax in range(3):
        n = out.shape[ax]
        h = (node_box.hi[ax] - node_box.lo[ax]) / (n - 1)
        edges = np.linspace(box.lo[ax], box.hi[ax], res + 1)
        # nodes i with x_i - reach h < cell_hi and x_i + reach h > cell_lo (a margin of
        # 1e-9 h against rounding: including one more node only widens the bound)
        first = np.ceil((edges[:-1] - node_box.lo[ax]) / h - reach - 1e-9).astype(int)
        last = np.floor((edges[1:] - node_box.lo[ax]) / h + reach + 1e-9).astype(int)
        first, last = np.clip(first, 0, n - 1), np.clip(last, 0, n - 1)
        power = np.floor(np.log2(last - first + 1)).astype(int)
        block = np.moveaxis(out, ax, 0)  # block[i]: op of nodes i .. i + 2^j - 1
        red = np.empty((res,) + block.shape[1:], block.dtype)
        for j in range(int(power.max()) + 1):
            if j:
                block = ufunc(block[: -(1 << (j - 1))], block[1 << (j - 1) :])
            cells = np.flatnonzero(power == j)
            if len(cells):
                red[cells] = ufunc(block[first[cells]], block[last[cells] - (1 << j) + 1])
        out = np.moveaxis(red, 0, ax)
    return out


def live_cells_nodes(free: np.ndarray, field, box: Box, res: int, dilate: int = 1):
    """Cells that a trainable node (free, the node grid's shape) can change: its support."""
    reach = REACH[getattr(field, "interp", "bspline")]
    live = cell_reduce(free.astype(np.int8), field.box, box, res, reach, np.max) > 0
    return binary_dilation(live, iterations=dilate) if dilate > 0 else live


def live_cells_levelset(field, box: Box, res: int, slack: float, dilate: int = 1):
    """Cells where a level set's eta may vary while no phi node moves by more than `slack`
    mm: its band |phi| < w/2 + slack can reach them (phi in a cell lies between its nodes'
    extremes), or the solid reaches the box window there (eta = 1 + W (n - 1) inside)."""
    c = field.width / 2 + slack
    lo = cell_reduce(field.phi, field.box, box, res, 2, np.min)
    hi = cell_reduce(field.phi, field.box, box, res, 2, np.max)
    band = (lo < c) & (hi > -c)
    # the window varies within 2 margins of the walls
    wall = np.zeros((res,) * 3, bool)
    for ax in range(3):
        e = np.linspace(box.lo[ax], box.hi[ax], res + 1)
        m = 2 * field.box.margin
        near = (e[:-1] < field.box.lo[ax] + m) | (e[1:] > field.box.hi[ax] - m)
        shape = [1, 1, 1]
        shape[ax] = res
        wall |= near.reshape(shape)
    live = band | (wall & (lo < c))
    return binary_dilation(live, iterations=dilate) if dilate > 0 else live


def exact_live_cells(field, box: Box, res: int) -> np.ndarray:
    """Cells whose skipping leaves every parameter's gradient exact: a level set's band
    (off it eta is flat whatever the nodes do); for other fields every cell (a parameter
    changes eta where it is flat too)."""
    from .fields.levelset import LevelSetField

    if isinstance(field, LevelSetField):
        return live_cells_levelset(field, box, res, 0.0)
    return np.ones((res,) * 3, bool)
