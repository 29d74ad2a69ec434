"""The visual hull tightened: the least-area shape inside it that every mask ray still meets.

A hull from finitely many views is the largest shape their silhouettes allow. Over a flat
face it rises in a roof of cone facets (up to 3 mm on the quick protocol's rounded cube), and
glass refracts by its normals, so the roof bends every ray that crosses it. The object's edges
lie on the silhouettes of many views and are held there; its faces between them are not.
Mean-curvature flow lowers area: run inside the hull, with the shape pushed back wherever a
ray through a mask stops meeting it, it flattens the roofs onto the faces between the edges.
That is exact for convex polyhedra whose edges the views see as rims; a curved surface sags
between rims by their sagitta.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage

from .fields.base import Box
from .hull import Hull
from .samples import ray_samples

RIM_PIXELS = 3  # rays this close to a mask's edge hold the shape; inside it they rarely bind
INTERIOR_SHARE = 0.1  # of the rays deeper inside a mask, checked too (thin parts)
DEPTH = 0.1  # cells a ray must reach into the shape (at most half the hull's depth on it)
# mean-curvature flow times in mm^2 at which the flow's shape is taken (110: 800 steps of
# 0.15 cell^2 at 0.95 mm): a roof's height falls as its face's width squared over the time, so
# large faces need the longer flows; curved surfaces sag between rims with them
FLOW_TIMES = (110.0, 330.0)
PUSH_GAIN = 8.0
CHECK_EVERY = 5  # flow steps between checks of the rays
MAX_RES = 64  # finer grids take the flow of this one (its steps grow as 1 / cell^2)
MARGIN = 3.0  # cells outside the hull where a ray's samples are kept (RayDepths)


def tighten(hull: Hull, box: Box, cameras, masks, seed: int = 0, times=FLOW_TIMES) -> list:
    """The hull (on its grid over `box`) tightened by silhouette-held curvature flow: one
    Hull per flow time in `times` (increasing), all from one flow."""
    fine = hull.distance.shape
    if max(fine) <= MAX_RES:
        return _tighten(hull, box, cameras, masks, seed, times)
    coarse = tuple(min(n, MAX_RES) for n in fine)
    down = _resampled(hull.distance, coarse)
    width = hull.width * (max(fine) - 1) / (max(coarse) - 1)
    tight = _tighten(Hull(down, width, hull.mask_fraction), box, cameras, masks, seed, times)
    up = [np.minimum(hull.distance, _resampled(t.distance, fine)) for t in tight]
    return [Hull(d, hull.width, hull.mask_fraction) for d in up]


def _resampled(grid: np.ndarray, shape) -> np.ndarray:
    """A node grid over the same box at another node count, trilinear."""
    axes = [np.linspace(0, n - 1, m) for n, m in zip(grid.shape, shape)]
    coords = np.stack(np.meshgrid(*axes, indexing="ij"))
    return ndimage.map_coordinates(grid, coords, order=1, mode="nearest")


def _tighten(hull: Hull, box: Box, cameras, masks, seed: int, times) -> list:
    res = hull.distance.shape
    h = (np.asarray(box.hi) - np.asarray(box.lo)) / (np.asarray(res) - 1)
    bound = hull.distance
    rays = RayDepths(
        box,
        res,
        *mask_edge_rays(cameras, masks, seed),
        0.5 * float(h.min()),
        bound,
        MARGIN * hull.width,
    )
    need = rays.deepest(bound)[0]
    rays.keep(need > 0)  # a ray the hull itself misses (a tolerated hole) asks nothing
    want = np.minimum(DEPTH * hull.width, 0.5 * need[need > 0])
    d = bound.copy()
    dt = 0.15 * float(h.min()) ** 2
    out, step = [], 0
    for time in times:
        steps = max(int(round(time / dt)), CHECK_EVERY)
        while step < steps:
            step += 1
            d = np.minimum(bound, d + dt * _curvature_motion(d, h))
            if step % CHECK_EVERY == 0:
                depth, at = rays.deepest(d)
                short = depth < want
                if short.any():
                    d = np.minimum(bound, d + _push(res, at[short], want[short] - depth[short]))
        out.append(Hull(_redistanced(d, h), hull.width, hull.mask_fraction))
    return out


def mask_edge_rays(cameras, masks, seed: int):
    """Rays of the pixels near each mask's edge, and a share of those inside it."""
    rng = np.random.default_rng(seed)
    origins, dirs = [], []
    for cam, mask in zip(cameras, masks):
        inner = ndimage.binary_erosion(mask, iterations=RIM_PIXELS)
        pick = (mask & ~inner).ravel() | (inner.ravel() & (rng.random(mask.size) < INTERIOR_SHARE))
        o, d = cam.rays()
        origins.append(o[pick])
        dirs.append(d[pick])
    return np.concatenate(origins), np.concatenate(dirs)


class RayDepths:
    """The largest value a grid takes along each ray across the box, and where. The rays'
    samples are made once, and only those where `bound` is above -`margin` are kept: the
    flow's shape stays under the hull, so it peaks elsewhere unless it left the ray by more
    than the margin (the pushes keep it on every ray). Rays with no sample kept peak at
    -inf."""

    def __init__(self, box: Box, res, origins, dirs, spacing: float, bound, margin: float):
        near, far = box.ray_span(origins, dirs)
        hit = far > np.maximum(near, 0.0)
        origins, dirs = origins[hit], dirs[hit]
        scale = (np.asarray(res) - 1) / box.size
        coords, rays = [], []
        chunk = 8192  # rays at a time: bounded temporaries
        for a in range(0, len(origins), chunk):
            s = ray_samples(origins[a : a + chunk], dirs[a : a + chunk], box, spacing)
            g = (s.points - np.asarray(box.lo)) * scale
            near_hull = ndimage.map_coordinates(bound, g.T, order=1, mode="nearest") > -margin
            coords.append(g[near_hull])
            rays.append(s.ray[near_hull] + a)
        self.g = np.concatenate(coords) if coords else np.empty((0, 3))
        self._weights = trilinear_matrix(self.g, tuple(res))
        self._set(np.concatenate(rays) if rays else np.empty(0, np.int64), len(origins))

    def _set(self, ray: np.ndarray, n: int) -> None:
        self.ray, self.n = ray, n  # samples come ray by ray
        self.rays, self.starts = np.unique(ray, return_index=True)

    def keep(self, which: np.ndarray) -> None:
        kept = which[self.ray]
        new_id = np.cumsum(which) - 1
        self.g = self.g[kept]
        self._weights = self._weights[kept]
        self._set(new_id[self.ray[kept]], int(which.sum()))

    def deepest(self, grid: np.ndarray):
        value, where = np.full(self.n, -np.inf), np.zeros((self.n, 3))
        if len(self.ray) == 0:
            return value, where
        v = self._weights @ grid.ravel()
        value[self.rays] = np.maximum.reduceat(v, self.starts)
        at = np.flatnonzero(v == value[self.ray])
        first = at[np.unique(self.ray[at], return_index=True)[1]]
        where[self.ray[first]] = self.g[first]
        return value, where


def trilinear_matrix(g: np.ndarray, shape: tuple):
    """Sparse (points, nodes) matrix whose product with a grid is its trilinear value at the
    points g (node coordinates; beyond the edge, the edge's: map_coordinates' order=1,
    mode="nearest"). The flow checks its rays every few steps at the same points: on the
    quick sphere (2.5 million samples) a product takes 24 ms, map_coordinates 155 ms."""
    from scipy.sparse import csr_matrix

    top = np.asarray(shape) - 1
    g = np.clip(g, 0, top)
    base = np.minimum(np.floor(g).astype(np.int64), np.maximum(top - 1, 0))
    f = g - base
    stride = np.array([shape[1] * shape[2], shape[2], 1])
    flat = base @ stride
    cols = np.empty((len(g), 8), np.int64)
    vals = np.empty((len(g), 8))
    for k, corner in enumerate(np.ndindex(2, 2, 2)):  # x slowest: columns in order
        off = np.array(corner)
        cols[:, k] = flat + off @ stride
        vals[:, k] = np.prod(np.where(off, f, 1 - f), axis=1)
    n_nodes = int(np.prod(shape))  # a 1-node axis's far corner (weight 0) kept in range
    return csr_matrix(
        (vals.ravel(), np.minimum(cols, n_nodes - 1).ravel(), np.arange(0, 8 * len(g) + 1, 8)),
        shape=(len(g), n_nodes),
    )


def _curvature_motion(d: np.ndarray, h) -> np.ndarray:
    """|grad d| div(grad d / |grad d|): the speed that shrinks a level set by its curvature."""
    g = np.gradient(d, *h)
    norm = np.sqrt(g[0] ** 2 + g[1] ** 2 + g[2] ** 2 + 1e-8)
    return norm * sum(np.gradient(g[a] / norm, h[a], axis=a) for a in range(3))


def _push(res, at: np.ndarray, amount: np.ndarray) -> np.ndarray:
    """Raise the grid around each short ray's deepest point by what it lacks (mean of the
    rays sharing a node), spread over a cell so the surface stays smooth."""
    push, weight = np.zeros(res), np.zeros(res)
    base = np.floor(at).astype(int)
    frac = at - base
    for corner in np.ndindex(2, 2, 2):
        off = np.array(corner)
        w = np.prod(np.where(off, frac, 1 - frac), axis=1)
        j = np.clip(base + off, 0, np.asarray(res) - 1)
        np.add.at(push, tuple(j.T), w * amount)
        np.add.at(weight, tuple(j.T), w)
    push = np.where(weight > 0, push / np.maximum(weight, 1e-12), 0.0)
    return PUSH_GAIN * ndimage.gaussian_filter(push, 1.0)


def _redistanced(d: np.ndarray, h) -> np.ndarray:
    """A signed distance in mm with d's zero level: d / |grad d| near it (the flow leaves
    |grad d| off 1), the distance transform of the inside further out."""
    g = np.gradient(d, *h)
    local = d / np.maximum(np.sqrt(g[0] ** 2 + g[1] ** 2 + g[2] ** 2), 0.05)
    inside = d > 0
    cell = float(np.mean(h))
    far = ndimage.distance_transform_edt(inside, sampling=h) - ndimage.distance_transform_edt(
        ~inside, sampling=h
    )
    far = far - np.sign(far) * 0.5 * cell
    return np.where(np.abs(local) < 2.5 * cell, local, far)
