"""Every kernel family builds and runs at every lane width device selection can pick, on
whatever driver runs the tests, and the driver probe behind that choice."""

import subprocess
from dataclasses import replace

import numpy as np
import pytest

from clrefract import locations, probe, runtime
from clrefract.envmap import EnvMap
from clrefract.errors import BuildError, ClrefractError
from clrefract.fields import field_from_spec
from clrefract.fields.base import Box
from clrefract.fields.hashgrid import HashGridConfig, HashGridField
from clrefract.fields.levelset import LevelSetField
from clrefract.fields.voxel import VoxelGrid
from clrefract.gradient import GradientEngine
from clrefract.runtime import default_runtime
from clrefract.snell import SnellRenderer
from clrefract.tracer import Status, Tracer, TraceSettings

BOX = Box()
ANALYTIC = [
    "luneburg",
    "maxwell",
    "fibre",
    "blobs",
    "sphere",
    "prism",
    "drop",
    "grin-rod",
    "grin-lens",
    "plume",
]
FITTED = [
    "voxel-trilinear",
    "voxel-smoothstep",
    "voxel-bspline",
    "levelset",
    "hashgrid",
    "hashgrid-ramp",
]


def _selected_widths():
    """(precision, lanes) pairs selection can produce: the default per precision, and 1."""
    rt = default_runtime()
    pairs = {("float32", rt.default_lanes("float32")), ("float32", 1)}
    if rt.info.fp64:
        pairs.add(("float64", rt.default_lanes("float64")))
    return sorted(pairs)


def _fitted_field(kind: str):
    g = np.linspace(-1, 1, 12)
    x, y, z = np.meshgrid(g, g, g, indexing="ij")
    r = np.sqrt(x**2 + y**2 + z**2) * 50
    if kind.startswith("voxel"):
        return VoxelGrid(1 + 0.3 * np.exp(-((r / 18) ** 2)), BOX, interp=kind.split("-")[1])
    if kind == "levelset":
        return LevelSetField(r - 20, BOX, eta=1.5, width=4.0)
    cfg = HashGridConfig(levels=3, log2_table=10, n_min=4, n_max=16, hidden=8, eta_max=1.5)
    if kind == "hashgrid":
        return HashGridField(cfg, BOX, seed=1)
    # the ramp output with o across both of its ends (interface steps when rendering);
    # weak, as a strong random field is chaotic and lane widths then differ by rounding
    f = HashGridField(replace(cfg, output="ramp", eta_max=1.05), BOX, seed=1)
    p = f.data().copy()
    p[f.table_slice] = np.random.default_rng(2).uniform(-3, 3, cfg.n_table_params)
    p[-1 - cfg.hidden : -1] *= 4.0
    p[-1] = 4.4
    f.set_data(p)
    return f


def _rays(n=32, seed=0):
    rng = np.random.default_rng(seed)
    target = rng.uniform(-15, 15, size=(n, 3))
    origins = np.tile([0.0, -150.0, 0.0], (n, 1)) + rng.normal(scale=5, size=(n, 3))
    d = target - origins
    return origins, d / np.linalg.norm(d, axis=1, keepdims=True)


def _trace(field, precision, lanes):
    tr = Tracer(field, BOX, TraceSettings(step=0.5, precision=precision, lanes=lanes))
    o, d = _rays()
    res = tr.trace(o, d)
    return res


@pytest.mark.parametrize("precision,lanes", _selected_widths())
@pytest.mark.parametrize("kind", ANALYTIC)
def test_analytic_trace_builds_and_agrees_with_one_lane(kind, precision, lanes):
    field = field_from_spec(kind)
    res = _trace(field, precision, lanes)
    ref = _trace(field, precision, 1)
    assert np.all(res.status != Status.NONFINITE) and np.all(np.isfinite(res.direction))
    assert np.array_equal(res.status, ref.status)
    out = res.status == Status.EXITED
    if kind == "fibre":  # the fibre guides these rays to the step cap: compare them there
        out = res.status == Status.TRAPPED
    assert out.sum() >= 8, np.bincount(res.status)  # never a check over no ray
    tol = 1e-4 if precision == "float32" else 1e-10
    assert np.abs(res.direction - ref.direction)[out].max() < tol


@pytest.mark.parametrize("precision,lanes", _selected_widths())
@pytest.mark.parametrize("kind", FITTED)
def test_fitted_forward_and_backward_build_and_agree_with_one_lane(kind, precision, lanes):
    env = EnvMap.procedural(64, 32, seed=3)
    o, d = _rays(48, seed=2)
    target = np.full((len(o), 3), 0.3)
    grads = []
    for p, n in ((precision, lanes), (precision, 1)):
        eng = GradientEngine(
            _fitted_field(kind), BOX, TraceSettings(step=0.5, precision=p, lanes=n)
        )
        r = eng.loss_and_grad(o, d, target, env)
        assert np.isfinite(r.loss) and np.all(np.isfinite(r.grad))
        grads.append(r.grad)
    g, g1 = grads
    assert np.abs(g1).max() > 0, "no ray carried gradient"
    tol = 1e-3 if precision == "float32" else 1e-9
    assert np.abs(g - g1).max() <= tol * np.abs(g1).max()
    # rendering (interface steps where the field has kinks) agrees too
    field = _fitted_field(kind)
    res, ref = _trace(field, precision, lanes), _trace(field, precision, 1)
    assert np.array_equal(res.status, ref.status)
    out = res.status == Status.EXITED
    assert out.sum() >= 8  # never a check over no ray
    tol = 1e-4 if precision == "float32" else 1e-10
    assert np.abs(res.direction - ref.direction)[out].max() < tol


@pytest.mark.parametrize("interp", ["trilinear", "bspline"])
def test_grids_of_other_shapes_in_other_boxes_share_one_program(interp):
    """The box and the node counts are data (fp's geometry), not build defines: two grids of
    other shapes in other boxes trace through one program, each by its own geometry, and
    each agrees with its own NumPy reference."""
    rt = default_runtime()
    rng = np.random.default_rng(5)
    boxes = [
        Box((-30.0, -20.0, -25.0), (30.0, 25.0, 20.0), 3.0),
        Box((-5.0, -40.0, 0.0), (55.0, 10.0, 45.0), 2.0),
    ]
    grids = [
        VoxelGrid(rng.uniform(1.0, 1.2, s), b, interp)
        for s, b in zip([(9, 12, 7), (14, 6, 10)], boxes)
    ]
    settings = TraceSettings(step=0.5, precision="float64" if rt.info.fp64 else "float32")
    first = Tracer(grids[0], boxes[0], settings, runtime=rt)
    built = len(rt.build_seconds)
    second = Tracer(grids[1], boxes[1], settings, runtime=rt)
    assert len(rt.build_seconds) == built and second.kernels is first.kernels
    tol = 1e-9 if settings.precision == "float64" else 1e-4
    for field, tr, box in zip(grids, (first, second), boxes):
        lo, hi = np.asarray(box.lo), np.asarray(box.hi)
        pts = rng.uniform(lo - 2, hi + 2, (256, 3))  # the window's ramps and beyond the box
        eta, grad = tr.eval_field(pts)
        want_eta, want_grad = field.eval(pts)
        assert np.abs(eta - want_eta).max() < tol
        assert np.abs(grad - want_grad).max() < tol * 10
        # rays leave through this grid's own box
        o = np.tile((lo + hi) / 2 + [0.0, 0.0, -200.0], (64, 1)) + rng.normal(0, 3, (64, 3))
        d = np.column_stack([rng.normal(0, 0.05, (64, 2)), np.ones(64)])
        res = tr.trace(o, d)
        out = res.status == Status.EXITED
        assert out.sum() >= 48
        near = dict(atol=100 * tol)
        on_wall = np.isclose(res.position, lo, **near) | np.isclose(res.position, hi, **near)
        assert np.all(on_wall[out].any(axis=1))


def _sphere_exit(o, d, radius, eta):
    """Closed form: a ray at impact parameter b < R through a sharp ball is turned towards
    its centre, in the plane of the ray and the centre, by 2 (asin(b/R) - asin(b/(eta R)))."""
    p = o - (o * d).sum(1, keepdims=True) * d  # the ray's closest approach to the centre
    b = np.linalg.norm(p, axis=1)
    s = np.minimum(b / radius, 1.0)
    turn = np.where(b < radius, 2 * (np.arcsin(s) - np.arcsin(s / eta)), 0.0)
    return np.cos(turn)[:, None] * d - np.sin(turn)[:, None] * p / b[:, None], b < radius


@pytest.mark.parametrize("precision", ["float32", "float64"])
def test_snell_kernel_builds_and_bends_as_the_closed_form(precision):
    """Exit directions through the ball against the closed form (measured off by 2.5e-15
    in float64 and 6.4e-7 in float32; the rays turn by up to 60 degrees)."""
    if precision == "float64" and not default_runtime().info.fp64:
        pytest.skip("no float64 on this device")
    o, d = _rays()
    f = field_from_spec("sphere")
    res = SnellRenderer(f, BOX, precision=precision).trace(o, d)
    assert np.all(res.status == Status.EXITED) and np.all(np.isfinite(res.direction))
    want, hit = _sphere_exit(o, d, f.radius, f.eta)
    assert hit.sum() >= 24 and np.abs(want - d).max() > 0.5  # most rays bent, some strongly
    tol = 5e-6 if precision == "float32" else 2e-14
    assert np.linalg.norm(res.direction - want, axis=1).max() < tol


def test_probe_passes_at_the_selected_widths_against_numpy():
    rt = default_runtime()
    for precision, lanes in _selected_widths():
        rec = probe.probe_width(rt, lanes, precision)
        assert rec["ok"], rec
        assert rec["error"] < (1e-4 if precision == "float32" else 1e-10)
        assert lanes in rt.lane_widths(precision)


def test_probe_reference_is_the_kernel_formula():
    # spot values of the closed form the kernel computes
    a = np.array([0.75, 1.5])
    s = np.clip(a - 0.5, 0, 1)
    want = (
        np.sqrt(a)
        + 1 / np.sqrt(a)
        + np.exp(-a)
        + np.log1p(a)
        + np.sin(a)
        + np.cos(a)
        + np.arccos(a - 1)
        + np.abs(1 - a)
        + np.floor(3 * a)
        + 1.25 * a
        + np.minimum(a, 1)
        + np.maximum(a, 1.5)
        + np.array([0.75, -1.5])
        + np.array([-1, 1])
        + s**3 * (s * (6 * s - 15) + 10)
        + np.array([0, 1])
        + np.array([3, 5])
    )
    assert np.allclose(probe.reference(a), want, rtol=1e-14)


def test_lane_report_is_cached_and_survives_an_aborting_driver(tmp_path, monkeypatch):
    monkeypatch.setenv("CLREFRACT_CACHE_DIR", str(tmp_path))
    info = default_runtime().info
    lines = [
        '{"lanes": 1, "ok": true}',
        '{"lanes": 2, "ok": true}',
        '{"lanes": 4, "ok": true}',
        '{"lanes": 8, "ok": false, "why": "wrong results (error 1e-2)"}',
    ]

    def aborting(cmd, **kw):  # a driver that dies at 16 lanes, as pip PoCL 3.0 did on znver3
        assert cmd[1:3] == ["-m", "clrefract.probe"]
        return subprocess.CompletedProcess(
            cmd, -6, "\n".join(lines) + "\n", "LLVM ERROR: Cannot select: fsqrt\n"
        )

    monkeypatch.setattr(probe.subprocess, "run", aborting)
    rep = probe.lane_report(info, "float32")
    assert rep["widths"] == [1, 2, 4]
    last = next(r for r in rep["results"] if r["lanes"] == 16)
    assert not last["ok"] and "code -6" in last["why"] and "LLVM ERROR" in last["why"]

    def must_not_run(cmd, **kw):
        raise AssertionError("the cached report should have been used")

    monkeypatch.setattr(probe.subprocess, "run", must_not_run)
    assert probe.lane_report(info, "float32")["widths"] == [1, 2, 4]


def test_lane_widths_the_driver_cannot_build_are_refused_in_one_line(monkeypatch):
    rt = runtime.Runtime(default_runtime().info.selector)
    monkeypatch.setattr(rt, "lane_widths", lambda precision: [1, 2, 4, 8])
    assert rt.default_lanes("float32") == (8 if rt.info.kind == "cpu" else 1)
    with pytest.raises(ClrefractError, match=r"cannot build float32 kernels at 16 lanes") as e:
        Tracer(field_from_spec("sphere"), BOX, TraceSettings(lanes=16), runtime=rt)
    assert "--lanes 8" in str(e.value) and "\n" not in str(e.value)
    monkeypatch.setattr(rt, "lane_widths", lambda precision: [])
    with pytest.raises(ClrefractError, match="cannot build clrefract's float32 kernels"):
        rt.default_lanes("float32")


def test_a_failed_build_is_one_line_naming_the_driver_with_the_log_on_disk(tmp_path, monkeypatch):
    monkeypatch.setenv("CLREFRACT_CACHE_DIR", str(tmp_path))
    rt = default_runtime()
    with pytest.raises(BuildError) as e:
        rt.build(["probe.cl"], {"LANES": 4}, "float32")  # without common.h: no realv
    msg = str(e.value)
    assert "\n" not in msg and "probe.cl" in msg and rt.info.driver in msg
    assert "--lanes 2" in msg and e.value.compiler_error
    logs = list((tmp_path / "build-logs").glob("probe-*.log"))
    assert len(logs) == 1 and rt.info.driver in logs[0].read_text()


def test_kernel_sources_are_found_beside_a_checkout_package(monkeypatch, tmp_path):
    """A checkout's clrefract/ reads kernels_cl/ beside it, whatever is installed (here a
    checkout laid out in tmp_path, so the test holds for a plain install too)."""
    (tmp_path / "clrefract").mkdir()
    (tmp_path / "kernels_cl").mkdir()
    (tmp_path / "kernels_cl" / "probe.cl").write_text(runtime.kernel_source("probe.cl"))

    def missing(name):
        raise ModuleNotFoundError("No module named 'clrefract.kernels_cl'")

    monkeypatch.setattr(locations.resources, "files", missing)
    monkeypatch.setattr(locations, "__file__", str(tmp_path / "clrefract" / "locations.py"))
    assert "probe_builtins" in locations.kernel_source("probe.cl")
    with pytest.raises(ClrefractError, match="no-such.cl"):
        locations.kernel_source("no-such.cl")
