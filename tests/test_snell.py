"""Snell ground truth (sphere, prism, drop) against closed forms, invariants and the reference."""

import math

import numpy as np
import pytest
from rays import camera_rays, unit

from clrefract.errors import ClrefractError
from clrefract.fields.analytic import Drop, Luneburg, Prism, Sphere
from clrefract.snell import SnellRenderer, drop_F, snell_numpy
from clrefract.tracer import Status

S3 = math.sqrt(3.0) / 2
SOLIDS = {
    "sphere": (Sphere(radius=20.0, eta=1.5, center=(3.0, -2.0, 1.0)), (25.0, 25.0, 25.0)),
    "prism": (Prism(), (30.0, 30.0, 30.0)),
    "drop": (Drop(), (13.0, 13.0, 23.0)),
}


def _angle(a, b):
    return np.arctan2(np.linalg.norm(np.cross(a, b), axis=-1), (a * b).sum(-1))


def _random_rotation(seed):
    q, r = np.linalg.qr(np.random.default_rng(seed).normal(size=(3, 3)))
    q = q * np.sign(np.diag(r))
    return q if np.linalg.det(q) > 0 else -q


# ----------------------------------------------------------------------------- sphere


def test_sphere_matches_closed_form():
    R, n = 20.0, 1.5
    center = np.array([3.0, -2.0, 1.0])
    sphere = Sphere(radius=R, eta=n, center=tuple(center))
    b = R * np.linspace(0.0, 0.995, 200)
    rot = _random_rotation(3)  # columns: the frame of the 2D closed form
    ex, ey = rot[:, 0], rot[:, 1]
    origins = center - 120.0 * ex + b[:, None] * ey
    dirs = np.tile(ex, (len(b), 1))
    res = SnellRenderer(sphere, precision="float64").trace(origins, dirs)
    assert np.all(res.status == Status.EXITED) and np.all(res.events == 2)
    ti = np.arcsin(b / R)
    tt = np.arcsin(np.sin(ti) / n)
    dev = 2 * (ti - tt)
    # the ray turns towards the axis by dev; it leaves at polar angle 2 tt - ti
    want_dir = np.cos(dev)[:, None] * ex - np.sin(dev)[:, None] * ey
    a2 = 2 * tt - ti
    want_exit = center + R * (np.cos(a2)[:, None] * ex + np.sin(a2)[:, None] * ey)
    assert np.abs(res.direction - want_dir).max() < 1e-12
    assert np.abs(res.surface - want_exit).max() < 1e-10
    # position: where the exit line meets the box [-50, 50]^3
    assert np.allclose(np.abs(res.position).max(1), 50.0, atol=1e-9)
    w = res.position - res.surface
    assert np.abs(np.cross(w, res.direction)).max() < 1e-9
    assert np.all((w * res.direction).sum(1) > 0)


def test_sphere_conserves_angular_momentum():
    sphere, spread = SOLIDS["sphere"]
    o, d = camera_rays(4000, spread, seed=1)
    res = SnellRenderer(sphere).trace(o, d)
    c = np.asarray(sphere.center)
    ok = res.status == Status.EXITED
    assert ok.sum() > 1000
    l0 = np.cross(o - c, unit(d))
    l1 = np.cross(res.surface - c, res.direction)
    assert np.abs(l1 - l0)[ok].max() < 1e-11


# ------------------------------------------------------------------------------ prism


def _prism_rays(prism, theta1_deg):
    """Principal-plane rays hitting the middle of side face 1 at incidence theta1, turned
    towards face 2 (apex angle A = 60 degrees between faces 1 and 2)."""
    h = prism.side / (2 * math.sqrt(3.0))
    n1 = np.array([-S3, -0.5, 0.0])
    th = np.radians(np.atleast_1d(theta1_deg))
    v = -n1  # inward normal, rotated clockwise by theta1
    d_loc = np.column_stack(
        [
            v[0] * np.cos(th) + v[1] * np.sin(th),
            -v[0] * np.sin(th) + v[1] * np.cos(th),
            np.zeros_like(th),
        ]
    )
    o_loc = h * n1 - 150.0 * d_loc
    m = prism.world_to_local
    c = np.asarray(prism.center)
    return c + o_loc @ m, d_loc @ m  # local -> world: x = c + M^T l


def _to_local(prism, x, direction=False):
    m = prism.world_to_local
    return (x if direction else x - np.asarray(prism.center)) @ m.T


def test_prism_deviation_formula():
    prism = Prism(eta=1.5, center=(2.0, -1.0, 3.0))
    n, A = prism.eta, math.radians(60.0)
    theta1 = np.linspace(30.0, 85.0, 56)
    o, d = _prism_rays(prism, theta1)
    res = SnellRenderer(prism).trace(o, d)
    assert np.all(res.status == Status.EXITED) and np.all(res.events == 2)
    t1 = np.radians(theta1)
    r1 = np.arcsin(np.sin(t1) / n)
    t2 = np.arcsin(n * np.sin(A - r1))
    delta = t1 + t2 - A
    assert np.abs(_angle(unit(d), res.direction) - delta).max() < 1e-12
    # it leaves through face 2, in the principal plane
    h = prism.side / (2 * math.sqrt(3.0))
    loc = _to_local(prism, res.surface)
    assert np.abs(loc @ np.array([S3, -0.5, 0.0]) - h).max() < 1e-10
    assert np.abs(_to_local(prism, res.direction, True)[:, 2]).max() < 1e-12

    # minimum deviation at symmetric passage: n = sin((A + delta_min) / 2) / sin(A / 2)
    t_min = math.degrees(math.asin(n * math.sin(A / 2)))
    o, d = _prism_rays(prism, [t_min - 2.0, t_min, t_min + 2.0])
    res = SnellRenderer(prism).trace(o, d)
    dev = _angle(unit(d), res.direction)
    assert dev[1] < dev[0] and dev[1] < dev[2]
    assert math.sin((A + dev[1]) / 2) / math.sin(A / 2) == pytest.approx(n, abs=1e-12)


def test_prism_total_internal_reflection():
    prism = Prism(eta=1.5)
    n, A = prism.eta, math.radians(60.0)
    th = 10.0  # internal angle at face 2: 60 - 6.65 = 53.35 > critical 41.8 degrees
    o, d = _prism_rays(prism, th)
    r1 = math.asin(math.sin(math.radians(th)) / n)
    assert A - r1 > math.asin(1 / n)
    n1_loc = np.array([-S3, -0.5, 0.0])
    n2_loc = np.array([S3, -0.5, 0.0])
    h = prism.side / (2 * math.sqrt(3.0))

    # one event: Snell at face 1, then the cap stops the ray inside
    r = SnellRenderer(prism, max_events=1).trace(o, d)
    assert r.status[0] == Status.TRAPPED and r.events[0] == 1
    d_in = _to_local(prism, r.direction[0], True)
    assert math.degrees(_angle(d_in, -n1_loc)) == pytest.approx(math.degrees(r1), abs=1e-10)
    assert abs(d_in[2]) < 1e-14

    # two events: the second is a mirror reflection at face 2
    r = SnellRenderer(prism, max_events=2).trace(o, d)
    assert r.status[0] == Status.TRAPPED and r.events[0] == 2
    d_ref = _to_local(prism, r.direction[0], True)
    mirror = d_in - 2 * (d_in @ n2_loc) * n2_loc
    assert np.abs(d_ref - mirror).max() < 1e-13
    assert _to_local(prism, r.surface[0]) @ n2_loc == pytest.approx(h, abs=1e-10)
    assert np.array_equal(r.position, r.surface)  # a trapped ray reports its last event

    # uncapped: it leaves after three events, in the principal plane, as the reference says
    r = SnellRenderer(prism).trace(o, d)
    ref = snell_numpy(prism, o, d)
    assert r.status[0] == Status.EXITED and r.events[0] == ref.events[0] == 3
    assert np.abs(r.direction - ref.direction).max() < 1e-12
    assert abs(_to_local(prism, r.direction[0], True)[2]) < 1e-12


# ------------------------------------------------------------------------------- drop


def test_drop_surface_points_and_axial_angular_momentum():
    drop, spread = SOLIDS["drop"]
    o, d = camera_rays(4000, spread, seed=2)
    res = SnellRenderer(drop).trace(o, d)
    hit = res.status != Status.MISSED
    assert hit.sum() > 1500
    assert np.any(res.events > 2)  # total internal reflection inside the drop happens
    assert np.abs(drop_F(res.surface[hit] - np.asarray(drop.center), drop.R, drop.H)).max() < 1e-8
    # the normal of a body of revolution lies in the meridional plane: L_z is conserved
    du = unit(d)
    lz0 = o[:, 0] * du[:, 1] - o[:, 1] * du[:, 0]
    lz1 = res.surface[:, 0] * res.direction[:, 1] - res.surface[:, 1] * res.direction[:, 0]
    ok = res.status == Status.EXITED
    assert np.abs(lz1 - lz0)[ok].max() < 1e-11


# -------------------------------------------------------------------- kernel vs reference


@pytest.mark.parametrize("kind", list(SOLIDS))
def test_kernel_matches_numpy_reference(kind):
    solid, spread = SOLIDS[kind]
    o, d = camera_rays(300, spread, seed=4)
    res = SnellRenderer(solid, precision="float64").trace(o, d)
    ref = snell_numpy(solid, o, d)
    assert np.array_equal(res.status, ref.status)
    assert np.array_equal(res.events, ref.events)
    assert set(np.unique(res.status)) <= {Status.EXITED, Status.MISSED, Status.TRAPPED}
    assert (res.status == Status.EXITED).sum() > 50 and (res.status == Status.MISSED).sum() > 0
    # the drop reference finds crossings independently (dense sampling), to bisection tolerance
    tol = 1e-7 if kind == "drop" else 1e-11
    assert np.abs(res.direction - ref.direction).max() < tol
    assert np.abs(res.surface - ref.surface).max() < 100 * tol
    assert np.abs(res.position - ref.position).max() < 1e4 * tol
    assert np.allclose(np.linalg.norm(res.direction, axis=1), 1.0, atol=1e-14)
    ex = res.status == Status.EXITED
    assert np.allclose(np.abs(res.position[ex]).max(1), 50.0, atol=1e-9)


@pytest.mark.parametrize("kind", list(SOLIDS))
def test_float32_close_to_float64(kind):
    solid, spread = SOLIDS[kind]
    o, d = camera_rays(3000, spread, seed=5)
    r64 = SnellRenderer(solid, precision="float64").trace(o, d)
    r32 = SnellRenderer(solid, precision="float32").trace(o, d)
    assert (r32.status == r64.status).mean() > 0.99
    hit = (r64.status == Status.EXITED) & (r32.status == Status.EXITED)
    err = _angle(r32.direction[hit], r64.direction[hit])
    assert np.median(err) < 2e-6
    assert np.percentile(err, 95) < 2e-5


# ----------------------------------------------------------------------------- misses


@pytest.mark.parametrize("kind", list(SOLIDS))
def test_missed_rays_keep_their_direction(kind):
    solid, _ = SOLIDS[kind]
    c = np.asarray(solid.center)
    rng = np.random.default_rng(6)
    o = c + np.array([-150.0, 0.0, 0.0]) + rng.uniform(-1, 1, (50, 3))
    d = np.column_stack([np.ones(50), np.full(50, 0.5), np.full(50, 0.7)])  # far above it
    res = SnellRenderer(solid).trace(o, 3.0 * d)
    assert np.all(res.status == Status.MISSED) and np.all(res.events == 0)
    assert np.abs(res.direction - unit(d)).max() < 1e-15
    assert np.array_equal(res.position, o)
    ref = snell_numpy(solid, o, d)
    assert np.all(ref.status == Status.MISSED)


def test_inputs_are_checked():
    with pytest.raises(ClrefractError, match="Sphere, Prism or Drop"):
        SnellRenderer(Luneburg())
    s = SnellRenderer(Sphere(radius=20.0))
    with pytest.raises(ClrefractError, match="inside"):
        s.trace(np.zeros((1, 3)), np.array([[1.0, 0.0, 0.0]]))
    with pytest.raises(ClrefractError, match="zero vector"):
        s.trace(np.array([[-100.0, 0.0, 0.0]]), np.zeros((1, 3)))
    with pytest.raises(ClrefractError, match="shape"):
        s.trace(np.zeros((2, 2)), np.zeros((2, 2)))
    with pytest.raises(ClrefractError, match="max_events"):
        SnellRenderer(Sphere(), max_events=0)
    empty = s.trace(np.empty((0, 3)), np.empty((0, 3)))
    assert empty.direction.shape == (0, 3)
