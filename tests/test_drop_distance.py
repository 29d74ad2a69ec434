"""The drop's signed distance: the NumPy reference against a dense search, the kernel against
the reference in the interface band, near the tip (where the profile's derivative vanishes)
and elsewhere."""

import numpy as np
import pytest

from clrefract.fields.analytic import Drop
from clrefract.tracer import Tracer, TraceSettings


def _band_points(d: Drop, n=6000, seed=0):
    """Points within one width of the profile, half of them near the tip (t < 0.3)."""
    rng = np.random.default_rng(seed)
    t = np.concatenate([rng.uniform(0, np.pi, n // 2), rng.uniform(0, 0.3, n - n // 2)])
    r, z = d.profile(t)
    off = rng.uniform(-1, 1, (n, 2)) * d.width
    phi = rng.uniform(0, 2 * np.pi, n)
    rho = np.abs(r + off[:, 0])
    return np.column_stack([rho * np.cos(phi), rho * np.sin(phi), z + off[:, 1]])


def _dense_distance(d: Drop, pts):
    """Unsigned distance to the profile: the nearest of 4,001 samples, then 4,001 more
    across that sample's two intervals (resolution 4e-7 rad)."""
    rho, z = np.hypot(pts[:, 0], pts[:, 1]), pts[:, 2]
    t = np.linspace(0, np.pi, 4001)
    dt = t[1] - t[0]
    out = np.empty(len(pts))
    for a in range(0, len(pts), 256):
        s = slice(a, a + 256)
        r, zz = d.profile(t)
        tk = t[((r[None] - rho[s, None]) ** 2 + (zz[None] - z[s, None]) ** 2).argmin(1)]
        tt = np.clip(tk[:, None] + np.linspace(-dt, dt, 4001)[None], 0, np.pi)
        r, zz = d.profile(tt)
        out[s] = np.sqrt(((r - rho[s, None]) ** 2 + (zz - z[s, None]) ** 2).min(1))
    return out


def test_reference_distance_matches_a_dense_search_near_the_surface():
    """Within 1 mm of the surface, tip included: 2e-8 mm off the dense search (measured);
    the Newton steps before the safeguard went to the far end from the tip (3e-2 mm)."""
    d = Drop(width=2.0)
    pts = _band_points(d, 3000)
    sd = d.sdf(pts)[0]
    dense = _dense_distance(d, pts)
    near = dense < 1.0
    assert near.sum() > 1000
    assert np.abs(np.abs(sd) - dense)[near].max() < 1e-6


@pytest.mark.parametrize(
    "precision,lanes,eta_tol,grad_tol",
    # measured 1.8e-15 / 2.2e-13, and in float32 1.0e-6 / 1.8e-4 (grad eta up to 0.31)
    [("float64", 8, 1e-12, 1e-11), ("float32", 16, 4e-6, 6e-4), ("float32", 1, 4e-6, 6e-4)],
)
def test_kernel_matches_the_reference_in_the_band(precision, lanes, eta_tol, grad_tol):
    d = Drop(width=2.0)
    pts = _band_points(d)
    eta_ref, grad_ref = d.eval(pts)
    assert ((eta_ref > 1 + 1e-3) & (eta_ref < d.eta - 1e-3)).mean() > 0.4  # in the band
    eta, grad = Tracer(d, settings=TraceSettings(precision=precision, lanes=lanes)).eval_field(pts)
    assert np.abs(eta - eta_ref).max() < eta_tol
    assert np.abs(grad - grad_ref).max() < grad_tol


def test_kernel_is_one_outside_the_drops_cylinder():
    """Beyond a width of the bounding cylinder (radius 3 sqrt 3 R / 8, |z| < H) the kernel
    skips the search: eta is exactly 1 there with no gradient, as the reference's."""
    d = Drop(width=1.0)
    rng = np.random.default_rng(3)
    pts = rng.uniform(-45, 45, (4000, 3))
    rho = np.hypot(pts[:, 0], pts[:, 1])
    far = (rho > 0.6495 * d.R + 1.01) | (np.abs(pts[:, 2]) > d.H + 1.01)
    eta, grad = Tracer(d, settings=TraceSettings(lanes=16)).eval_field(pts[far])
    assert far.sum() > 3000 and np.all(eta == 1.0) and np.all(grad == 0.0)
