"""Voxel grid field: kernel against the NumPy reference, exact gradients, files."""

import json

import numpy as np
import pytest

from clrefract.errors import ClrefractError
from clrefract.fields import load_field_file
from clrefract.fields.analytic import Sphere
from clrefract.fields.base import Box
from clrefract.fields.voxel import VoxelGrid
from clrefract.tracer import Tracer, TraceSettings

BOX = Box()  # [-50, 50]^3, margin 4: window ramps over 4..8 mm from each wall
SHAPE = (9, 10, 11)  # distinct per axis, so a swapped axis or index order shows
INTERPS = ("trilinear", "smoothstep", "bspline")
CONFIGS = [("float64", 1), ("float64", 16), ("float32", 1), ("float32", 16)]


def random_grid(interp, seed=0):
    vals = 1.0 + 0.5 * np.random.default_rng(seed).random(SHAPE)
    return VoxelGrid(vals, BOX, interp)


_TRACERS: dict = {}


def tracer(field, precision, lanes):
    key = (id(field), precision, lanes)
    if key not in _TRACERS:
        _TRACERS[key] = Tracer(field, BOX, TraceSettings(precision=precision, lanes=lanes))
    return _TRACERS[key]


GRIDS = {interp: random_grid(interp) for interp in INTERPS}


def node_planes(axis):
    return np.linspace(BOX.lo[axis], BOX.hi[axis], SHAPE[axis])


def face_distance(pts):
    """Distance (mm) of each point to the nearest node plane, over the three axes."""
    d = [np.abs(pts[:, a, None] - node_planes(a)[None, :]).min(1) for a in range(3)]
    return np.min(d, axis=0)


def sample_points(offset, n=3000, seed=3):
    """Uniform points (some outside the box), points in the window ramp, and points at
    `offset` from a cell face along one axis (offset 0: exactly on it)."""
    rng = np.random.default_rng(seed)
    uni = rng.uniform(-55, 55, (n, 3))
    ramp = rng.uniform(-42, 42, (n, 3))
    walls = np.where(rng.random((n, 3)) < 0.5, -50.0, 50.0)
    depth = rng.uniform(3.5, 8.5, (n, 3))
    pick = rng.random((n, 3)) < 0.5
    ramp[pick] = (walls - np.sign(walls) * depth)[pick]
    face = rng.uniform(-49, 49, (n, 3))
    ax = rng.integers(0, 3, n)
    for a in range(3):
        m = ax == a
        planes = node_planes(a)[1:-1]
        face[m, a] = rng.choice(planes, m.sum()) + offset * rng.choice([-1, 1], m.sum())
    return np.concatenate([uni, ramp, face])


@pytest.mark.parametrize("interp", INTERPS)
@pytest.mark.parametrize("precision,lanes", CONFIGS)
def test_kernel_matches_numpy_reference(interp, precision, lanes):
    field = GRIDS[interp]
    tr = tracer(field, precision, lanes)
    if precision == "float64":
        pts = sample_points(0.0)
        eta, grad = tr.eval_field(pts)
        eta_ref, grad_ref = field.eval(pts)
        assert np.abs(eta - eta_ref).max() < 1e-14
        assert np.abs(grad - grad_ref).max() < 1e-15
        return
    # float32: the reference at the rounded points. Exactly on a face the two precisions may
    # pick different cells (same eta, one-sided gradients), so gradients off the faces.
    on = sample_points(0.0).astype(np.float32).astype(np.float64)
    eta, _ = tr.eval_field(on)
    assert np.abs(eta - field.eval(on)[0]).max() < 2e-6  # measured 6e-7
    pts = sample_points(1e-3).astype(np.float32).astype(np.float64)
    eta, grad = tr.eval_field(pts)
    eta_ref, grad_ref = field.eval(pts)
    assert np.abs(eta - eta_ref).max() < 2e-6
    assert np.abs(grad - grad_ref).max() < 3e-6 * np.abs(grad_ref).max()  # measured 8e-7


def central_fd(f, pts, h):
    out = np.empty_like(pts)
    for k in range(3):
        e = np.zeros(3)
        e[k] = h
        out[:, k] = (f(pts + e) - f(pts - e)) / (2 * h)
    return out


@pytest.mark.parametrize("interp", INTERPS)
def test_gradient_matches_finite_differences(interp):
    field = GRIDS[interp]
    h = 1e-5
    pts = sample_points(0.0, n=1000)
    if interp == "trilinear":
        pts = pts[face_distance(pts) > 10 * h]  # the gradient jumps across cell faces
    _, grad = field.eval(pts)
    scale = np.abs(grad).max()
    assert scale > 1e-2  # the sample saw a non-trivial gradient
    # smoothstep: the second derivative jumps at faces, so the FD error is O(h) there
    # (measured 3e-7 relative); 3e-10 elsewhere. B-spline: C2, only the third jumps.
    tol = 1e-6 if interp == "smoothstep" else 1e-9
    fd_ref = central_fd(lambda p: field.eval(p)[0], pts, h)
    assert np.abs(fd_ref - grad).max() < tol * scale
    off_faces = face_distance(pts) > 1e-3
    assert np.abs(fd_ref - grad)[off_faces].max() < 1e-9 * scale  # measured 3e-10
    tr = tracer(field, "float64", 16)
    fd_kernel = central_fd(lambda p: tr.eval_field(p)[0], pts, h)
    assert np.abs(fd_kernel - tr.eval_field(pts)[1]).max() < tol * scale


@pytest.mark.parametrize("precision,lanes,tol", [("float64", 16, 1e-13), ("float32", 1, 2e-6)])
def test_trilinear_reproduces_a_linear_field(precision, lanes, tol):
    a = np.array([0.002, -0.001, 0.003])
    nodes = VoxelGrid(np.ones(SHAPE), BOX).node_points()
    field = VoxelGrid((1.5 + nodes @ a).reshape(SHAPE), BOX, "trilinear")
    pts = np.random.default_rng(5).uniform(-41.9, 41.9, (3000, 3))  # W = 1 here
    pts[:500, 0] = node_planes(0)[1:-1].repeat(100)[:500]  # and on faces
    pts = pts.astype(np.float32).astype(np.float64)
    for eta, grad in (field.eval(pts), tracer(field, precision, lanes).eval_field(pts)):
        assert np.abs(eta - (1.5 + pts @ a)).max() < tol
        assert np.abs(grad - a).max() < tol


@pytest.mark.parametrize("evaluate", ["numpy", "kernel"])
def test_smooth_gradients_are_continuous_across_faces_trilinear_is_not(evaluate):
    rng = np.random.default_rng(7)
    d = 1e-7
    jumps = {}
    for interp in INTERPS:
        field = GRIDS[interp]
        tr = tracer(field, "float64", 16)
        ev = field.eval if evaluate == "numpy" else tr.eval_field
        for axis in range(3):
            pts = rng.uniform(-40, 40, (200, 3))  # W = 1 here
            planes = node_planes(axis)
            pts[:, axis] = rng.choice(planes[(planes > -40) & (planes < 40)], 200)
            e = np.zeros(3)
            e[axis] = d
            jump = np.abs(ev(pts + e)[1] - ev(pts - e)[1]).max(0)  # per component
            jumps[interp, axis] = jump
            scale = np.abs(ev(pts + 5.0 * e / d)[1]).max()
            if interp != "trilinear":
                assert jump.max() < 1e-5 * scale
            else:
                assert jump[axis] > 0.1 * scale  # the normal derivative jumps
                tangential = np.delete(jump, axis)
                assert tangential.max() < 1e-5 * scale  # C0: tangential ones do not


def test_data_layout_defines_and_metadata():
    field = GRIDS["smoothstep"]
    nx, ny, nz = SHAPE
    i, j, k = 3, 7, 2
    assert field.data()[(i * ny + j) * nz + k] == field.values[i, j, k]
    assert field.defines() == {
        "FIELD_VOXEL": 1,
        "VOX_SMOOTH": 1,
        "VOX_BSPLINE": 0,
        "VOX_ZVEC": int(nz >= 4),
    }
    assert field.nodes() == (nx, ny, nz)  # data in fp, not build defines
    assert GRIDS["trilinear"].defines()["VOX_SMOOTH"] == 0
    assert GRIDS["bspline"].defines()["VOX_SMOOTH"] == 0
    assert GRIDS["bspline"].defines()["VOX_BSPLINE"] == 1
    assert field.uses_window()
    assert field.eta_max == field.values.max()
    d = field.to_dict()
    json.dumps(d)
    assert d["kind"] == "voxel" and d["shape"] == list(SHAPE) and "values" not in d
    # the node values are the samples; near the walls the window takes eta to 1
    eta, grad = field.eval(field.node_points())
    inner = np.all(np.abs(field.node_points()) < 42, axis=1)
    assert np.allclose(eta[inner], field.data()[inner], rtol=0, atol=1e-15)
    assert np.all(eta[~np.all(np.abs(field.node_points()) < 46, axis=1)] == 1.0)
    far = np.array([[60.0, 0.0, 0.0], [0.0, -70.0, 55.0]])
    assert np.all(field.eval(far)[0] == 1.0) and np.all(field.eval(far)[1] == 0.0)


def test_from_field_samples_the_nodes():
    sphere = Sphere(radius=20.0, eta=1.5, width=4.0)
    field = VoxelGrid.from_field(sphere, BOX, 21, "smoothstep")
    assert field.shape == (21, 21, 21) and field.interp == "smoothstep"
    assert np.array_equal(field.data(), sphere.eval(field.node_points())[0])
    assert field.eta_max == pytest.approx(1.5)
    assert VoxelGrid.from_field(sphere, BOX, (5, 6, 7)).shape == (5, 6, 7)


@pytest.mark.parametrize("interp", ["smoothstep", "bspline"])
def test_save_load_roundtrip(tmp_path, interp):
    box = Box((-10.0, -20.0, -30.0), (10.0, 20.0, 30.0), 2.0)
    field = VoxelGrid(1 + np.random.default_rng(1).random((4, 5, 6)), box, interp)
    path = tmp_path / "grid.npz"
    field.save(path)
    for back in (VoxelGrid.load(path), load_field_file(path)):
        assert isinstance(back, VoxelGrid)
        assert back.box == box and back.interp == interp
        assert np.array_equal(back.values, field.values)
    assert list(tmp_path.iterdir()) == [path]  # no temporary left behind


def _write(path, **arrays):
    base = dict(
        kind="voxel",
        values=np.ones((3, 3, 3)),
        lo=np.full(3, -1.0),
        hi=np.full(3, 1.0),
        margin=0.2,
        interp="trilinear",
    )
    base.update(arrays)
    with open(path, "wb") as f:
        np.savez(f, **{k: v for k, v in base.items() if v is not None})
    return path


@pytest.mark.parametrize(
    "make,message",
    [
        (lambda p: p, "not found"),
        (lambda p: p.write_bytes(b"not an npz at all") and p, "cannot read"),
        (lambda p: _write(p, values=None), "missing values"),
        (lambda p: _write(p, values=np.ones((3, 3))), "shape"),
        (lambda p: _write(p, values=np.ones((3, 1, 3))), "shape"),
        (lambda p: _write(p, values=np.full((3, 3, 3), np.nan)), "non-finite"),
        (lambda p: _write(p, values=np.full((3, 3, 3), 0.9)), "at least 1"),
        (lambda p: _write(p, interp="cubic"), "interp"),
        (lambda p: _write(p, lo=np.zeros(2)), "3 entries"),
        (lambda p: _write(p, kind="hashgrid"), "not a voxel grid"),
    ],
    ids=[
        "missing",
        "corrupt",
        "no-values",
        "2d",
        "one-node",
        "nan",
        "below-one",
        "interp",
        "box",
        "kind",
    ],
)
def test_load_errors_name_the_file(tmp_path, make, message):
    path = tmp_path / "bad.npz"
    make(path)
    with pytest.raises(ClrefractError) as exc:
        VoxelGrid.load(path)
    assert str(path) in str(exc.value) and message in str(exc.value)


def test_constructor_checks_and_the_eta_range(tmp_path):
    with pytest.raises(ClrefractError, match="interp"):
        VoxelGrid(np.ones((3, 3, 3)), BOX, "cubic")
    with pytest.raises(ClrefractError, match="non-finite"):
        VoxelGrid(np.full((3, 3, 3), np.inf), BOX)
    with pytest.raises(ClrefractError, match="exceed"):
        VoxelGrid(np.full((3, 3, 3), 2.0), BOX, eta_max=1.5)
    with pytest.raises(ClrefractError, match="at least 1"):
        VoxelGrid(np.full((3, 3, 3), 0.9), BOX, eta_max=1.5)
    # without a bound values below 1 are allowed (FD checks), but such a grid is not saved
    free = VoxelGrid(np.full((3, 3, 3), 0.9), BOX)
    path = tmp_path / "low.npz"
    with pytest.raises(ClrefractError, match="at least 1") as exc:
        free.save(path)
    assert str(path) in str(exc.value) and not path.exists()


def test_fitting_helpers():
    field = VoxelGrid(np.ones(SHAPE), BOX, "trilinear", eta_max=1.6)
    p = 1 + np.random.default_rng(2).normal(0, 0.5, field.values.size)
    q = p.copy()
    field.set_data(p)
    assert p.min() == 1.0 and p.max() == 1.6  # projected in place
    assert np.array_equal(field.data(), p)
    free = VoxelGrid(np.ones(SHAPE), BOX)
    free.set_data(q.copy())
    assert np.array_equal(free.data(), q)  # no bound: taken as they are
    # regulariser gradient against central differences along a random direction
    u = np.random.default_rng(3).normal(size=p.size)
    r, g = field.regularizer(p)
    e = 1e-6
    fd = (field.regularizer(p + e * u)[0] - field.regularizer(p - e * u)[0]) / (2 * e)
    assert fd == pytest.approx(g @ u, rel=1e-6) and r > 0
    # resampling a linear field onto a finer grid keeps it exactly
    a = np.array([0.002, -0.001, 0.003])
    lin = VoxelGrid((1.5 + field.node_points() @ a).reshape(SHAPE), BOX)
    fine = lin.resampled(17)
    assert fine.shape == (17, 17, 17)
    assert np.abs(fine.data() - (1.5 + fine.node_points() @ a)).max() < 1e-13


# --- tricubic B-spline ---------------------------------------------------------------------


def test_bspline_matches_scipy_spline_without_prefilter():
    """An independent oracle: scipy's order-3 spline of the node values taken as control
    points (prefilter=False), edge nodes repeated (mode="nearest") as the clamped indices."""
    from scipy.ndimage import map_coordinates

    field = GRIDS["bspline"]
    pts = np.random.default_rng(11).uniform(-50, 50, (3000, 3))
    u = ((pts - np.asarray(BOX.lo)) / field.spacing).T
    ref = map_coordinates(field.values, u, order=3, prefilter=False, mode="nearest")
    g, _ = field.interpolant(pts)
    assert np.abs(g - ref).max() < 1e-13


@pytest.mark.parametrize("precision,lanes,tol", [("float64", 16, 1e-13), ("float32", 1, 2e-6)])
def test_bspline_reproduces_a_linear_field_smoothstep_does_not(precision, lanes, tol):
    """Away from the border cells (clamped node indices) and inside the window, B-spline
    weights reproduce a linear ramp of nodes exactly, value and gradient; smoothstep turns it
    into terraces (gradient zero across every node plane)."""
    a = np.array([0.002, -0.001, 0.003])
    vals = (1.5 + VoxelGrid(np.ones(SHAPE), BOX).node_points() @ a).reshape(SHAPE)
    spline = VoxelGrid(vals, BOX, "bspline")
    pts = np.random.default_rng(5).uniform(-37.0, 37.0, (3000, 3))  # cells 1 .. n-3, W = 1
    pts[:500, 1] = node_planes(1)[2:-2].repeat(100)[:500]  # and on faces
    pts = pts.astype(np.float32).astype(np.float64)
    for eta, grad in (spline.eval(pts), tracer(spline, precision, lanes).eval_field(pts)):
        assert np.abs(eta - (1.5 + pts @ a)).max() < tol
        assert np.abs(grad - a).max() < tol
    eta, grad = VoxelGrid(vals, BOX, "smoothstep").eval(pts)
    assert np.abs(grad - a).max() > 0.5 * np.abs(a).max()  # terraces
    # the border cells do not reproduce it (node indices clamped there), nor does the window
    edge = np.array([[-45.0, 0.0, 0.0], [0.0, 0.0, 47.0]])
    assert np.abs(spline.eval(edge)[0] - (1.5 + edge @ a)).min() > 1e-4


def test_bspline_second_derivatives_are_continuous_across_faces_smoothstep_are_not():
    """C2 against C1: one-sided differences of the gradient just either side of a node plane
    agree for the B-spline and differ for smoothstep (kernel, float64)."""
    rng = np.random.default_rng(8)
    d = 1e-4
    rel = {}
    for interp in ("smoothstep", "bspline"):
        ev = tracer(GRIDS[interp], "float64", 16).eval_field
        worst = 0.0
        for axis in range(3):
            pts = rng.uniform(-35, 35, (200, 3))
            planes = node_planes(axis)
            pts[:, axis] = rng.choice(planes[(planes > -35) & (planes < 35)], 200)
            e = np.zeros(3)
            e[axis] = d
            right = (ev(pts + 2 * e)[1] - ev(pts + e)[1]) / d
            left = (ev(pts - e)[1] - ev(pts - 2 * e)[1]) / d
            worst = max(worst, np.abs(right - left).max() / np.abs(right).max())
        rel[interp] = worst
    assert rel["bspline"] < 1e-3 and rel["smoothstep"] > 0.1, rel


def test_bspline_from_field_takes_the_samples_as_control_points():
    """No prefilter: the node values are the samples, and the spline at a node is their
    (1, 4, 1) / 6 blend per axis, not the sample itself."""
    sphere = Sphere(radius=20.0, eta=1.5, width=4.0)
    field = VoxelGrid.from_field(sphere, BOX, 21, "bspline")
    assert field.interp == "bspline"
    nodes = field.node_points()
    assert np.array_equal(field.data(), sphere.eval(nodes)[0])
    v = field.values
    i, j, k = 10, 10, 13  # a node on the sphere's interface
    blend = np.einsum("a,b,c,abc->", *[np.array([1, 4, 1]) / 6] * 3, v[9:12, 9:12, 12:15])
    g, _ = field.interpolant(nodes[[(i * 21 + j) * 21 + k]])
    assert g[0] == pytest.approx(blend, abs=1e-14)
    assert abs(g[0] - v[i, j, k]) > 1e-3
    eta = field.eval(nodes)[0]  # non-negative weights summing to 1: within the samples' range
    assert eta.max() < 1.5 + 1e-12 and eta.min() > 1.0 - 1e-12


def test_bspline_resampling_keeps_a_linear_field():
    a = np.array([0.002, -0.001, 0.003])
    nodes = VoxelGrid(np.ones(SHAPE), BOX).node_points()
    lin = VoxelGrid((1.5 + nodes @ a).reshape(SHAPE), BOX, "bspline", eta_max=2.0)
    fine = lin.resampled(17)
    assert fine.interp == "bspline" and fine.eta_bound == 2.0
    pts = np.random.default_rng(4).uniform(-37, 37, (500, 3))
    assert np.abs(fine.eval(pts)[0] - (1.5 + pts @ a)).max() < 1e-13


@pytest.mark.parametrize("shape", [(2, 3, 2), (4, 5, 3), (3, 4, 4)])
def test_bspline_kernel_on_grids_with_fewer_than_4_nodes_per_axis(shape):
    """Small grids clamp most taps (and, under 4 nodes along z, take the kernel's per-tap
    gather path instead of its 4-vector row reads)."""
    field = VoxelGrid(1 + 0.5 * np.random.default_rng(9).random(shape), BOX, "bspline")
    pts = sample_points(0.0, n=500)
    eta_ref, grad_ref = field.eval(pts)
    for lanes in (1, 8):
        eta, grad = Tracer(field, BOX, TraceSettings(precision="float64", lanes=lanes)).eval_field(
            pts
        )
        assert np.abs(eta - eta_ref).max() < 1e-14
        assert np.abs(grad - grad_ref).max() < 1e-15
