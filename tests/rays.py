"""Shared ray sets of the Snell renderer tests."""

import numpy as np


def unit(a):
    return a / np.linalg.norm(a, axis=-1, keepdims=True)


def camera_rays(n, spread, center=(0.0, 0.0, 0.0), seed=0, dist=200.0):
    """Origins on a sphere of radius dist about the origin, aimed at uniform points of the box
    center +- spread (a number or three)."""
    rng = np.random.default_rng(seed)
    o = dist * unit(rng.normal(size=(n, 3)))
    return o, np.asarray(center) + rng.uniform(-1, 1, (n, 3)) * np.asarray(spread) - o
