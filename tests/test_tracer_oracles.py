"""The tracer against closed forms (SPEC section 2) and a float64 SciPy reference."""

import numpy as np
import pytest
from scipy.integrate import solve_ivp

from clrefract.fields.analytic import Blobs, Fibre, Luneburg, Maxwell
from clrefract.tracer import Status, Tracer, TraceSettings

R = 20.0


def _unit(a):
    return a / np.linalg.norm(a, axis=1, keepdims=True)


def _luneburg_starts(n, seed=0):
    """Points on the lens surface with inward unit directions."""
    rng = np.random.default_rng(seed)
    p = R * _unit(rng.normal(size=(n, 3)))
    d = _unit(rng.normal(size=(n, 3)))
    d = np.where(((d * p).sum(1) < -0.2 * R)[:, None], d, -_unit(p + 0.3 * R * d))
    return p, d


def _luneburg_error(integrator, n_steps, precision="float64"):
    p, d = _luneburg_starts(64)
    sigma = np.pi * R / 2
    tr = Tracer(
        Luneburg(radius=R),
        settings=TraceSettings(step=sigma / n_steps, integrator=integrator, precision=precision),
    )
    x, v = tr.propagate(p * (1 - 1e-12), d, n_steps)
    # leaves at R d with velocity -P / R
    return max(np.abs(x - R * d).max(), R * np.abs(v + p / R).max())


@pytest.mark.parametrize("integrator,order", [("rkn4", 4), ("rk4", 4), ("euler", 1)])
def test_luneburg_trajectory_converges_at_integrator_order(integrator, order):
    n = 16 if order == 4 else 256
    e1, e2 = _luneburg_error(integrator, n), _luneburg_error(integrator, 2 * n)
    ratio = e1 / e2
    assert 2**order * 0.75 < ratio < 2**order * 1.3, (e1, e2, ratio)
    if order == 4:
        assert e2 < 1e-4


def test_luneburg_focuses_parallel_rays_through_the_box():
    rng = np.random.default_rng(1)
    yz = rng.uniform(-1, 1, (4000, 2))
    yz = R * yz[(yz**2).sum(1) < 0.9][:500]
    origins = np.column_stack([np.full(len(yz), -120.0), yz])
    dirs = np.tile([1.0, 0.0, 0.0], (len(yz), 1))
    res = Tracer(Luneburg(radius=R), settings=TraceSettings(step=0.1, precision="float64")).trace(
        origins, dirs
    )
    assert np.all(res.status == Status.EXITED)
    # every exit line passes through the antipodal focus (R, 0, 0)
    w = np.array([R, 0.0, 0.0]) - res.position
    miss = np.linalg.norm(w - (w * res.direction).sum(1)[:, None] * res.direction, axis=1)
    assert miss.max() < 2e-3 * R
    # exit points lie on the box
    assert np.allclose(np.abs(res.position).max(1), 50.0, atol=1e-9)


def _fisheye_error(n_steps, sigma=25.0):
    f = Maxwell(radius=R, n0=2.0)
    rng = np.random.default_rng(2)
    p = rng.uniform(-30, 30, (64, 3))
    d = _unit(rng.normal(size=(64, 3)))
    eta, _ = f.eval(p)
    x, _ = Tracer(f, settings=TraceSettings(step=sigma / n_steps, precision="float64")).propagate(
        p, eta[:, None] * d, n_steps
    )
    # the ray is the circle through P, tangent to d there, through the image -R^2 P / |P|^2
    img = -(R**2) * p / (p * p).sum(1, keepdims=True)
    nrm = _unit(np.cross(p, d))
    u = np.cross(nrm, d)
    s = -((p - img) ** 2).sum(1) / (2 * (u * (p - img)).sum(1))
    c = p + s[:, None] * u
    radial = np.abs(np.linalg.norm(x - c, axis=1) - np.abs(s))
    planar = np.abs(((x - p) * nrm).sum(1))
    return np.max(radial + planar)


def test_maxwell_fisheye_rays_are_circles_through_the_image_point():
    e1, e2 = _fisheye_error(100), _fisheye_error(200)
    assert e2 < 1e-5
    assert 16 * 0.75 < e1 / e2 < 16 * 1.3, (e1, e2)


def _fibre_error(n_steps, sigma=120.0):
    n0, a = 1.5, 0.02
    f = Fibre(n0=n0, a=a)
    rng = np.random.default_rng(3)
    x0 = np.column_stack([rng.uniform(-10, 10, (32, 2)), rng.uniform(-40, 0, 32)])
    d = _unit(np.column_stack([rng.uniform(-0.3, 0.3, (32, 2)), np.ones(32)]))
    eta, _ = f.eval(x0)
    v0 = eta[:, None] * d
    x, v = Tracer(f, settings=TraceSettings(step=sigma / n_steps, precision="float64")).propagate(
        x0, v0, n_steps
    )
    w = n0 * a
    exp = np.empty_like(x0)
    exp[:, :2] = x0[:, :2] * np.cos(w * sigma) + v0[:, :2] / w * np.sin(w * sigma)
    exp[:, 2] = x0[:, 2] + v0[:, 2] * sigma
    return np.abs(x - exp).max()


def test_parabolic_fibre_trajectory_matches_closed_form():
    e1, e2 = _fibre_error(40), _fibre_error(80)
    assert e2 < 1e-4
    assert 16 * 0.75 < e1 / e2 < 16 * 1.3, (e1, e2)


def _blob_rhs(field):
    def rhs(_, y):
        eta, g = field.eval(y[None, :3])
        return np.concatenate([y[3:], eta[0] * g[0]])

    return rhs


def test_random_blob_field_matches_dop853_in_float64():
    f = Blobs.random(6, amplitude=0.15, seed=4)
    rng = np.random.default_rng(5)
    x0 = rng.uniform(-30, 30, (8, 3))
    d = _unit(rng.normal(size=(8, 3)))
    eta, _ = f.eval(x0)
    v0 = eta[:, None] * d
    sigma, n = 60.0, 300
    x, v = Tracer(f, settings=TraceSettings(step=sigma / n, precision="float64")).propagate(
        x0, v0, n
    )
    for i in range(len(x0)):
        sol = solve_ivp(
            _blob_rhs(f),
            (0, sigma),
            np.concatenate([x0[i], v0[i]]),
            method="DOP853",
            rtol=1e-11,
            atol=1e-12,
        )
        ref = sol.y[:, -1]
        assert np.abs(x[i] - ref[:3]).max() < 1e-6
        assert np.abs(v[i] - ref[3:]).max() < 1e-7


def test_speed_equals_eta_drift_float32_vs_float64():
    """|v| = eta drifts by truncation in float64 (falls 16x per halving) and by rounding in
    float32 (grows with the step count but stays near float epsilon)."""
    f = Blobs.random(6, amplitude=0.15, seed=6)
    rng = np.random.default_rng(7)
    x0 = rng.uniform(-20, 20, (256, 3))
    eta, _ = f.eval(x0)
    v0 = eta[:, None] * _unit(rng.normal(size=(256, 3)))
    drift = {}
    for prec in ("float32", "float64"):
        for h in (0.5, 0.25):
            x, v = Tracer(f, settings=TraceSettings(step=h, precision=prec)).propagate(
                x0, v0, int(100 / h)
            )
            drift[prec, h] = np.abs(np.linalg.norm(v, axis=1) - f.eval(x)[0]).max()
    assert 10 < drift["float64", 0.5] / drift["float64", 0.25] < 24
    assert drift["float64", 0.25] < 1e-9
    assert 1e-8 < drift["float32", 0.25] < 1e-5
    assert drift["float32", 0.25] > 100 * drift["float64", 0.25]


def test_status_missed_and_trapped():
    f = Blobs.random(2, amplitude=0.05, seed=0)
    tr = Tracer(f, settings=TraceSettings(step=1.0))
    origins = np.array([[-100.0, 0, 0], [-100.0, 200.0, 0]])
    dirs = np.array([[1.0, 0, 0], [1.0, 0, 0]])
    res = tr.trace(origins, dirs)
    assert list(res.status) == [Status.EXITED, Status.MISSED]
    assert np.allclose(res.position[1], origins[1]) and np.allclose(res.direction[1], dirs[1])
    short = Tracer(f, settings=TraceSettings(step=1.0, max_steps=10)).trace(origins, dirs)
    assert short.status[0] == Status.TRAPPED and short.steps[0] == 10


@pytest.mark.parametrize("lanes", [1, 4, 16])
def test_lane_width_does_not_change_results(lanes):
    f = Blobs.random(4, amplitude=0.1, seed=8)
    rng = np.random.default_rng(9)
    o = np.column_stack([rng.uniform(-40, 40, (37, 2)), np.full(37, -80.0)])
    d = _unit(np.column_stack([rng.normal(0, 0.1, (37, 2)), np.ones(37)]))
    ref = Tracer(f, settings=TraceSettings(step=0.5, precision="float64", lanes=1)).trace(o, d)
    res = Tracer(f, settings=TraceSettings(step=0.5, precision="float64", lanes=lanes)).trace(o, d)
    assert np.array_equal(res.steps, ref.steps)
    assert np.abs(res.direction - ref.direction).max() < 1e-12
