"""A graded interior inside a sharp surface (fields/interior.py, SDF_GRADED in
kernels_cl/interface.cl): curved crossings against SciPy's DOP853, the gradient of every
parameter against central differences, the file, the graded-glass scenes, and a fit."""

from __future__ import annotations

import numpy as np
import pytest

from clrefract.errors import ClrefractError
from clrefract.fields.base import Box
from clrefract.fields.interface import PolytopeInterface, SphereInterface
from clrefract.fields.interior import N_COEFFS, GradedInterface
from clrefract.interface import InterfaceEngine, InterfaceTracer, interface_numpy
from clrefract.tracer import Status, TraceSettings

F64 = TraceSettings(precision="float64")
BOX = Box()
TERMS = [0.05, -0.03, 0.02, -0.2, -0.15, -0.1, 0.04, 0.0, -0.03]


def ball(step=None) -> GradedInterface:
    sphere = SphereInterface((1.0, -2.0, 0.5), 18.0, 1.5)
    return GradedInterface(sphere, TERMS, (0.0, 0.0, 0.0), 20.0, step)


def stone(step=None) -> GradedInterface:
    rng = np.random.default_rng(4)
    n = rng.normal(size=(7, 3))
    planes = np.column_stack([n * rng.uniform(0.8, 1.2, (7, 1)), rng.uniform(10, 14, 7)])
    box6 = np.column_stack([np.vstack([np.eye(3), -np.eye(3)]), np.full(6, 13.0)])
    solid = PolytopeInterface(np.vstack([planes, box6]), 1.5, BOX, (1.0, -0.5, 0.3))
    return GradedInterface(solid, TERMS, (1.0, 0.0, 0.0), 16.0, step)


def rays(n, seed, spread):
    rng = np.random.default_rng(seed)
    o = np.c_[rng.uniform(-spread, spread, (n, 2)), np.full(n, -80.0)]
    d = np.tile([0.0, 0.0, 1.0], (n, 1)) + rng.normal(0, 0.04, (n, 3))
    return o, d


@pytest.mark.parametrize("make", [ball, stone], ids=["sphere", "planes"])
def test_curved_crossings_match_scipy(make):
    """Rays through a quadratic index (contrast 0.3) inside a sphere and a polytope, at the
    default step (the box's side / 256): status, events and exit directions in float64
    against interface_numpy's DOP853 segments (rtol 1e-12) to 1e-9 rad; some rays reflect
    inside. Traced with the terms zeroed, the same rays leave as the constant solid's."""
    field = make()
    o, d = rays(50, 3, 14.0)
    tr = InterfaceTracer(field, BOX, F64)
    res = tr.trace(o, d)
    st, ref, ev = interface_numpy(field, BOX, o, d, curved=True)
    assert np.array_equal(res.status, st) and np.array_equal(tr.events, ev)
    assert (ev == 2).sum() > 10 and (ev > 2).sum() >= 1
    out = st == Status.EXITED
    angle = np.linalg.norm(res.direction[out] - ref[out], axis=1)  # arccos loses below 1e-8
    assert angle.max() < 1e-9, angle.max()
    flat = GradedInterface(field.solid, np.zeros(9), field.centre, field.scale)
    a = InterfaceTracer(flat, BOX, F64).trace(o, d).direction
    b = InterfaceTracer(field.solid, BOX, F64).trace(o, d).direction
    assert np.abs(a - b).max() < 1e-9
    assert np.abs(a - res.direction).max() > 0.05  # the grading bends the rays


@pytest.mark.parametrize("make", [ball, stone], ids=["sphere", "planes"])
def test_the_gradient_matches_central_differences(make):
    """Float64, no grazing cut: d J / d theta of J = sum w . exit direction through the
    entry, the curved path (the ray and its adjoint integrated back), the exit point on
    phi = 0 and Snell's law with the local index, for every parameter of the surface and
    the ten terms, against central differences (h = 1e-6) to 1e-4 relative."""
    field = make(step=0.2)
    o, d = rays(40, 11, 14.0)  # few: Oclgrind runs it (tools/oclgrind_check.py)
    w = np.random.default_rng(12).normal(size=(40, 3))

    def terminal(status, vel):
        ok = (status == Status.EXITED)[:, None]
        return float((w * vel * ok).sum()), w * ok, np.zeros_like(vel)

    eng = InterfaceEngine(field, BOX, F64, grazing_cos=0.0)
    grad = eng.loss_and_grad(o, d, None, None, terminal=terminal).grad
    p0 = field.data()
    for i in range(len(p0)):
        js = []
        for s in (1, -1):
            p = p0.copy()
            p[i] += s * 1e-6
            eng.set_params(p)
            js.append(eng.loss_and_grad(o, d, None, None, terminal=terminal).loss)
        fd = (js[0] - js[1]) / 2e-6
        assert abs(grad[i] - fd) <= 1e-4 * abs(fd) + 1e-9, (i, grad[i], fd)
    assert np.abs(grad[-9:]).min() > 1e-3  # every term bends the rays


def test_a_graded_file_round_trips(tmp_path):
    """field.npz keeps the surface's keys and adds the interior's; it loads as the same
    field, traced the same; a file with a broken interior is refused naming itself."""
    from clrefract.fields import load_field_file

    field = stone()
    field.save(tmp_path / "f.npz")
    back = load_field_file(tmp_path / "f.npz")
    assert isinstance(back, GradedInterface) and back.kind == "polytope"
    assert np.array_equal(back.data(), field.data())
    o, d = rays(40, 5, 14.0)
    a = InterfaceTracer(field, BOX, F64).trace(o, d).direction
    assert np.array_equal(a, InterfaceTracer(back, BOX, F64).trace(o, d).direction)
    with np.load(tmp_path / "f.npz") as z:
        arrays = {k: z[k] for k in z.files}
    np.savez(tmp_path / "bad.npz", **{**arrays, "interior": np.zeros(4)})
    with pytest.raises(ClrefractError, match="bad.npz: bad graded interior"):
        load_field_file(tmp_path / "bad.npz")


def test_the_graded_glass_scenes_hold_their_index(tmp_path):
    """`dataset make grin-ball` and `grin-stone`: scene.json's object rebuilds the field
    (its index at the centre and under the surface as drawn), and the renders differ from
    the same solid at one index."""
    from clrefract.dataset import Dataset
    from clrefract.fields import field_from_dict
    from clrefract.synth import MakeOptions, make_dataset, scene_object

    ball = scene_object("grin-ball")
    eta, _ = ball.eval(np.array([[0.0, 0.0, 0.0], [0.0, 17.99, 0.0], [0.0, 0.0, 17.99]]))
    assert np.allclose(eta, [1.6, 1.5, 1.52], atol=1e-3)
    for name, seed in (("grin-ball", 0), ("grin-stone", 3)):
        root = tmp_path / name
        make_dataset(
            name, root, MakeOptions(views=4, res=16, env_width=256, volume_res=8, seed=seed)
        )
        ds = Dataset(root)
        truth = field_from_dict(ds.scene.object)
        obj = scene_object(name, seed=seed)
        assert np.array_equal(truth.data(), obj.data())
        assert ds.scene.ground_truth["renderer"] == "interface-f64"
    a, b = scene_object("grin-stone", seed=3), scene_object("grin-stone", seed=4)
    assert not np.array_equal(a.data(), b.data())


def test_an_interior_a_field_cannot_take_is_refused(tmp_path, capsys):
    """A graded interior of a voxel grid, and the model choice's interior for one kind: one
    line each, exit status 2, nothing written."""
    from clrefract.cli import main

    code = main(
        [
            "fit",
            str(tmp_path),
            "--out",
            str(tmp_path / "r"),
            "--field-kind",
            "voxel",
            "--interior",
            "quadratic",
        ]
    )
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and "interior 'quadratic'" in err[0]
    assert not (tmp_path / "r").exists()
    code = main(["fit", str(tmp_path), "--out", str(tmp_path / "r"), "--field-kind", "polytope",
                 "--interior", "auto"])  # fmt: skip
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and "model choice's" in err[0]
    assert not (tmp_path / "r").exists()


def test_adam_on_the_terms_finds_a_cut_stones_graded_index(tmp_path):
    """The user's loop of ten lines: a grin-stone (16 views of 32 x 32) behind its true faces
    with one index 1.5 inside; Adam on the ten terms and the photometric loss of every pixel
    (float32). The index inside the stone comes within a fifth of its start's RMS error of
    the truth, and the loss falls tenfold (measured: 0.068 -> 0.0003, and 1.5e-3 -> 2.8e-5,
    in 200 steps)."""
    from clrefract.adam import Adam, ParamGroup
    from clrefract.dataset import Dataset
    from clrefract.synth import MakeOptions, make_dataset, scene_object

    root = tmp_path / "stone"
    make_dataset("grin-stone", root, MakeOptions(views=16, res=32, env_width=512, volume_res=8))
    ds = Dataset(root)
    o, d, px = ds.rays_and_pixels()
    truth = scene_object("grin-stone", seed=0)
    solid = PolytopeInterface(truth.solid.planes, 1.5, ds.box, truth.solid.centre)
    field = GradedInterface(solid, np.zeros(9), truth.centre, truth.scale)
    eng = InterfaceEngine(field, ds.box, TraceSettings())
    params, off = field.data(), field.shared_offset
    adam = Adam(len(params), [ParamGroup("interior", off, len(params), 0.005)])
    inside = np.random.default_rng(0).uniform(-30, 30, (20000, 3))
    inside = inside[truth.sdf(inside)[0] < -0.5]

    def error():
        return np.sqrt(np.mean((field.index(inside)[0] - truth.index(inside)[0]) ** 2))

    start_error = error()
    losses = []
    for k in range(200):
        r = eng.loss_and_grad(o, d, px, ds.envmap())
        losses.append(r.loss)
        adam.step(params, np.where(np.arange(len(params)) >= off, r.grad, 0.0), 0.05 ** (k / 200))
        eng.set_params(params)
    assert error() < start_error / 5, (start_error, error())
    assert losses[-1] < losses[0] / 10, (losses[0], losses[-1])


def test_a_graded_polytope_fit_runs_renders_and_resumes(tmp_path, capsys):
    """`fit --field-kind polytope --interior quadratic` on a small grin-stone: config.toml
    records the interior, field.npz and the run's checkpoint hold the graded field (the
    terms moved from 0), `render` draws the run, and `--resume` of the finished run takes
    the checkpoint back without a word about its parameters."""
    from clrefract.cli import main
    from clrefract.fields import load_field_file
    from clrefract.fit.session import field_from_run
    from clrefract.synth import MakeOptions, make_dataset

    data, run = tmp_path / "stone", tmp_path / "run"
    make_dataset("grin-stone", data, MakeOptions(views=12, res=32, env_width=512, volume_res=8))
    fit = ["fit", str(data), "--out", str(run), "--field-kind", "polytope"]
    fit += ["--interior", "quadratic", "--iterations", "40", "--rounding", "0", "-q"]
    assert main(fit) == 0
    assert 'interior = "quadratic"' in (run / "config.toml").read_text()
    saved = load_field_file(run / "field.npz")  # the best-validated field: the start's may be
    assert isinstance(saved, GradedInterface)
    terms = np.load(run / "checkpoint.npz")["params"][-(N_COEFFS - 1) :]
    assert np.abs(terms).max() > 1e-4  # the last step's
    # the interior's frame as the start placed it, recorded: the checkpoint's field is the run's
    back = field_from_run(run)
    assert isinstance(back, GradedInterface) and back.scale == saved.scale
    assert np.array_equal(back.centre, saved.centre)
    assert "interior_frame = [" in (run / "config.toml").read_text()
    assert (
        main(
            [
                "render",
                "--field",
                str(run),
                "--dataset",
                str(data),
                "--only",
                "0",
                "--out",
                str(tmp_path / "img"),
                "-q",
            ]
        )
        == 0
    )
    assert len(list((tmp_path / "img").glob("*.exr"))) == 1
    capsys.readouterr()
    assert main([*fit[:4], "--resume", "-q"]) == 0, capsys.readouterr().err
