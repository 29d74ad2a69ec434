"""Benchmark metrics: PSNR/SSIM conventions and the chamfer distance between surfaces."""

import warnings

import numpy as np
import pytest

from clrefract.fields.analytic import Sphere
from clrefract.fields.base import Box
from clrefract.fields.voxel import VoxelGrid
from clrefract.metrics import chamfer_distance, eta_surface, psnr_ssim, sample_surface
from clrefract.synth import surface_mesh


def test_surface_samples_are_uniform_by_area():
    verts, faces = surface_mesh(Sphere(radius=20.0, eta=1.5, width=1.0), spacing=1.0)
    p = sample_surface(verts, faces, 20000)
    assert np.abs(np.linalg.norm(p, axis=1) - 20).max() < 0.2
    # equal-area bands of a sphere hold equal shares of the samples (Archimedes)
    counts = np.histogram(p[:, 2], bins=4, range=(-20, 20))[0]
    assert counts.min() > 0.9 * counts.max()


def test_chamfer_of_concentric_spheres_is_their_gap():
    a = surface_mesh(Sphere(radius=20.0, eta=1.5, width=1.0), spacing=0.5)
    b = surface_mesh(Sphere(radius=21.0, eta=1.5, width=1.0), spacing=0.5)
    assert chamfer_distance(a, b, 50000) == pytest.approx(1.0, abs=0.05)
    # two independent samplings of one surface: the Poisson spacing 0.5 / sqrt(density)
    assert chamfer_distance(a, a, 50000) < 0.2


def test_eta_surface_of_a_grid_finds_the_sphere():
    sph = Sphere(radius=20.0, eta=1.5, width=1.0)
    grid = VoxelGrid.from_field(sph, Box(), 64)
    mesh = eta_surface(grid, Box(), 1.25, res=96)
    assert chamfer_distance(mesh, surface_mesh(sph, spacing=0.5), 50000) < 0.5
    assert eta_surface(VoxelGrid(np.ones((8, 8, 8)), Box()), Box(), 1.25, res=16) is None


def test_psnr_ssim_of_identical_and_shifted_images():
    rng = np.random.default_rng(0)
    img = rng.random((32, 32, 3))
    assert psnr_ssim(img + 1e-9, img)[1] == pytest.approx(1.0)
    p, s = psnr_ssim(img + 0.01, img)
    mse = np.mean((_srgb(img + 0.01) - _srgb(img)) ** 2)
    assert p == pytest.approx(-10 * np.log10(mse), rel=1e-6)  # sRGB is taken in float32
    # SSIM against the float64 reference below (measured off by 4e-11 here and 1e-9 at a
    # shift of 0.1, from sRGB in float32; a uniform window is off by 3e-5 and 3e-4, sample
    # covariance by 6e-8 and 2e-6, SSIM of the linear values by 7e-4 and 1e-2)
    assert s == pytest.approx(ssim_reference(img + 0.01, img), abs=1e-8)
    s = psnr_ssim(img + 0.1, img)[1]
    assert s == pytest.approx(ssim_reference(img + 0.1, img), abs=1e-8) and s < 0.99


def ssim_reference(rendered, reference) -> float:
    """SSIM as Wang et al. 2004 define it, in float64 on clipped sRGB values: an 11-tap
    Gaussian window (sigma 1.5, cut at 3.5 sigma), population moments, K1 = 0.01, K2 = 0.03,
    data range 1, averaged over the channels and the pixels 5 or more from the border."""
    from scipy.ndimage import gaussian_filter

    a, b = _srgb(np.asarray(rendered, np.float64)), _srgb(np.asarray(reference, np.float64))

    def w(x):
        return gaussian_filter(x, sigma=(1.5, 1.5, 0), truncate=3.5, mode="reflect")

    ma, mb = w(a), w(b)
    va, vb, cab = w(a * a) - ma**2, w(b * b) - mb**2, w(a * b) - ma * mb
    c1, c2 = 0.01**2, 0.03**2
    s = (2 * ma * mb + c1) * (2 * cab + c2) / ((ma**2 + mb**2 + c1) * (va + vb + c2))
    return float(s[5:-5, 5:-5].mean())


def _lin(s):
    return ((s + 0.055) / 1.055) ** 2.4  # IEC 61966-2-1 above its linear toe


def _srgb(x):
    x = np.clip(x, 0, 1)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * x ** (1 / 2.4) - 0.055)


def test_psnr_is_taken_on_clipped_srgb_values():
    """sRGB 0.5 against 0.6 everywhere is 20 dB exactly; radiance above 1 counts as 1."""
    ref = np.full((16, 16, 3), _lin(0.5))
    assert psnr_ssim(np.full_like(ref, _lin(0.6)), ref)[0] == pytest.approx(20.0, abs=1e-4)
    white = np.ones((16, 16, 3))
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # identical images: inf, not a division warning
        assert psnr_ssim(white * 7.0, white)[0] == np.inf
