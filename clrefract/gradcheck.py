"""Gradient checks against central differences of the discretised forward renderer: a
smooth environment, a small lens on a voxel grid, and directional differences. Used by
`clrefract bench`, tools/bench_adjoint_modes.py and the gradient tests."""

from __future__ import annotations

import numpy as np

from .envmap import EnvMap, pixel_directions
from .loss import photometric_loss


def smooth_env(width: int = 2048) -> EnvMap:
    """A smooth analytic environment at high resolution: the loss is smooth enough for
    finite differences (bilinear texel kinks are far below the difference's size)."""
    d = pixel_directions(width, width // 2)
    img = np.stack(
        [
            1 + 0.5 * np.sin(3 * d[..., 0] + 1) * np.cos(2 * d[..., 2]),
            1 + 0.5 * np.cos(4 * d[..., 1]),
            1 + 0.3 * d[..., 2],
        ],
        -1,
    )
    return EnvMap(img * 0.4)


def lens_scene(n_rays: int = 300, res: int = 12, seed: int = 0):
    """A Gaussian lens with noise on a res^3 grid over [-50, 50]^3 mm, rays along +z
    through it, the smooth environment, and targets from slightly perturbed directions.
    Returns (values, origins, directions, env, targets)."""
    rng = np.random.default_rng(seed)
    ax = np.linspace(-50, 50, res)
    X, Y, Z = np.meshgrid(ax, ax, ax, indexing="ij")
    vals = 1 + 0.3 * np.exp(-(X**2 + Y**2 + Z**2) / (2 * 18**2))
    vals += 0.02 * rng.normal(size=X.shape)
    o = np.column_stack([rng.uniform(-30, 30, (n_rays, 2)), np.full(n_rays, -150.0)])
    d = np.column_stack([rng.normal(0, 0.05, (n_rays, 2)), np.ones(n_rays)])
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    env = smooth_env()
    target = env.lookup(d + rng.normal(0, 0.02, d.shape)).astype(np.float64)
    return vals, o, d, env, target


def directional_errors(eng, o, d, env, target, grad, p0, directions, eps):
    """Relative error of <grad, u> against (J(p0 + eps u) - J(p0 - eps u)) / 2 eps for each
    direction u, J being the forward renderer's loss; leaves the engine at p0."""

    def loss(p):
        eng.set_params(p)
        tr = eng.tracer.trace(o, d)
        ok = (tr.status == 0).astype(float)
        return photometric_loss(env, tr.last_velocity, target, weight=ok)[0]

    errs = []
    for u in directions:
        fd = (loss(p0 + eps * u) - loss(p0 - eps * u)) / (2 * eps)
        errs.append(abs(fd - grad @ u) / abs(fd))
    eng.set_params(p0)
    return np.array(errs)
