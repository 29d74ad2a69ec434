"""Image and geometry metrics of the benchmark protocol (SPEC section 5)."""

from __future__ import annotations

import numpy as np
from skimage.metrics import peak_signal_noise_ratio, structural_similarity

from .imageio import linear_to_srgb


def psnr_ssim(rendered: np.ndarray, reference: np.ndarray) -> tuple[float, float]:
    """PSNR and SSIM of sRGB-encoded images clipped to [0, 1]."""
    a = linear_to_srgb(np.asarray(rendered, np.float64)).astype(np.float64)
    b = linear_to_srgb(np.asarray(reference, np.float64)).astype(np.float64)
    psnr = peak_signal_noise_ratio(b, a, data_range=1.0)
    ssim = structural_similarity(
        b,
        a,
        data_range=1.0,
        channel_axis=-1,
        gaussian_weights=True,
        sigma=1.5,
        use_sample_covariance=False,
    )
    return float(psnr), float(ssim)


def psnr_linear_batch(rendered: np.ndarray, reference: np.ndarray) -> float:
    """PSNR of sRGB-encoded pixel batches (n, 3): the training-time figure."""
    a = linear_to_srgb(np.asarray(rendered, np.float64))
    b = linear_to_srgb(np.asarray(reference, np.float64))
    mse = float(np.mean((a - b) ** 2))
    return float("inf") if mse == 0 else float(-10 * np.log10(mse))
