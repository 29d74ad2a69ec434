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


def _ycc(rgb):
    """JFIF's YCbCr of sRGB-encoded values (without the 128 offset), in float64."""
    r, g, b = rgb[..., 0], rgb[..., 1], rgb[..., 2]
    y = 0.299 * r + 0.587 * g + 0.114 * b
    return np.stack([y, (b - y) / 1.772, (r - y) / 1.402], axis=-1)


def test_the_420_loss_compares_luma_per_pixel_and_chroma_per_block():
    """srgb420: the squared error of luma per ray and of the chroma of each run of 4 rays (a
    2 x 2 block), against JFIF's YCbCr written out here; zero where only the chroma inside a
    block differs (what 4:2:0 subsampling loses), with dJ/dv matching central differences."""
    from clrefract.loss import srgb

    env = _env()
    rng = np.random.default_rng(5)
    v = rng.normal(size=(200, 3))
    target = env.lookup(rng.normal(size=(200, 3))).astype(np.float64)
    weight = (rng.random(200) > 0.1).astype(float)
    loss, g, rad = photometric_loss(env, v, target, weight=weight, space="srgb420")
    diff = _ycc(srgb(rad)[0] - srgb(target)[0]) * weight[:, None]
    chroma = diff[:, 1:].reshape(50, 4, 2).mean(1)
    want = ((diff[:, 0] ** 2).sum() + 4 * (chroma**2).sum()) / diff.size
    assert loss == pytest.approx(want, rel=1e-5)  # the matrix's rounding in JFIF: 6 digits

    # the truth's luma, and chroma that differs from it only inside each block (zero mean
    # over the block): srgb420 sees nothing, srgb does (blocks that clip carry no weight)
    ycc = _ycc(srgb(rad)[0])
    spread = rng.normal(size=(50, 4, 2)) * 0.02
    ycc[:, 1:] += (spread - spread.mean(1, keepdims=True)).reshape(200, 2)
    y, cb, cr = ycc.T
    enc = np.stack([y + 1.402 * cr, y - 0.344136 * cb - 0.714136 * cr, y + 1.772 * cb], axis=1)
    lin = np.where(enc <= 0.04045, enc / 12.92, ((np.clip(enc, 0, 1) + 0.055) / 1.055) ** 2.4)
    ok = np.all((enc > 0.01) & (enc < 0.99) & (rad > 0) & (rad < 1), axis=1)
    kept = np.repeat(ok.reshape(50, 4).all(1), 4).astype(float)
    assert kept.sum() >= 40
    assert photometric_loss(env, v, lin, weight=kept, space="srgb420")[0] < 1e-14
    assert photometric_loss(env, v, lin, weight=kept, space="srgb")[0] > 1e-5

    hits = 0
    for _ in range(10):
        u = rng.normal(size=v.shape) * 1e-7
        fd = (
            photometric_loss(env, v + u, target, weight=weight, space="srgb420")[0]
            - photometric_loss(env, v - u, target, weight=weight, space="srgb420")[0]
        )
        hits += abs(fd / 2 - (g * u).sum()) < 1e-3 * abs((g * u).sum()) + 1e-15
    assert hits >= 9
    with pytest.raises(ValueError, match="2 x 2 blocks"):
        photometric_loss(env, v[:6], target[:6], space="srgb420")
