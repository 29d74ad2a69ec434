"""Straight-ray emission-absorption compositing on the host, in float64, for a model that gives
density and colour at points (the neural Meridian-style baseline, clrefract.baselines.neural).

The same rules as kernels_cl/straight_volume.cl: a ray is cut where it crosses the box into
m = ceil(length / step) equal segments of length dt, sampled at their middles, and
    alpha_i = 1 - exp(-sigma_i dt),  T_i = prod_{j<i} (1 - alpha_j),
    C = sum_i T_i alpha_i c_i + T_m bg.
Reverse: dC/dc_i = T_i alpha_i, dC/dsigma_i = dt (T_{i+1} c_i - R_{i+1}) with R_{i+1} the light
reaching the camera from behind sample i. The forward pass keeps every sample (they are placed
before their densities are known); the reverse drops samples reached by less than T_STOP of
the light, as the grid kernel's march stops there (their gradient is below T_STOP's scale).
"""

from __future__ import annotations

import numpy as np

from ..samples import Samples
from ..samples import ray_samples as ray_samples  # re-exported: the samples composite() takes

T_STOP = 1e-5  # kernels_cl/straight_volume.cl's


def _exclusive_cumsum(x: np.ndarray, s: Samples) -> np.ndarray:
    """Per ray, the sum of x over the ray's earlier samples (x (P,) or (P, k))."""
    c = np.cumsum(x, axis=0)
    c = np.concatenate([np.zeros((1,) + x.shape[1:]), c])
    return c[:-1] - c[s.starts[:-1]][s.ray]


def composite(sigma: np.ndarray, rgb: np.ndarray, s: Samples, bg: np.ndarray):
    """Colour (n, 3) and light left (n,) of the rays in front of background radiance bg."""
    n = len(s.dt)
    tau = sigma * s.dt[s.ray]
    T = np.exp(-_exclusive_cumsum(tau, s))
    w = T * -np.expm1(-tau)  # T_i alpha_i
    colour = np.stack([np.bincount(s.ray, w * rgb[:, k], minlength=n) for k in range(3)], 1)
    left = np.exp(-np.bincount(s.ray, tau, minlength=n))
    return colour + left[:, None] * bg, left


def composite_backward(sigma, rgb, s: Samples, colour: np.ndarray, dl_dc: np.ndarray):
    """dLoss/dsigma (P,) and dLoss/drgb (P, 3) given each ray's colour and dLoss/dcolour,
    and the samples that matter (P,) bool: reached by T_STOP of the light or more, on rays
    with a gradient."""
    tau = sigma * s.dt[s.ray]
    T = np.exp(-_exclusive_cumsum(tau, s))
    alpha = -np.expm1(-tau)
    w = T * alpha
    wc = w[:, None] * rgb
    behind = colour[s.ray] - _exclusive_cumsum(wc, s) - wc  # R_{i+1}
    g = dl_dc[s.ray]
    d_sigma = s.dt[s.ray] * (((T * (1 - alpha))[:, None] * rgb - behind) * g).sum(1)
    live = (T >= T_STOP) & np.any(g != 0, axis=1)
    return d_sigma, w[:, None] * g, live
