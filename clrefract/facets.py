"""The faces of a convex solid from its visual hull: the planes a polytope start begins with.

A visual hull from finitely many views is bounded by its silhouette cones, so over each flat
face of the object it lies as a low roof of facets tilted a few degrees each way. The convex
hull of the hull's surface, its facets merged where their normals lie within an angle (their
area-weighted mean normal), gives one plane per face, pushed out to the farthest point of its
facets; faces smaller than a share of the area (the corners the cones cut) are dropped.
"""

from __future__ import annotations

import numpy as np

from .errors import ClrefractError


def hull_surface(distance: np.ndarray, box) -> np.ndarray:
    """Points of the zero set of a signed distance on the nodes of `box` (+ inside)."""
    from skimage.measure import marching_cubes

    if not distance.min() < 0 < distance.max():
        raise ClrefractError("the visual hull has no surface in the box")
    spacing = tuple((np.asarray(box.hi) - np.asarray(box.lo)) / (np.asarray(distance.shape) - 1))
    verts = marching_cubes(distance, 0.0, spacing=spacing)[0]
    return verts + np.asarray(box.lo)


def merged_planes(
    points: np.ndarray, centre: np.ndarray, angle_deg: float, min_share: float
) -> np.ndarray:
    """Rows (n, d): unit outward normal n and offset d from `centre` (n . (x - centre) <= d
    inside), one per group of the convex hull's facets whose normals lie within angle_deg of
    the group's first (largest) facet, for groups of at least min_share of the area."""
    from scipy.spatial import ConvexHull

    hull = ConvexHull(points)
    tri = hull.points[hull.simplices]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    normals = hull.equations[:, :3]
    cos = np.cos(np.radians(angle_deg))
    seeds, sums, areas, members = [], [], [], []
    for i in np.argsort(-area):
        near = [k for k, s in enumerate(seeds) if s @ normals[i] > cos]
        if near:
            k = near[0]
            sums[k] += area[i] * normals[i]
            areas[k] += area[i]
            members[k].append(i)
        else:
            seeds.append(normals[i])
            sums.append(area[i] * normals[i])
            areas.append(area[i])
            members.append([i])
    total = float(area.sum())
    rows = []
    for s, a, m in sorted(zip(sums, areas, members), key=lambda g: -g[1]):
        if a < min_share * total:
            continue
        n = s / np.linalg.norm(s)
        d = float(np.max((tri[m].reshape(-1, 3) - centre) @ n))
        rows.append([*n, d])
    return np.asarray(rows)


def bounded(planes: np.ndarray) -> bool:
    """Whether the planes (n, d) close a solid about the centre: every direction meets one
    (the normals span all sides: no unit u with n . u <= 0 for all)."""
    from scipy.optimize import linprog

    if len(planes) < 4:
        return False
    n = planes[:, :3]
    # maximise the smallest margin t: u in [-1, 1]^3 with n . u <= -t for every plane
    res = linprog(
        [0, 0, 0, -1],
        A_ub=np.column_stack([n, np.ones(len(n))]),
        b_ub=np.zeros(len(n)),
        bounds=[(-1, 1)] * 3 + [(None, 1)],
    )
    return bool(res.status == 0 and -res.fun <= 1e-9)


def spread_normals(n: int) -> np.ndarray:
    """n unit normals spread evenly over the sphere (a golden-angle spiral)."""
    k = np.arange(n)
    z = 1.0 - (2.0 * k + 1.0) / n
    r = np.sqrt(np.maximum(0.0, 1.0 - z * z))
    a = k * np.pi * (3.0 - np.sqrt(5.0))
    return np.column_stack([r * np.cos(a), r * np.sin(a), z])
