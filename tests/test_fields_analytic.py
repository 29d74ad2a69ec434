"""Every analytic field: kernel against NumPy reference, reference gradient against FD."""

import numpy as np
import pytest

from clrefract.fields.analytic import Blobs, Drop, Fibre, Luneburg, Maxwell, Prism, Sphere
from clrefract.tracer import Tracer, TraceSettings

FIELDS = [
    Luneburg(radius=20.0),
    Maxwell(radius=20.0, n0=2.0),
    Fibre(n0=1.5, a=0.02),
    Blobs.random(5, amplitude=0.2, seed=1),
    Sphere(radius=20.0, eta=1.5, width=2.0),
    Prism(width=2.0),
    Drop(width=2.0),
]


def _points(n=4000, seed=0):
    return np.random.default_rng(seed).uniform(-30, 30, (n, 3))


@pytest.mark.parametrize("field", FIELDS, ids=lambda f: f.kind)
@pytest.mark.parametrize(
    "precision,lanes,tol", [("float64", 8, 1e-12), ("float32", 16, 3e-5), ("float32", 1, 3e-5)]
)
def test_kernel_matches_numpy_reference(field, precision, lanes, tol):
    pts = _points()
    eta, grad = Tracer(field, settings=TraceSettings(precision=precision, lanes=lanes)).eval_field(
        pts
    )
    eta_ref, grad_ref = field.eval(pts)
    scale = max(1.0, np.abs(grad_ref).max())
    assert np.abs(eta - eta_ref).max() < tol * 10
    assert np.abs(grad - grad_ref).max() < tol * 10 * scale


@pytest.mark.parametrize("field", FIELDS, ids=lambda f: f.kind)
def test_reference_gradient_matches_finite_differences(field):
    pts = _points(600, seed=1)
    _, grad = field.eval(pts)
    h = 1e-5
    fd = np.empty_like(grad)
    for k in range(3):
        e = np.zeros(3)
        e[k] = h
        fd[:, k] = (field.eval(pts + e)[0] - field.eval(pts - e)[0]) / (2 * h)
    err = np.abs(fd - grad).max(axis=1)
    if field.kind == "prism":
        # the plane distance switches at the medial planes: compare away from them
        sd, _ = field.sdf(pts)
        err = err[np.abs(sd) < field.width]
    assert np.all(err < 1e-6 * max(1.0, np.abs(grad).max())), err.max()
    assert np.abs(grad).max() > 1e-3  # the sample saw a non-trivial gradient


def test_solids_have_their_index_inside_and_one_outside():
    for f in (Sphere(), Prism(), Drop()):
        eta, grad = f.eval(np.array([[0.0, 0.0, 0.0], [45.0, 45.0, 45.0]]))
        assert eta[0] == pytest.approx(f.eta) and eta[1] == 1.0
        assert np.all(grad == 0)


def test_drop_signed_distance_is_a_distance():
    """On the surface the sdf is zero; a step along its gradient moves it by the same amount."""
    d = Drop(width=1.0)
    t = np.linspace(0.3, np.pi - 0.05, 50)
    r, z = d.profile(t)
    phi = np.linspace(0, 2 * np.pi, 50)
    surf = np.column_stack([r * np.cos(phi), r * np.sin(phi), z])
    sd, n = d.sdf(surf)
    assert np.abs(sd).max() < 1e-9
    sd2, _ = d.sdf(surf + 0.5 * n)
    assert np.abs(sd2 - 0.5).max() < 2e-3
