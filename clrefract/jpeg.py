"""What a 4:2:0 JPEG file holds of a photograph: each 8 x 8 block's DCT coefficients, each
quantised to a bin of its table's step. Any image whose coefficients lie in those bins is
stored as the same file, so a render is as right as the file can say once it lies in them.

The `jpeg` loss compares a render with its nearest such image (`consistent`) instead of the
decoded photograph, whose quantisation error (up to half a step: 12 levels in a q90 file's
finest luma) otherwise sits in every residual. The true quick sphere against 30 of its
noisy quality-90 views keeps 0.95 of the srgb420 loss of an index 0.002 low, and 0.43 of
the jpeg loss's (docs/design/jpeg-chroma.md).

Ray layout (`columns`): the rays of a 16 x 16 macroblock in raster order; each carries its
luma coefficient's bin (the coefficient at its place in its 8 x 8 block) and, in the first
128 of the block, a chroma coefficient's bin (Cb then Cr, 64 each, in raster order).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.fft import dctn, idctn

from .errors import ClrefractError
from .imageio import YCC, read_pillow, stored_chroma

MB = 16  # a 4:2:0 macroblock's side, pixels: 4 luma blocks and one of each chroma
COLUMNS = 4  # per ray: luma bin centre and step, chroma bin centre and step (levels)


@dataclass
class JpegBins:
    """One frame's quantised coefficients (as bin indices) and its two tables."""

    q_luma: np.ndarray  # (8, 8) steps, levels of 255
    q_chroma: np.ndarray  # (8, 8)
    k_luma: np.ndarray  # (H16 / 8, W16 / 8, 8, 8) int32: the frame padded to whole macroblocks
    k_chroma: np.ndarray  # (2, H16 / 16, W16 / 16, 8, 8) int32: Cb, Cr


def blocks_dct(x: np.ndarray) -> np.ndarray:
    """(..., H, W) -> (..., H / 8, W / 8, 8, 8): JPEG's DCT (orthonormal DCT-II) per block."""
    *lead, h, w = x.shape
    b = x.reshape(*lead, h // 8, 8, w // 8, 8)
    return dctn(np.moveaxis(b, -3, -2), axes=(-2, -1), norm="ortho")


def blocks_idct(c: np.ndarray) -> np.ndarray:
    """The inverse of blocks_dct."""
    *lead, by, bx, _, _ = c.shape
    b = np.moveaxis(idctn(c, axes=(-2, -1), norm="ortho"), -2, -3)
    return b.reshape(*lead, by * 8, bx * 8)


def pad_to(x: np.ndarray, rows: int, cols: int) -> np.ndarray:
    """x (H, W, ...) padded by its last row and column, as an encoder fills a partial block."""
    pad = [(0, rows - x.shape[0]), (0, cols - x.shape[1])] + [(0, 0)] * (x.ndim - 2)
    return np.pad(x, pad, mode="edge")


def read_bins(path: Path) -> JpegBins:
    """The bins of a 4:2:0 JPEG frame, from its tables and its decoded pixels: the decoder's
    rounding to 8 bits moves a coefficient by about half a level, far less than half of the
    finest step, so rounding each back to its step recovers the stored one."""
    from PIL import Image, JpegImagePlugin

    with Image.open(path) as im:
        tables = getattr(im, "quantization", None) or {}
        if im.format != "JPEG" or JpegImagePlugin.get_sampling(im) != 2 or len(tables) < 2:
            raise ClrefractError(f"{path}: the jpeg loss needs JPEG frames with 4:2:0 chroma")
        q_luma = np.array(tables[0], float).reshape(8, 8)
        q_chroma = np.array(tables[1], float).reshape(8, 8)
    raw = read_pillow(path, "image", "JPEG image")[:, :, :3].astype(np.float64) / 255
    h16, w16 = -(-raw.shape[0] // MB) * MB, -(-raw.shape[1] // MB) * MB
    ycc = pad_to(stored_chroma(raw).astype(np.float64), h16, w16) @ YCC.T * 255
    k_luma = np.round(blocks_dct(ycc[:, :, 0] - 128) / q_luma)
    chroma = np.moveaxis(ycc[::2, ::2, 1:], -1, 0)  # the stored samples, one per block
    k_chroma = np.round(blocks_dct(chroma) / q_chroma)
    return JpegBins(q_luma, q_chroma, k_luma.astype(np.int32), k_chroma.astype(np.int32))


def columns(bins: list[JpegBins], view: np.ndarray, y0: np.ndarray, x0: np.ndarray):
    """(len(view) * 256, COLUMNS): the bins of the rays of the macroblocks whose top-left
    pixels are (y0, x0) of `view`, in the layout above."""
    p = np.arange(MB * MB)
    dy, dx = np.divmod(p, MB)
    out = np.zeros((len(view), MB * MB, COLUMNS))
    for v in np.unique(view):
        at = np.flatnonzero(view == v)
        b = bins[v]
        by = (y0[at, None] + dy) // 8
        bx = (x0[at, None] + dx) // 8
        u, w = dy % 8, dx % 8
        out[at, :, 0] = b.k_luma[by, bx, u, w] * b.q_luma[u, w]
        out[at, :, 1] = b.q_luma[u, w]
        c = p[: 2 * 64]
        plane, cu, cw = c // 64, c % 64 // 8, c % 8
        cy, cx = y0[at, None] // MB, x0[at, None] // MB
        out[at, : 2 * 64, 2] = b.k_chroma[plane, cy, cx, cu, cw] * b.q_chroma[cu, cw]
        out[at, : 2 * 64, 3] = b.q_chroma[cu, cw]
    return out.reshape(-1, COLUMNS)


def consistent(levels: np.ndarray, cols: np.ndarray) -> np.ndarray:
    """The image nearest a render (n, 3: YCbCr, levels of 255, whole macroblocks in the layout
    above) whose coefficients lie in the file's bins `cols` (n, COLUMNS): each coefficient
    clipped to its bin. Luma per pixel; chroma where the file keeps it, per 2 x 2 block, the
    render's own variation within a block kept."""
    m = len(levels) // (MB * MB)
    ycc = levels.reshape(m, MB, MB, 3)
    c = cols.reshape(m, MB * MB, COLUMNS)
    out = ycc.copy()
    luma = blocks_dct(ycc[..., 0] - 128)
    centre = blocks_dct_layout(c[:, :, 0].reshape(m, MB, MB))
    step = blocks_dct_layout(c[:, :, 1].reshape(m, MB, MB))
    out[..., 0] = blocks_idct(np.clip(luma, centre - step / 2, centre + step / 2)) + 128
    means = ycc[..., 1:].reshape(m, 8, 2, 8, 2, 2).mean(axis=(2, 4))  # (m, 8, 8, 2)
    coef = dctn(means, axes=(1, 2), norm="ortho")
    centre = np.moveaxis(c[:, :128, 2].reshape(m, 2, 8, 8), 1, -1)
    step = np.moveaxis(c[:, :128, 3].reshape(m, 2, 8, 8), 1, -1)
    kept = idctn(np.clip(coef, centre - step / 2, centre + step / 2), axes=(1, 2), norm="ortho")
    out[..., 1:] += (kept - means).repeat(2, axis=1).repeat(2, axis=2)
    return out.reshape(-1, 3)


def blocks_dct_layout(x: np.ndarray) -> np.ndarray:
    """(m, 16, 16) per-pixel values -> (m, 2, 2, 8, 8) as blocks_dct lays coefficients out:
    the value at a pixel's place in its 8 x 8 block is its coefficient's."""
    m = x.shape[0]
    return np.moveaxis(x.reshape(m, 2, 8, 2, 8), -3, -2)
