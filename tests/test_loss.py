"""The photometric loss gradient against central finite differences."""

import numpy as np
import pytest

from clrefract.envmap import EnvMap
from clrefract.loss import envmap_lookup_jacobian, photometric_loss


def _env():
    return EnvMap.procedural(width=256, height=128, seed=3)


def test_lookup_matches_envmap_and_jacobian_matches_fd():
    env = _env()
    rng = np.random.default_rng(0)
    d = rng.normal(size=(300, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    rad, jac = envmap_lookup_jacobian(env, d)
    assert np.abs(rad - env.lookup(d)).max() < 1e-5 * max(1.0, np.abs(rad).max())
    eps = 1e-5  # well inside a texel (0.025 rad); the float32 lookup limits how small
    scale = np.abs(jac).max()
    for k in range(3):
        e = np.zeros(3)
        e[k] = eps
        # along tangent directions only: the lookup ignores |d|
        fd = (env.lookup(d + e).astype(np.float64) - env.lookup(d - e)) / (2 * eps)
        proj = jac[:, :, k] - np.einsum("nc,n->nc", np.einsum("ncj,nj->nc", jac, d), d[:, k])
        fd_proj = fd  # lookup normalises, so its FD is already tangential
        ok = np.abs(proj - fd_proj) < 1e-3 * scale
        assert ok.mean() > 0.97  # a few samples straddle texel edges (bilinear kinks)


@pytest.mark.parametrize("space", ["srgb", "linear"])
def test_loss_gradient_matches_fd_along_random_directions(space):
    env = _env()
    rng = np.random.default_rng(1)
    v = rng.normal(size=(200, 3)) * 1.3
    target = env.lookup(rng.normal(size=(200, 3))).astype(np.float64)
    loss, g, _ = photometric_loss(env, v, target, space=space)
    hits = 0
    for _ in range(10):
        u = rng.normal(size=v.shape) * 1e-7
        fd = (
            photometric_loss(env, v + u, target, space=space)[0]
            - photometric_loss(env, v - u, target, space=space)[0]
        )
        hits += abs(fd / 2 - (g * u).sum()) < 1e-3 * abs((g * u).sum()) + 1e-15
    assert hits >= 9


def test_dark_rays_cost_their_target_and_carry_no_adjoint():
    """Trapped and non-finite rays render black: the loss counts them as black (trapping a
    ray must not lower it) and gives them no adjoint, even where v is not finite."""
    from clrefract.loss import srgb

    env = _env()
    rng = np.random.default_rng(2)
    v = rng.normal(size=(50, 3))
    v[3] = np.nan
    target = env.lookup(rng.normal(size=(50, 3))).astype(np.float64)
    dark = np.zeros(50, bool)
    dark[[3, 7, 11]] = True
    loss, g, rad = photometric_loss(env, v, target, dark=dark)
    lit, _, _ = photometric_loss(env, v[~dark], target[~dark])
    black = (srgb(target[dark])[0] ** 2).sum()
    assert loss == pytest.approx((lit * 47 * 3 + black) / (50 * 3), rel=1e-12)
    assert np.all(rad[dark] == 0) and np.all(g[dark] == 0) and np.all(np.isfinite(g))
    # left out instead (weight 0), the same rays would lower the loss
    assert photometric_loss(env, np.where(dark[:, None], 1.0, v), target, weight=~dark)[0] < loss


def test_block_loss_is_the_error_of_block_means_and_its_gradient_matches_fd():
    """Rays compared by groups of 4: the loss is the squared error of the group means (zero
    when only the pixels inside a block trade places), and dJ/dv matches central differences."""
    from clrefract.loss import srgb

    env = _env()
    rng = np.random.default_rng(4)
    v = rng.normal(size=(200, 3))
    target = env.lookup(rng.normal(size=(200, 3))).astype(np.float64)
    weight = (rng.random(200) > 0.1).astype(float)
    loss, g, rad = photometric_loss(env, v, target, weight=weight, group=4)
    diff = (srgb(rad)[0] - srgb(target)[0]) * weight[:, None]
    assert loss == pytest.approx((diff.reshape(50, 4, 3).mean(1) ** 2).mean(), rel=1e-12)
    assert loss < photometric_loss(env, v, target, weight=weight)[0]
    swapped = np.roll(v.reshape(50, 4, 3), 1, axis=1).reshape(200, 3)
    assert photometric_loss(env, swapped, rad, group=4)[0] < 1e-12
    assert photometric_loss(env, swapped, rad)[0] > 1e-3
    hits = 0
    for _ in range(10):
        u = rng.normal(size=v.shape) * 1e-7
        fd = (
            photometric_loss(env, v + u, target, weight=weight, group=4)[0]
            - photometric_loss(env, v - u, target, weight=weight, group=4)[0]
        )
        hits += abs(fd / 2 - (g * u).sum()) < 1e-3 * abs((g * u).sum()) + 1e-15
    assert hits >= 9
    with pytest.raises(ValueError, match="groups of 3"):
        photometric_loss(env, v, target, group=3)
