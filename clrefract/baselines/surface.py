"""The straight-ray baselines' surface for the chamfer distance (they have no index): marching
cubes of density at half its 99.9th percentile over a node grid. A fixed absorption level
(ln 2 per cell, say) depends on the grid and was never reached by fits that render glass as a
thin, faint shell; the percentile keeps a few floaters from setting the level."""

from __future__ import annotations

import numpy as np

from ..fields.base import Box


def density_level(density: np.ndarray) -> float:
    """The documented surface rule: half the density's 99.9th percentile over the nodes."""
    return 0.5 * float(np.percentile(density, 99.9))


def density_surface(vol: np.ndarray, box: Box):
    """Vertices (mm) and faces of the rule's level set of density on res^3 nodes spanning the
    box (x slowest), or None when the level is not crossed."""
    from skimage.measure import marching_cubes

    level = density_level(vol)
    if not (level > 0 and vol.min() < level < vol.max()):
        return None
    spacing = tuple(float(h) for h in box.size / (np.asarray(vol.shape) - 1))
    verts, faces, _, _ = marching_cubes(vol, level, spacing=spacing)
    return verts + np.asarray(box.lo), faces
