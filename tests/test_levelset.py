"""Level-set field: kernels against the NumPy reference, the sharp surface it represents, its
adjoint against finite differences, files, and a fit that starts from the smoothed hull."""

import json
import re

import numpy as np
import pytest

from clrefract.errors import ClrefractError
from clrefract.fields import load_field_file
from clrefract.fields.base import Box
from clrefract.fields.levelset import LevelSetField
from clrefract.gradcheck import directional_errors, smooth_env
from clrefract.gradient import GradientEngine
from clrefract.tracer import Tracer, TraceSettings

BOX = Box(lo=(-30.0,) * 3, hi=(30.0,) * 3, margin=3.0)


def ellipsoid(res=16, width=4.0, noise=0.3, seed=0):
    rng = np.random.default_rng(seed)
    f = LevelSetField.from_sdf(
        lambda p: np.linalg.norm(p * [1.0, 1.1, 0.9], axis=1) - 15.0, BOX, res, 1.4, width
    )
    p = f.data()
    p[:-1] += noise * rng.normal(size=f.phi.size)
    f.set_data(p)
    return f


@pytest.mark.parametrize(
    "precision,lanes,tol", [("float64", 1, 1e-12), ("float64", 4, 1e-12), ("float32", 16, 2e-4)]
)
def test_kernel_matches_the_numpy_reference(precision, lanes, tol):
    f = ellipsoid()
    pts = np.random.default_rng(1).uniform(-32, 32, (3000, 3))
    eta, grad = Tracer(f, BOX, TraceSettings(precision=precision, lanes=lanes)).eval_field(pts)
    ref, gref = f.eval(pts)
    assert np.abs(eta - ref).max() < tol
    assert np.abs(grad - gref).max() < tol * 10
    assert ref.min() == 1.0 and ref.max() == pytest.approx(1.4)  # air outside, n inside


def test_surface_is_as_sharp_as_the_width_on_a_coarse_grid():
    """A 32^3 grid of distances (1.9 mm cells) holds a glass sphere whose index crosses the
    midpoint within 0.08 mm of the true radius (the spline of the samples smooths the distance:
    a sphere shrinks by about h^2 / 3R = 0.06 mm), and ramps over the 1 mm width."""
    f = LevelSetField.from_sdf(lambda p: np.linalg.norm(p, axis=1) - 20.0, BOX, 32, 1.5, 1.0)
    rng = np.random.default_rng(2)
    u = rng.normal(size=(50, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    r = np.linspace(18.0, 22.0, 4001)
    for d in u:
        eta = f.eval(r[:, None] * d)[0]
        assert abs(r[np.argmax(eta < 1.25)] - 20.0) < 0.08
        ramp = r[(eta > 1.01) & (eta < 1.49)]
        assert 0.6 < ramp.max() - ramp.min() < 1.1


def fd_errors(step, checkpoint_every=8, seed=3):
    f = ellipsoid()
    rng = np.random.default_rng(seed)
    n = 300
    o = np.column_stack([rng.uniform(-18, 18, (n, 2)), np.full(n, -150.0)])
    d = np.column_stack([rng.normal(0, 0.03, (n, 2)), np.ones(n)])
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    env = smooth_env()
    target = env.lookup(d + rng.normal(0, 0.02, d.shape)).astype(np.float64)
    eng = GradientEngine(
        f,
        BOX,
        TraceSettings(step=step, precision="float64", lanes=4, checkpoint_every=checkpoint_every),
    )
    res = eng.loss_and_grad(o, d, target, env)
    p0 = f.data().copy()
    dirs = [np.append(rng.normal(size=f.phi.size), 0.0) for _ in range(2)]
    dirs.append(np.eye(len(p0))[-1])  # the index n, a shared parameter
    return directional_errors(eng, o, d, env, target, res.grad, p0, dirs, 1e-6), res


def test_adjoint_matches_finite_differences_and_converges_with_step():
    """Distances and the index, width 4 mm: measured max 2.3e-2 at step 1 (w/4), 1.9e-5 at
    step 0.25 (w/16), with checkpoints every 8 steps."""
    coarse, _ = fd_errors(1.0)
    fine, res = fd_errors(0.25)
    assert fine.max() < 2e-4, fine
    assert fine.max() < coarse.max() / 20, (coarse, fine)
    assert res.grad[-1] != 0 and np.abs(res.grad[:-1]).max() > 0
    assert res.drift.max() < 1e-4


def test_adjoint_is_the_same_for_every_lane_width():
    f = ellipsoid(noise=0.1)
    rng = np.random.default_rng(4)
    n = 200
    o = np.column_stack([rng.uniform(-18, 18, (n, 2)), np.full(n, -150.0)])
    d = np.tile([0.0, 0.0, 1.0], (n, 1))
    env = smooth_env()
    target = env.lookup(d + rng.normal(0, 0.02, d.shape)).astype(np.float64)
    grads = {
        (p, lanes): GradientEngine(f, BOX, TraceSettings(step=0.5, precision=p, lanes=lanes))
        .loss_and_grad(o, d, target, env)
        .grad
        for p, lanes in [("float64", 1), ("float64", 8), ("float32", 16)]
    }
    ref = grads["float64", 1]
    assert np.abs(grads["float64", 8] - ref).max() < 1e-10 * np.abs(ref).max()
    assert abs(grads["float32", 16][-1] - ref[-1]) < 1e-3 * abs(ref[-1])


def test_eikonal_regulariser_gradient_and_zero_on_a_distance():
    f = ellipsoid(res=10, noise=0.5)
    p = f.data()
    val, g = f.regularizer(p)
    rng = np.random.default_rng(5)
    u = np.append(rng.normal(size=f.phi.size), 0.0)
    eps = 1e-6
    fd = (f.regularizer(p + eps * u)[0] - f.regularizer(p - eps * u)[0]) / (2 * eps)
    assert g @ u == pytest.approx(fd, rel=1e-6)
    plane = LevelSetField.from_sdf(lambda q: q @ np.array([0.6, 0.0, 0.8]) - 1.0, BOX, 10, 1.5)
    assert plane.regularizer(plane.data())[0] < 1e-20 < val


def test_files_round_trip_and_name_the_file_on_error(tmp_path):
    f = ellipsoid()
    f.save(tmp_path / "ls.npz")
    g = load_field_file(tmp_path / "ls.npz")
    assert isinstance(g, LevelSetField) and g.box == f.box and g.width == f.width
    assert np.array_equal(g.data(), f.data())
    bad = tmp_path / "bad.npz"
    np.savez(bad, kind="levelset", phi=np.zeros((5, 5, 5)))
    with pytest.raises(ClrefractError, match="bad.npz.*missing"):
        load_field_file(bad)
    g = LevelSetField(np.zeros((5, 5, 5)), BOX, eta=1.5, eta_max=1.6)
    p = np.append(np.zeros(125), 2.0)
    g.set_data(p)  # the optimiser's copy is projected onto [1, eta_max] with the field
    assert p[-1] == g.eta == 1.6
    p.flags.writeable = False
    g.set_data(p)
    p = np.append(np.zeros(125), 0.5)
    p.flags.writeable = False
    with pytest.raises(ClrefractError, match="index must lie"):
        g.set_data(p)
    with pytest.raises(ClrefractError, match="non-finite"):
        g.set_data(np.append(np.full(125, np.nan), 1.5))


def _search_checks(run, log, calls, total):
    """What a level set's start search (in `run`, whose progress went to `log`, its forward
    losses counted in `calls`) must have done, whatever its size: every candidate traced once,
    each shape smoothed up to the first smoothing that scores no better, the progress bar
    full; its init.json."""
    from clrefract.start_losses import NAME, count

    assert len(calls) == count(run) and len(calls) <= total
    smoothings = {}  # shape -> the best loss of each smoothing searched, in order
    for line in (run / NAME).read_text().splitlines()[1:]:
        row = json.loads(line)
        name, sigma = row["key"].split("|")[:2]
        coarse = row["key"].endswith("|coarse")  # a quarter of the rays: another scale
        if name not in ("empty",) and not name.startswith("shell") and not coarse:
            best = smoothings.setdefault(name, {})
            best[sigma] = min(best.get(sigma, np.inf), row["loss"])
    assert set(smoothings) == {"visual", "tightened 110 mm^2", "tightened 330 mm^2"}
    for name, best in smoothings.items():
        losses = list(best.values())
        assert all(b < a for a, b in zip(losses[:-2], losses[1:-1])), best
        assert len(losses) == (6 if name == "visual" else 3) or losses[-1] >= losses[-2], best
    # tqdm's bar, redrawn after carriage returns: "start: 100%|...| 518/518 [..., best=...]"
    bars = [x for x in re.split(r"[\r\n]", log.getvalue()) if x.startswith("start:") and "|" in x]
    assert bars and f" {total}/{total} " in bars[-1] and "best=" in bars[-1]
    return json.loads((run / "init.json").read_text())


def test_a_small_fit_starts_from_the_smoothed_hull(sphere_12x24, tmp_path, monkeypatch):
    """The benchmark below on the 24 x 24 sphere, a 16^3 level set with a 2 mm interface:
    the same search (the hull's smoothings, two tightened hulls', three shells), counted and
    ordered alike. Its coarse pixels bound what it finds: measured index 1.36, a loss a
    fifth of empty space's, a box of 69 mm, a surface 1.7 mm off after one step."""
    import io

    from clrefract.fit import load_config, prepare_fit
    from clrefract.fit.objective import Objective
    from clrefract.fit.starts import search_losses

    cfg = load_config(
        None, dict(field="levelset", res=16, width=2.0, iterations=1, batch=256, test_views=1)
    )
    calls = []
    forward = Objective.loss
    monkeypatch.setattr(
        Objective, "loss", lambda self, tracer, idx: calls.append(1) or forward(self, tracer, idx)
    )
    log = io.StringIO()
    fit = prepare_fit(sphere_12x24, tmp_path / "run", cfg, stream=log)
    monkeypatch.undo()
    total = 1 + search_losses(8, [6, 3, 3], 3)
    info = _search_checks(tmp_path / "run", log, calls, total)
    assert abs(info["eta"] - 1.5) < 0.2, info
    assert info["loss"] < info["loss_empty"] / 3, info
    assert np.all(fit.box.size < 80) and np.all(fit.box.size > 40)  # not the scene's 100 mm
    result = fit.run()
    assert result["chamfer_mm"] < 3.0, result
    run_box = json.loads((tmp_path / "run" / "run.json").read_text())["box"]
    assert run_box == fit.box.to_dict()
    assert isinstance(load_field_file(tmp_path / "run" / "field.npz"), LevelSetField)


@pytest.mark.benchmark  # about 100 to 200 s; test_a_small_fit_starts_from_the_smoothed_hull
def test_fit_starts_from_the_smoothed_hull_near_the_truth(sphere_25x48, tmp_path, monkeypatch):
    """A glass sphere at 48 x 48 pixels: the start alone (line searches on the index, the
    offset and the smoothing of the hull) finds the index within 0.06 and beats empty space
    by a large factor, in the box around the object. Its progress bar counts every loss the
    search may evaluate; it smooths each shape up to the first smoothing that scores no
    better than the one before."""
    import io

    from clrefract.fit import load_config, prepare_fit
    from clrefract.fit.objective import Objective
    from clrefract.fit.starts import search_losses

    data = sphere_25x48
    cfg = load_config(None, dict(field="levelset", res=32, iterations=2, batch=2048))
    calls = []
    forward = Objective.loss
    monkeypatch.setattr(
        Objective, "loss", lambda self, tracer, idx: calls.append(1) or forward(self, tracer, idx)
    )
    log = io.StringIO()
    fit = prepare_fit(data, tmp_path / "run", cfg, stream=log)
    monkeypatch.undo()
    # the hull's 6 smoothings, two flows' 3 each, three shells' coarse indices and the best's
    total = 1 + search_losses(8, [6, 3, 3], 3)
    assert total == 1 + 81 + 5 * 25 + 2 * (81 + 2 * 25) + 3 * 8 + 25
    # every candidate is traced once (the line searches revisit a few)
    info = _search_checks(tmp_path / "run", log, calls, total)
    assert abs(info["eta"] - 1.5) < 0.06, info  # measured 1.458 at 48 pixels
    assert info["loss"] < info["loss_empty"] / 3, info
    assert np.all(fit.box.size < 70) and np.all(fit.box.size > 40)  # the object's box
    result = fit.run()
    assert result["chamfer_mm"] < 1.0, result
    run_box = json.loads((tmp_path / "run" / "run.json").read_text())["box"]
    assert run_box == fit.box.to_dict()
    assert isinstance(load_field_file(tmp_path / "run" / "field.npz"), LevelSetField)


def test_high_index_glass_is_traced_with_a_step_fine_enough_to_find_its_index(tmp_path):
    """Glass of index 1.9 bends rays 1.8 times as hard across the interface as 1.5: at the
    default quarter of the width the true cylinder's loss is lowest at index 1.8 (measured
    0.0169 against 0.0183 at 1.9, 48 x 48 views); at the step scaled to the contrast (0.14
    mm), at 1.9 (0.0138 against 0.0153). A fresh level-set run records that step."""
    from clrefract.fit import Fit, Tag, guide_config, interface_step_scale, load_config, prepare_fit
    from clrefract.report import scene_truth
    from clrefract.synth import MakeOptions, make_dataset

    data = tmp_path / "cylinder"
    opt = MakeOptions(views=40, res=48, env_width=512, volume_res=32, eta=1.9)
    make_dataset("cylinder", data, opt)
    cfg = load_config(None, dict(field="levelset", res=48, width=1.0, iterations=1))
    fit = Fit(data, tmp_path / "run", cfg)
    fit.box = fit.hulls.object_box()
    fit.size_from_images()
    truth = scene_truth(fit.ds)
    phi = LevelSetField.from_sdf(lambda p: truth.sdf(p)[0], fit.box, 48, 1.9, 1.0).data()
    idx = fit.rays.mask_batch(Tag.START)

    def losses(step):
        fit.bind(fit.make_field(48), step=step)
        out = []
        for eta in (1.8, 1.9):
            fit.params[:] = phi
            fit.params[-1] = eta
            fit.bound.set_params(fit.params, fit.it)
            out.append(fit.loss(idx))
        return out

    coarse, scaled = losses(0.25), losses(0.25 * interface_step_scale(1.9))
    assert coarse[0] < coarse[1], coarse
    assert scaled[1] < 0.95 * scaled[0], scaled
    assert interface_step_scale(1.5) == 1.0 and interface_step_scale(1.33) == 1.0
    small = tmp_path / "small"
    make_dataset(
        "cylinder", small, MakeOptions(views=6, res=16, env_width=128, volume_res=16, eta=1.9)
    )
    run = dict(field="levelset", res=16, iterations=1, batch=256, tighten_hull=False)
    fit = prepare_fit(small, tmp_path / "start", load_config(None, run))
    # killed before its first step (no Ctrl-C to save it), the run resumes from its start
    again = prepare_fit(small, tmp_path / "start", load_config(None, run), resume=True)
    assert again.it == 0 and np.array_equal(again.params, fit.params)
    saved = load_config(tmp_path / "start" / "config.toml", {})
    assert saved.step == pytest.approx(0.25 * 0.5 / 0.9)
    # a hash grid's level-set guide (its start, its line search, a resume) steps alike
    # (at the hash grid's own default interface of 0.5 mm)
    hashgrid = load_config(None, dict(field="hashgrid"))
    assert guide_config(hashgrid, 1.9).step == pytest.approx(0.5 / 4 * 0.5 / 0.9)
