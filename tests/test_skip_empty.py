"""Empty-space skipping (issue 12): rays fly straight through cells where eta is constant;
same exit rays to rounding, far fewer integration steps when the object is small; in fits
the same loss and gradient, with the occupancy rebuilt as the field trains."""

from dataclasses import replace

import numpy as np
import pytest
from scipy.ndimage import binary_dilation

from clrefract.errors import ClrefractError
from clrefract.fields.analytic import Luneburg, Sphere
from clrefract.fields.base import Box
from clrefract.fields.levelset import LevelSetField
from clrefract.fields.voxel import VoxelGrid
from clrefract.fit import Fit, kind_of, load_config
from clrefract.fit.kinds import kind_named
from clrefract.fit.occupancy import TrainingOccupancy
from clrefract.fit.optimizers import AdamSteps
from clrefract.gradcheck import smooth_env
from clrefract.gradient import GradientEngine
from clrefract.occupancy import (
    cell_reduce,
    distance_of,
    live_cells_levelset,
    live_cells_nodes,
    occupied_cells,
)
from clrefract.synth import MakeOptions, make_dataset
from clrefract.tracer import Tracer, TraceSettings


def _rays(n=256, seed=0):
    rng = np.random.default_rng(seed)
    o = np.column_stack([np.full(n, -120.0), rng.uniform(-12, 12, (n, 2))])
    d = np.column_stack([np.ones(n), rng.normal(0, 0.02, (n, 2))])
    return o, d


@pytest.mark.parametrize(
    "field,step",
    [(Sphere(radius=10.0, eta=1.5, width=1.0), 0.125), (Luneburg(radius=10.0), 0.25)],
)
def test_same_rays_with_fewer_steps(field, step):
    o, d = _rays()
    a = Tracer(field, settings=TraceSettings(step=step, precision="float64")).trace(o, d)
    b = Tracer(
        field, settings=TraceSettings(step=step, precision="float64", skip_empty=True)
    ).trace(o, d)
    assert np.array_equal(a.status, b.status)
    assert np.abs(a.direction - b.direction).max() < 1e-9
    assert np.abs(a.position - b.position).max() < 1e-7
    assert b.steps.mean() < a.steps.mean() / 3


def test_a_launch_of_4096_work_items_skips_too():
    """65,536 rays in 16 lanes: PoCL's own work-group of 4,096 work-items put as many
    copies of the skipping gather's arrays on one thread's stack and crashed the process;
    tracer.work_group_size keeps groups at 32."""
    n = 65536
    o = np.column_stack([np.full(n, -120.0), np.random.default_rng(0).uniform(-30, 30, (n, 2))])
    d = np.tile([1.0, 0.0, 0.0], (n, 1))
    f = Sphere(radius=10.0, eta=1.5, width=1.0)
    a = Tracer(f, settings=TraceSettings(step=0.25, lanes=16)).trace(o, d)
    b = Tracer(f, settings=TraceSettings(step=0.25, lanes=16, skip_empty=True)).trace(o, d)
    assert np.array_equal(a.status, b.status)
    assert np.abs(a.direction - b.direction).max() < 1e-4
    assert b.steps.mean() < a.steps.mean() / 4


def test_a_fitted_hash_grid_renders_the_same_with_skipping_in_fewer_steps():
    """Scoring and a hash grid's validation trace through run_tracer: skipping the cells
    where eta is constant, as the device samples them. A ramp grid distilled from a sphere
    (eta exactly 1 in air): in float64 the same exits as without skipping, in under half
    the steps, and the device's samples give the NumPy reference's occupancy."""
    from clrefract.fields.hashgrid import HashGridField
    from clrefract.fit import forward_settings, hashgrid_config
    from clrefract.occupancy import empty_distance
    from clrefract.render import run_tracer

    box = Box((-12.0,) * 3, (12.0,) * 3, 1.0)
    cfg = load_config(None, dict(field="hashgrid", levels=4, log2_table=12, n_max=32,
                                 hidden=8, precision="float64"))  # fmt: skip
    field = HashGridField(hashgrid_config(cfg, 1.5), box, seed=0)
    assert field.config.output == "ramp"
    pts = np.random.default_rng(1).uniform(-12, 12, (100_000, 3))
    r = np.linalg.norm(pts, axis=1)
    field.fit_surface(pts, r - 8.0, pts / r[:, None], 1.5, cfg.width, iterations=150)
    settings = forward_settings(cfg)
    skip = run_tracer(field, box, settings)
    plain = Tracer(field, field.tracing_box(box), replace(settings, skip_empty=False))
    assert skip.skip_empty and not plain.skip_empty
    np.testing.assert_array_equal(skip.occupancy, empty_distance(field, skip.box))
    assert 0.5 < (skip.occupancy > 0).mean() < 0.95  # measured 0.83 of the cells skipped
    o, d = _rays()
    a, b = plain.trace(o, d), skip.trace(o, d)
    assert np.array_equal(a.status, b.status)
    off = np.abs(a.direction - b.direction).max(1)
    # a ray grazing the glass amplifies rounding (measured: one of 256 off by 7e-7)
    assert np.mean(off > 1e-9) < 0.02 and off.max() < 1e-5, np.sort(off)[-5:]
    assert b.steps.mean() < a.steps.mean() / 2, (b.steps.mean(), a.steps.mean())


def test_render_skips_empty_space_on_request(tmp_path):
    """`clrefract render --skip-empty`: the sphere's views as without it (float64), in
    fewer steps, and render.json says which way they were made."""
    import json

    from clrefract.cli import main
    from clrefract.imageio import read_exr_rgb

    runs = {}
    for skip in (False, True):
        out = tmp_path / f"skip{skip}"
        args = ["render", "--views", "2", "--res", "24", "--precision", "float64"]
        assert main([*args, "--out", str(out)] + ["--skip-empty"] * skip) == 0
        meta = json.loads((out / "render.json").read_text())
        assert meta["skip_empty"] is skip
        images = [read_exr_rgb(f) for f in sorted(out.glob("*.exr"))]
        runs[skip] = images, sum(v["steps"] for v in meta["views"])
    (plain, plain_steps), (skipped, skipped_steps) = runs[False], runs[True]
    assert len(plain) == len(skipped) == 2
    for a, b in zip(plain, skipped):
        np.testing.assert_allclose(b, a, rtol=0, atol=1e-6)
    assert skipped_steps < plain_steps / 2, (skipped_steps, plain_steps)


def test_voxel_grid_skipping_matches_but_for_chaotic_rays():
    """A voxel sphere whose band grazing rays orbit chaotically: those may differ by
    rounding amplified; the rest match to 1e-6."""
    vox = VoxelGrid.from_field(Sphere(radius=10.0, eta=1.5, width=2.0), res=33)
    o, d = _rays(128)
    settings = TraceSettings(step=0.5, precision="float64")
    a = Tracer(vox, vox.box, settings).trace(o, d)
    b = Tracer(vox, vox.box, replace(settings, skip_empty=True)).trace(o, d)
    off = np.abs(a.direction - b.direction).max(1) > 1e-6
    assert off.mean() < 0.03, off.mean()
    assert b.steps.mean() < a.steps.mean() / 2


def test_occupancy_covers_a_thin_interface():
    """A band 0.05 mm thick, far thinner than the samples (0.78 mm): every cell that the
    sphere's surface passes through is occupied."""
    f = Sphere(radius=20.0, eta=1.5, width=0.05)
    occ = occupied_cells(f, Box(), res=32, dilate=0)
    rng = np.random.default_rng(0)
    p = rng.normal(size=(2000, 3))
    p = 20.0 * p / np.linalg.norm(p, axis=1, keepdims=True)
    cells = np.floor((p + 50.0) / (100.0 / 32)).astype(int)
    assert occ[cells[:, 0], cells[:, 1], cells[:, 2]].all()


def test_a_cell_is_occupied_where_its_own_samples_differ():
    """Against a loop over the cells of the whole sample lattice: a cell's samples run from
    its lower corner to its upper one, both included. A field of flat steps whose edges
    fall on, beside and between sample planes."""

    class Steps:
        def eval(self, p):
            eta = 1 + 0.1 * (p[:, 0] >= 10) + 0.2 * (np.abs(p[:, 1] - 3) < 7) * (p[:, 2] > -21)
            return eta, None

    box, res, sub = Box((-40, -40, -40), (40, 40, 40), 4.0), 8, 3
    n = res * sub + 1
    axes = np.linspace(-40, 40, n)
    pts = np.stack(np.meshgrid(axes, axes, axes, indexing="ij"), -1).reshape(-1, 3)
    eta = Steps().eval(pts)[0].reshape(n, n, n)
    want = np.zeros((res, res, res), bool)
    for i, j, k in np.ndindex(want.shape):
        c = eta[
            i * sub : i * sub + sub + 1, j * sub : j * sub + sub + 1, k * sub : k * sub + sub + 1
        ]
        want[i, j, k] = c.max() > c.min()
    got = occupied_cells(Steps(), box, res=res, sub=sub, dilate=0)
    assert 0 < want.sum() < want.size / 2
    assert np.array_equal(got, want)


def test_discrete_adjoint_refuses_skipping():
    vox = VoxelGrid(np.ones((8, 8, 8)))
    with pytest.raises(ClrefractError, match="discrete adjoint"):
        Tracer(vox, vox.box, TraceSettings(skip_empty=True, adjoint="discrete"))


# --- while training: the backward pass flies back through the same empty cells ------------
BOX = Box((-40, -40, -40), (40, 40, 40), 4.0)


def _ball_sdf(p):
    return np.linalg.norm(p, axis=1) - 8.0


def _batch(n=256, seed=0):
    """Rays over the whole box face (most miss the ball), targets from jittered directions."""
    rng = np.random.default_rng(seed)
    o = np.column_stack([rng.uniform(-20, 20, (n, 2)), np.full(n, -150.0)])
    d = np.column_stack([rng.normal(0, 0.03, (n, 2)), np.ones(n)])
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    env = smooth_env(512)
    return o, d, env, env.lookup(d + rng.normal(0, 0.02, d.shape)).astype(np.float64)


def _grads(field, live, precision="float64", lanes=None):
    o, d, env, tgt = _batch()
    out = []
    for skip in (False, True):
        eng = GradientEngine(
            field, BOX, TraceSettings(step=0.25, precision=precision, lanes=lanes, skip_empty=skip)
        )
        if skip and live is not None:  # else the engine's own: exact for every parameter
            eng.tracer.set_occupancy(distance_of(live))
        out.append(eng.loss_and_grad(o, d, tgt, env))
    return out


@pytest.mark.parametrize("lanes", [1, None])  # a GPU's one ray per work-item; the CPU's
def test_level_set_gradient_is_the_same_with_skipping(lanes):
    ls = LevelSetField.from_sdf(_ball_sdf, BOX, 16, eta=1.5, width=2.0)
    live = live_cells_levelset(ls, BOX, 32, 0.0)
    assert live.mean() < 0.2  # most of the box is skipped
    a, b = _grads(ls, None, lanes=lanes)  # the engine's default occupancy is that band
    assert abs(a.loss - b.loss) <= 1e-12 * a.loss
    assert np.abs(a.grad - b.grad).max() <= 1e-9 * np.abs(a.grad).max()
    assert b.steps < a.steps / 2


def test_voxel_gradient_is_the_same_on_the_free_nodes():
    """Nodes whose support reaches a skipped cell lose the gradient of the flights there:
    a fit zeroes it anyway (they are not free); the free nodes' gradient is unchanged."""
    vox = VoxelGrid.from_field(
        Sphere(radius=8.0, eta=1.5, width=3.0), box=BOX, res=16, interp="bspline"
    )
    free = binary_dilation(vox.values > 1 + 1e-9, iterations=1)
    live = live_cells_nodes(free, vox, BOX, 32)
    a, b = _grads(vox, live)
    f = free.ravel()
    assert abs(a.loss - b.loss) <= 1e-12 * a.loss
    assert np.abs(a.grad[f] - b.grad[f]).max() <= 1e-9 * np.abs(a.grad[f]).max()
    assert np.abs(a.grad[~f]).max() > 0  # what a fit without skipping would zero too


def test_level_set_occupancy_holds_while_no_node_moves_more_than_the_slack():
    """Any change of the nodes within the slack keeps every cell where eta varies live."""
    ls = LevelSetField.from_sdf(_ball_sdf, BOX, 16, eta=1.5, width=1.0)
    slack = 0.8
    live = live_cells_levelset(ls, BOX, 24, slack, dilate=0)
    rng = np.random.default_rng(1)
    for _ in range(3):
        p = ls.data().copy()
        p[:-1] += rng.uniform(-slack, slack, p.size - 1)
        moved = LevelSetField(p[:-1].reshape(ls.shape), BOX, 1.5, 1.0)
        assert not (occupied_cells(moved, BOX, 24, dilate=0) & ~live).any()
    # a node moved by more than the slack may leave it: the fit then rebuilds at once
    occ = TrainingOccupancy(kind_named("levelset"), 24, every=10, lr_phi=0.001)
    assert occ.due(0, ls)  # never built

    class Taker:  # stands in for a tracer: takes the occupancy a rebuild gives it
        box = BOX

        def set_occupancy(self, distance):
            self.distance = distance

    assert occ.update(0, ls, Taker(), force=True) and occ.rebuilds == 1
    assert not occ.due(5, ls)
    ls.phi[8, 8, 8] += 2.1 * occ.slack
    assert occ.due(5, ls) and occ.due(10, ls)


@pytest.mark.parametrize("n,res", [(7, 5), (6, 16), (9, 9)])
def test_a_cells_bound_is_the_extreme_of_the_nodes_that_reach_it(n, res):
    """cell_reduce against the definition: per cell, the nodes within `reach` spacings of it
    on every axis (cells coarser and finer than the nodes, a box offset from the nodes')."""
    node_box = Box((-10.0, -8.0, -9.0), (10.0, 12.0, 9.0), 1.0)
    box = Box((-11.0, -7.0, -9.5), (9.0, 12.5, 10.0), 1.0)
    nodes = np.random.default_rng(n).normal(size=(n, n, n))
    lo = cell_reduce(nodes, node_box, box, res, 2, np.min)
    hi = cell_reduce(nodes, node_box, box, res, 2, np.max)
    near = []
    for a in range(3):
        x = np.linspace(node_box.lo[a], node_box.hi[a], n)
        e = np.linspace(box.lo[a], box.hi[a], res + 1)
        h = x[1] - x[0]
        # a node just 2 h away (support ends there) is in: a wider bound is still a bound
        ahead = x[None, :] - 2 * h < e[1:, None] + 1e-9 * h
        near.append(ahead & (x[None, :] + 2 * h > e[:-1, None] - 1e-9 * h))
    for c in np.ndindex(res, res, res):
        sel = nodes[np.ix_(near[0][c[0]], near[1][c[1]], near[2][c[2]])]
        if sel.size:  # cells beyond every node's reach take the nearest nodes' (clipped)
            assert lo[c] == sel.min() and hi[c] == sel.max()


def test_hash_grids_skip_only_on_the_level_set_they_follow():
    """A hash grid's own rays cannot skip; from the hull its line search traces a level
    set, and a graded medium's descent a voxel grid, and those rays do."""
    for other in (dict(init="empty", optimizer="adam"), dict(optimizer="adam")):
        with pytest.raises(ClrefractError, match="hash grid"):
            load_config(None, dict(field="hashgrid", skip_empty=True, **other))
    cfg = load_config(None, dict(field="hashgrid", skip_empty=True))
    assert kind_of(cfg).skipping_kind(cfg) == "levelset"
    for graded in (dict(init="empty"), dict(optimizer="descent")):
        cfg = load_config(None, dict(field="hashgrid", skip_empty=True, **graded))
        assert kind_of(cfg).skipping_kind(cfg) == "voxel", graded
    with pytest.raises(ClrefractError, match="continuous"):
        load_config(None, dict(field="levelset", skip_empty=True, adjoint="discrete"))


def test_skipping_is_on_by_default_where_most_of_the_box_is_held_at_1():
    """On by default where the level set a hash grid follows traces the rays, and for a
    voxel grid free near its hull alone; a user's own setting wins, and settings that
    cannot skip are not refused for a default."""
    assert load_config(None, dict(field="hashgrid")).skip_empty is True
    assert load_config(None, dict(field="hashgrid", skip_empty=False)).skip_empty is False
    assert load_config(None, dict(field="voxel")).skip_empty is True
    assert load_config(None, dict(field="voxel", skip_empty=False)).skip_empty is False
    for other in (
        dict(field="hashgrid", init="empty"),
        dict(field="hashgrid", optimizer="adam"),
        dict(field="hashgrid", adjoint="discrete"),
        dict(field="levelset"),
        dict(field="levelset", optimizer="line-search"),
        dict(field="voxel", init="empty"),
        dict(field="voxel", free_cells=-1),
        dict(field="voxel", adjoint="discrete"),
    ):
        assert load_config(None, other).skip_empty is False, other


@pytest.fixture(scope="module")
def sphere_data(tmp_path_factory):
    data = tmp_path_factory.mktemp("sphere")
    make_dataset("sphere", data, MakeOptions(views=4, res=24, env_width=256, volume_res=8))
    return data


def _truth(kind, box):
    if kind == "levelset":
        return LevelSetField.from_sdf(
            lambda p: np.linalg.norm(p, axis=1) - 20.0, box, 16, eta=1.5, width=1.0
        )
    return VoxelGrid.from_field(Sphere(radius=20.0, width=3.0), box=box, res=16, interp="bspline")


@pytest.mark.parametrize("kind", ["levelset", "voxel"])
def test_fit_steps_match_without_skipping(sphere_data, tmp_path, kind):
    """Three Adam steps of a fit from the truth (no start search; a voxel grid frees the
    nodes near the hull): the same losses with and without skipping, fewer steps with it."""
    runs = []
    for skip in (False, True):
        cfg = load_config(
            None,
            dict(field=kind, res=16, batch=1024, precision="float64", skip_empty=skip,
                 occupancy_every=2, init="hull", optimizer="adam", mask_share=0.0,
                 adjoint_growth_max=30.0),
        )  # fmt: skip
        fit = Fit(sphere_data, tmp_path / f"run{skip}", cfg)
        fit.bind(_truth(kind, fit.box))
        fit.optimizer = AdamSteps(fit)
        runs.append([fit.step() for _ in range(3)])
        if skip:
            assert fit.occupancy.rebuilds >= 2  # at the bind, and when due
            assert fit.occupancy.live_fraction < 0.7
    for a, b in zip(*runs):
        assert abs(a["loss"] - b["loss"]) <= 1e-9 * a["loss"]
        assert b["steps_per_ray"] < a["steps_per_ray"] * 0.8


# "best" traces the same start search again (a minute and a half); its validation on the
# level set is that of the line-search tests
@pytest.mark.parametrize("refit", [pytest.param("best", marks=pytest.mark.benchmark), "step"])
def test_a_hash_grid_fit_skips_on_its_level_set_alone(sphere_data, tmp_path, refit):
    """From the hull, the start search and the line search trace the level set the hash
    grid follows: those rays skip empty space, the hash grid's own do not. In float64 the
    search scores every candidate as a run without skipping does (to rounding), and the
    first step starts from the same loss. The validation skips too: the level set's with
    refit = "best", the grid's (on an occupancy sampled from it) with "step"."""
    import io
    import json

    from clrefract.fit import prepare_fit

    runs = []
    for skip in (False, True):
        cfg = load_config(
            None,
            dict(field="hashgrid", res=16, width=1.0, batch=1024, line_batch=1024,
                 precision="float64", skip_empty=skip, iterations=1, levels=4,
                 log2_table=12, hidden=8, distil_iterations=20, refit_iterations=10,
                 tighten_hull=False, shell_starts=False, test_views=1, refit=refit),
        )  # fmt: skip
        run = tmp_path / f"run{skip}"
        fit = prepare_fit(sphere_data, run, cfg, stream=io.StringIO())
        assert fit.optimizer.guide.engine.tracer.skip_empty is skip
        assert fit.engine.tracer.skip_empty is False
        fit.run()
        rows = [json.loads(line) for line in (run / "start_losses.jsonl").open()]
        losses = {r["key"]: r["loss"] for r in rows if "key" in r}
        first = json.loads((run / "metrics.jsonl").read_text().splitlines()[0])
        runs.append((losses, first["loss"], first["val_loss"]))
        # the grid's validation skips too, on an occupancy sampled from the grid
        grid_tracer = fit.optimizer.grid_tracer
        assert (grid_tracer is not None) is (skip and refit == "step")
        if grid_tracer is not None:
            assert (grid_tracer.occupancy > 0).mean() > 0.3
    (plain, plain_step, plain_val), (skipped, skipped_step, skipped_val) = runs
    assert plain.keys() == skipped.keys() and len(plain) > 50
    # measured: 1.3e-15 at the median, 5.5e-9 at most (a ray circling inside the glass
    # amplifies rounding); a cell skipped where the surface is moves a loss by percents
    rel = sorted(abs(skipped[k] - v) / v for k, v in plain.items())
    assert rel[len(rel) // 2] < 1e-12 and rel[-1] < 1e-6, rel[-5:]
    assert abs(skipped_step - plain_step) <= 1e-9 * plain_step
    assert abs(skipped_val - plain_val) <= 1e-9 * plain_val
