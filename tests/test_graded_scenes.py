"""The graded development scenes of `clrefract dataset make` (blobs, grin-rod, grin-lens,
plume): each field's kernel against its NumPy reference and that against finite differences,
the rod's rays against the Selfoc closed form, the seeded blob cluster, every scene held
inside the box, and each scene made and checked as a dataset."""

import json

import numpy as np
import pytest

from clrefract.cli import main
from clrefract.dataset import check_dataset
from clrefract.family import central_grad
from clrefract.fields import field_from_dict, field_from_spec
from clrefract.fields.analytic import GrinRod
from clrefract.fields.base import Box
from clrefract.synth import GRADED, MakeOptions, make_dataset, scene_object
from clrefract.tracer import Tracer, TraceSettings

NEW = ("blobs", "grin-rod", "grin-lens", "plume")


def _points(field, n=3000, seed=0):
    """Points over the box, half of them where eta - 1 exceeds a thousandth of its peak."""
    rng = np.random.default_rng(seed)
    pts = rng.uniform(-45, 45, (40 * n, 3))
    hot = field.eval(pts)[0] - 1 > 1e-3 * (field.eta_max - 1)
    assert hot.sum() >= n // 2
    return np.concatenate([pts[hot][: n // 2], pts[~hot][: n - n // 2]])


def _walls(n=61):
    """A grid of n x n points on each of the default box's six walls."""
    box = Box()
    lo, hi = np.asarray(box.lo), np.asarray(box.hi)
    u = np.linspace(0, 1, n)
    uv = np.stack(np.meshgrid(u, u, indexing="ij"), -1).reshape(-1, 2)
    out = []
    for axis in range(3):
        other = [k for k in range(3) if k != axis]
        for wall in (lo[axis], hi[axis]):
            p = np.full((len(uv), 3), wall)
            p[:, other] = lo[other] + uv * (hi - lo)[other]
            out.append(p)
    return np.concatenate(out)


def test_graded_scenes_are_listed(capsys):
    with pytest.raises(SystemExit):
        main(["dataset", "make", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    for name in NEW:
        assert name in GRADED and name in text


@pytest.mark.parametrize("name", NEW)
@pytest.mark.parametrize(
    "precision,lanes,eta_tol,grad_tol",
    [("float64", 8, 1e-13, 1e-12), ("float32", 16, 1e-6, 1e-5), ("float32", 1, 1e-6, 1e-5)],
)
def test_kernel_matches_numpy_reference(name, precision, lanes, eta_tol, grad_tol):
    field = scene_object(name)
    pts = _points(field)
    settings = TraceSettings(precision=precision, lanes=lanes)
    eta, grad = Tracer(field, settings=settings).eval_field(pts)
    eta_ref, grad_ref = field.eval(pts)
    assert np.abs(eta - eta_ref).max() < eta_tol
    assert np.abs(grad - grad_ref).max() < grad_tol * np.abs(grad_ref).max()


@pytest.mark.parametrize("name", NEW)
def test_reference_gradient_matches_finite_differences(name):
    field = scene_object(name)
    pts = _points(field, 1000, seed=1)
    _, grad = field.eval(pts)
    fd = central_grad(lambda p: field.eval(p)[0], pts, 1e-5)
    scale = np.abs(grad).max()
    assert scale > 1e-4  # the sample saw a non-trivial gradient
    assert np.abs(fd - grad).max() < 1e-6 * scale


@pytest.mark.parametrize("name", NEW)
def test_fields_round_trip_through_json(name):
    field = scene_object(name, seed=4)
    again = field_from_dict(json.loads(json.dumps(field.to_dict())))
    assert again == field
    pts = _points(field, 200)
    assert np.array_equal(again.eval(pts)[0], field.eval(pts)[0])


def test_grin_rod_ray_follows_the_selfoc_closed_form():
    """In the rod's core a meridional ray keeps beta = eta cos(theta) and follows
    rho(z) = rho_max sin(Omega z + phase), Omega = a n0 / beta."""
    rod = scene_object("grin-rod")
    n0, a, m = rod.n0, rod.a, rod.world_to_local
    # eta on the axis is n0, and 1 (continuous with the air) at the radius
    on = np.array([[0.0, 0.0, 0.0], [rod.radius, 0.0, 0.0], [0.0, rod.radius, 5.0]]) @ m
    assert np.abs(rod.eval(on)[0] - [n0, 1.0, 1.0]).max() < 1e-12
    rng = np.random.default_rng(2)
    k = 12
    rho0, theta = rng.uniform(2, 8, k), rng.uniform(-0.2, 0.2, k)
    phi = rng.uniform(0, 2 * np.pi, k)
    radial = np.column_stack([np.cos(phi), np.sin(phi), np.zeros(k)])
    axis = np.array([0.0, 0.0, 1.0])
    z0 = -15.0  # the exact profile holds for |z| < L/2 - cap = 17
    x0 = rho0[:, None] * radial + z0 * axis
    d0 = np.sin(theta)[:, None] * radial + np.cos(theta)[:, None] * axis
    eta0 = n0 * np.sqrt(1 - a**2 * rho0**2)
    beta = eta0 * np.cos(theta)
    sigma, n_steps = 30.0 / n0, 400  # dz/dsigma = beta < n0: z stays below 15
    tracer = Tracer(
        rod, settings=TraceSettings(precision="float64", integrator="rkn4", step=sigma / n_steps)
    )
    x, v = tracer.propagate(x0 @ m, eta0[:, None] * d0 @ m, n_steps)
    x, v = x @ m.T, v @ m.T  # back to the rod's frame
    z1 = z0 + beta * sigma
    omega = a * n0 / beta
    rho_max = np.hypot(rho0, np.tan(theta) / omega)
    phase = np.arctan2(rho0 * omega, np.tan(theta)) - omega * z0
    rho = rho_max * np.sin(omega * z1 + phase)
    slope = rho_max * omega * np.cos(omega * z1 + phase)
    assert rho_max.max() < rod.radius  # the rays stay in the profile
    assert (omega * (z1 - z0)).min() > 0.5  # and bend visibly
    exp_x = rho[:, None] * radial + z1[:, None] * axis
    exp_v = beta[:, None] * (slope[:, None] * radial + axis)
    assert np.abs(x - exp_x).max() < 1e-8
    assert np.abs(v - exp_v).max() < 1e-9


def test_blob_cluster_is_drawn_by_the_seed_inside_the_box():
    a, b, c = (scene_object("blobs", seed=s) for s in (7, 7, 8))
    assert a == b and a.to_dict() == b.to_dict()
    assert a.centers != c.centers and a.sigmas != c.sigmas
    assert scene_object("blobs") == scene_object("blobs", seed=0)
    walls = _walls(41)
    for seed in range(12):
        f = scene_object("blobs", seed=seed)
        assert len(f.amplitudes) == 5
        assert np.all(np.abs(f.centers) <= 16.0)
        assert np.all((np.asarray(f.sigmas) >= 5.0) & (np.asarray(f.sigmas) <= 8.0))
        assert 1.05 < f.eval(np.asarray(f.centers))[0].max() < 1.5
        assert f.eval(walls)[0].max() - 1 < 1e-4


@pytest.mark.parametrize("name", NEW)
def test_scenes_are_negligible_at_the_box_walls(name):
    field = scene_object(name)
    eta, grad = field.eval(_walls())
    peak = field.eval(_points(field, 2000))[0].max() - 1
    limit = 1e-4 if name == "blobs" else 1e-6 * peak
    assert eta.max() - 1 < limit and eta.min() >= 1.0
    assert np.abs(grad).max() < limit


def test_scene_contrasts():
    """The rod and the lens reach their peak index at their centres; the plume's column is
    about 1e-3 above 1 at its base, fades with height and widens as sigma0 + spread zeta."""
    rod, lens, plume = (scene_object(n) for n in ("grin-rod", "grin-lens", "plume"))
    assert rod.eval(np.zeros((1, 3)))[0][0] == pytest.approx(1.2, abs=1e-12)
    assert lens.eval(np.zeros((1, 3)))[0][0] == pytest.approx(1.4, abs=1e-12)
    g = np.linspace(-24, 24, 161)
    xy = np.stack(np.meshgrid(g, g, indexing="ij"), -1).reshape(-1, 2)
    z = np.arange(-31.0, 42.0, 2.0)
    peak, width = [], []
    for zk in z:
        f = plume.eval(np.column_stack([xy, np.full(len(xy), zk)]))[0] - 1
        peak.append(f.max())
        if f.sum() > 0:  # the Gaussian's sigma from its second moment about its centroid
            c = (f[:, None] * xy).sum(0) / f.sum()
            width.append(np.sqrt((f * ((xy - c) ** 2).sum(1)).sum() / (2 * f.sum())))
        else:
            width.append(0.0)
    peak, width = np.array(peak), np.array(width)
    assert peak[0] == 0 and peak[-1] == 0  # nothing below the source or above the top
    assert 0.7e-3 < peak.max() < 1e-3 and z[np.argmax(peak)] < -20
    assert np.all(np.diff(peak[z > -20]) < 0)  # fading with height
    zeta = z - (plume.center[2] - plume.half_height)
    live = peak > 1e-3 * peak.max()
    expected = plume.sigma0 + plume.spread * zeta
    assert np.abs(width[live] / expected[live] - 1).max() < 0.01
    assert expected[live].max() > 3 * plume.sigma0  # widening a lot


@pytest.mark.parametrize("name", NEW)
def test_scene_makes_a_clean_dataset(name, tmp_path):
    opt = MakeOptions(views=3, res=12, env_width=128, volume_res=12, seed=5)
    info = make_dataset(name, tmp_path, opt)
    assert info["untraced_pixels"] == 0 and check_dataset(tmp_path) == []
    scene = json.loads((tmp_path / "scene.json").read_text())
    assert field_from_dict(scene["object"]) == scene_object(name, seed=5)
    assert scene["ground_truth"]["renderer"] == "eikonal-f64"


def test_dataset_make_cli_takes_the_graded_scenes(tmp_path, capsys):
    out = tmp_path / "rod"
    args = ["dataset", "make", "grin-rod", "--out", str(out), "--views", "2", "--res", "8"]
    assert main([*args, "--env-width", "64"]) == 0
    assert main(["dataset", "check", str(out)]) == 0
    assert field_from_spec("grin-rod:n0=1.3,radius=10") == GrinRod(n0=1.3, radius=10.0)
