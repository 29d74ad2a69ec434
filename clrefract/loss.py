"""Photometric loss on exit directions and its gradient, the start of the backward pass.

The loss compares environment radiance in each ray's exit direction with the photographed
pixel. Its gradient with respect to the exit velocity v is the terminal adjoint
mu(T) = (I - d d^T) / |v| dJ/dd (SPEC section 3).
"""

from __future__ import annotations

import numpy as np

from .envmap import EnvMap
from .imageio import YCC


def envmap_lookup_jacobian(env: EnvMap, directions: np.ndarray):
    """Radiance (n, 3) and its derivative with respect to the unit direction (n, 3, 3):
    jac[i, c, k] = d radiance_c / d d_k, for the bilinear lookup of SPEC section 6."""
    d = env.to_panorama(directions)
    d = d / np.linalg.norm(d, axis=1, keepdims=True)
    h, w = env.height, env.width
    rxy2 = np.maximum(d[:, 0] ** 2 + d[:, 1] ** 2, 1e-30)
    u = 0.5 + np.arctan2(d[:, 1], d[:, 0]) / (2 * np.pi)
    dz = np.clip(d[:, 2], -1.0, 1.0)
    v = np.arccos(dz) / np.pi
    row, col = v * h - 0.5, u * w - 0.5
    r0, c0 = np.floor(row), np.floor(col)
    fr, fc = (row - r0)[:, None], (col - c0)[:, None]
    r0i = r0.astype(np.int64)
    r1 = np.clip(r0i + 1, 0, h - 1)
    r0i = np.clip(r0i, 0, h - 1)
    c0i = np.mod(c0.astype(np.int64), w)
    c1 = np.mod(c0i + 1, w)
    img = env.image  # gathered, then widened: the whole map in float64 is 20 ms a call
    a, b, c, e = (
        img[i, j].astype(np.float64) for i, j in ((r0i, c0i), (r0i, c1), (r1, c0i), (r1, c1))
    )
    top, bot = a * (1 - fc) + b * fc, c * (1 - fc) + e * fc
    rad = top * (1 - fr) + bot * fr
    d_col = (b - a) * (1 - fr) + (e - c) * fr  # d rad / d col
    d_row = np.where(((row >= 0) & (row <= h - 1))[:, None], bot - top, 0.0)  # clamped in v
    # col = u w - 1/2, u = 1/2 + atan2(y, x) / 2 pi;  row = v h - 1/2, v = acos(z) / pi
    dcol_dd = np.column_stack([-d[:, 1], d[:, 0], np.zeros(len(d))]) * (w / (2 * np.pi))
    dcol_dd /= rxy2[:, None]
    drow_dz = -h / (np.pi * np.sqrt(np.maximum(1 - dz * dz, 1e-30)))
    drow_dd = np.zeros_like(d)
    drow_dd[:, 2] = drow_dz
    jac = d_col[:, :, None] * dcol_dd[:, None, :] + d_row[:, :, None] * drow_dd[:, None, :]
    if env.rotation is not None:  # radiance of R^T d: the chain rule's R^T on the right
        jac = jac @ env.rotation.T
    return rad, jac


SPACES = ("srgb", "srgb420", "linear")


def srgb(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """sRGB encoding of linear values clipped to [0, 1], and its derivative (float64)."""
    c = np.clip(x, 0.0, 1.0)
    lo = c <= 0.0031308
    cs = np.maximum(c, 0.0031308)
    y = np.where(lo, 12.92 * c, 1.055 * cs ** (1 / 2.4) - 0.055)
    dy = np.where(lo, 12.92, 1.055 / 2.4 * cs ** (1 / 2.4 - 1))
    return y, np.where((x < 0) | (x > 1), 0.0, dy)


def photometric_loss(
    env: EnvMap,
    velocity: np.ndarray,
    target: np.ndarray,
    weight: np.ndarray | None = None,
    space: str = "srgb",
    dark: np.ndarray | None = None,
    group: int = 1,
):
    """Mean squared error over rays and channels, and the terminal adjoint dJ/dv (n, 3).

    velocity: exit v (n, 3), not necessarily unit; target: (n, 3) linear radiance;
    weight: (n,) 0/1 mask of rays that count (rays that missed the box get 0);
    space: "srgb" compares sRGB-encoded values clipped to [0, 1], as the test metrics do
    (bright lamps then do not dominate), "linear" compares radiance; "srgb420" compares the
    sRGB values' luma per ray and their chroma by the mean of each run of 4 rays (an aligned
    2 x 2 pixel block): all that a JPEG with 4:2:0 chroma subsampling keeps of the colours,
    so the decoder's smeared chroma at the object's edges is not fitted as refraction;
    dark: (n,) rays that render black (trapped or non-finite), as the renderer draws them:
    radiance 0 and no adjoint. Were they left out, trapping a badly rendered ray would
    lower the loss.
    group: consecutive runs of this many rays (a block of pixels) are compared by their
    mean: the error of the block-averaged images, which is zero at the truth as the per-ray
    one is, and smooth over shifts of image content smaller than the block.
    """
    v = np.asarray(velocity, np.float64)
    if dark is not None:
        dark = np.asarray(dark, bool)
        v = np.where(dark[:, None], (0.0, 0.0, 1.0), v)
    speed = np.linalg.norm(v, axis=1)
    d = v / speed[:, None]
    rad, jac = envmap_lookup_jacobian(env, d)
    if dark is not None:
        rad, jac = np.where(dark[:, None], 0.0, rad), np.where(dark[:, None, None], 0.0, jac)
    wgt = np.ones(len(v)) if weight is None else np.asarray(weight, np.float64)
    if space in ("srgb", "srgb420"):
        enc, denc = srgb(rad)
        resid = (enc - srgb(np.asarray(target, np.float64))[0]) * wgt[:, None]
        jac = denc[:, :, None] * jac
    elif space == "linear":
        resid = (rad - target) * wgt[:, None]
    else:
        raise ValueError(f"loss space must be one of {', '.join(SPACES)}, got {space!r}")
    if group > 1:
        if len(resid) % group:
            raise ValueError(f"{len(resid)} rays do not split into groups of {group}")
        mean = resid.reshape(-1, group, 3).mean(axis=1)
        n = max(mean.size, 1)
        loss = float((mean**2).sum() / n)
        dres = np.repeat(2 * mean / (n * group), group, axis=0) * wgt[:, None]
    elif space == "srgb420":
        if len(resid) % 4:
            raise ValueError(f"{len(resid)} rays do not split into 2 x 2 blocks")
        ycc = resid @ YCC.T
        ycc[:, 1:] = np.repeat(ycc[:, 1:].reshape(-1, 4, 2).mean(axis=1), 4, axis=0)
        n = max(resid.size, 1)
        loss = float((ycc**2).sum() / n)  # a block's chroma counts once per pixel
        dres = (2 * ycc / n) @ YCC * wgt[:, None]
    else:
        n = max(resid.size, 1)
        loss = float((resid**2).sum() / n)
        dres = 2 * resid / n
    dj_dd = np.einsum("nc,nck->nk", dres, jac)
    return loss, velocity_adjoint(dj_dd, d, speed), rad


def velocity_adjoint(dj_dd: np.ndarray, d: np.ndarray, speed: np.ndarray) -> np.ndarray:
    """dJ/dv from dJ/dd for d = v / |v|: the radial part removed, (I - d d^T) / |v| dJ/dd."""
    return (dj_dd - (dj_dd * d).sum(1, keepdims=True) * d) / speed[:, None]


def direction_loss(velocity: np.ndarray, target: np.ndarray, weight: np.ndarray):
    """Mean squared distance of exit directions from target unit directions over the rays
    of weight 1 (a diagnostic: the truth's directions stand in for what a photograph can
    only hint at); (loss, dJ/dv, zero radiance)."""
    v = np.asarray(velocity, np.float64)
    speed = np.maximum(np.linalg.norm(v, axis=1), 1e-30)
    d = v / speed[:, None]
    wgt = np.asarray(weight, np.float64)
    diff = (d - np.nan_to_num(target)) * wgt[:, None]
    n = max(int((wgt > 0).sum()), 1)
    return float((diff**2).sum() / n), velocity_adjoint(2 * diff / n, d, speed), np.zeros_like(v)
