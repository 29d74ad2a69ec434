"""The exact-gradient mode (adjoint = "discrete"): each RKN4 step reversed from checkpoints.

Tolerance: in float64 the discrete adjoint is the derivative of the forward renderer itself,
so it differs from central differences only by their own error: rounding of the loss over
2 eps (~1e-16 / 1e-7 relative) and eps^2 truncation (~1e-14); measured 6e-11 to 9e-10.
1e-6 leaves three orders of margin and sits far below the continuous adjoint's
discretisation error at step 2 (1e-4 to 5e-4, measured)."""

import numpy as np
import pytest
from test_adjoint import BOX

from clrefract.errors import ClrefractError
from clrefract.fields.voxel import VoxelGrid
from clrefract.gradcheck import directional_errors, lens_scene, smooth_env
from clrefract.gradient import GradientEngine, backward_state_bytes, discrete_segment
from clrefract.runtime import default_runtime
from clrefract.tracer import Tracer, TraceSettings

EXACT = 1e-6


def fd_check(mode, interp="smoothstep", step=2.0, every=0, lanes=4, n_rays=100):
    vals, o, d, env, target = lens_scene(n_rays=n_rays)
    eng = GradientEngine(
        VoxelGrid(vals, BOX, interp),
        BOX,
        TraceSettings(
            step=step, precision="float64", lanes=lanes, adjoint=mode, checkpoint_every=every
        ),
    )
    res = eng.loss_and_grad(o, d, target, env)
    p0 = vals.ravel().copy()
    rng = np.random.default_rng(1)
    dirs = [rng.normal(size=p0.shape) for _ in range(3)]
    # eps 1e-7: below the environment's texel kinks (see test_adjoint.fd_errors)
    return directional_errors(eng, o, d, env, target, res.grad, p0, dirs, 1e-7), res


@pytest.mark.parametrize("interp", ["smoothstep", "bspline"])
def test_discrete_adjoint_matches_finite_differences_to_rounding(interp):
    exact, r_exact = fd_check("discrete", interp)
    cont, _ = fd_check("continuous", interp)
    assert exact.max() < EXACT, exact
    # the continuous adjoint's O(step^4) error at step 2 is far above that
    assert cont.min() > 1e-5, cont
    assert exact.max() < cont.min() / 1000, (exact, cont)
    # the replay from checkpoints retraces the forward pass to rounding: no drift
    assert r_exact.drift.max() < 1e-10, r_exact.drift.max()


def test_segment_length_and_lanes_do_not_change_the_gradient():
    """K only moves the checkpoints (a segment of 1 step, 5, the default sqrt); lanes the
    vector width: the same gradient up to rounding."""
    _, ref = fd_check("discrete")
    for every, lanes in [(1, 4), (5, 1), (0, 1)]:
        _, r = fd_check("discrete", every=every, lanes=lanes)
        scale = np.abs(ref.grad).max()
        assert np.abs(r.grad - ref.grad).max() < 1e-11 * scale, (every, lanes)


def test_trilinear_gradient_is_exact_between_face_crossings():
    """C0 trilinear weights: grad eta jumps at cell faces, so the discrete renderer jumps
    where a stage point crosses one; with a perturbation too small to cross any (eps 1e-8
    here) the discrete adjoint is its exact derivative."""
    vals, o, d, env, target = lens_scene(n_rays=100)
    eng = GradientEngine(
        VoxelGrid(vals, BOX, "trilinear"),
        BOX,
        TraceSettings(step=0.5, precision="float64", lanes=4, adjoint="discrete"),
    )
    g = eng.loss_and_grad(o, d, target, env).grad
    p0 = vals.ravel().copy()
    rng = np.random.default_rng(1)
    dirs = [rng.normal(size=p0.shape) for _ in range(3)]
    errs = directional_errors(eng, o, d, env, target, g, p0, dirs, 1e-8)
    assert errs.max() < 1e-6, errs  # measured 1.3e-8 (eps 1e-8: FD rounding 1e-8)


def test_checkpoint_memory(monkeypatch):
    """Device bytes of the backward pass's state: max_steps // K checkpoints of 6 reals and
    K scratch steps of 9 reals per ray, as backward_state_bytes says; O(n / K + K)."""
    import pyopencl as cl

    assert backward_state_bytes(1000, 32, "discrete", 8) == 8 * (6 * 31 + 9 * 32)
    assert backward_state_bytes(1000, 32, "continuous", 8) == 8 * 6 * 31
    assert backward_state_bytes(1000, 0, "continuous", 8) == 0
    assert discrete_segment(1000) == 32 and discrete_segment(1024) == 32
    assert discrete_segment(1025) == 33 and discrete_segment(1) == 1

    vals, o, d, env, target = lens_scene(n_rays=64)
    sizes = []
    real = cl.Buffer

    def spy(ctx, flags, size=0, hostbuf=None):
        sizes.append(hostbuf.nbytes if hostbuf is not None else size)
        if hostbuf is None:
            return real(ctx, flags, size)
        return real(ctx, flags, hostbuf=hostbuf)

    totals = {}
    for mode in ("continuous", "discrete"):
        eng = GradientEngine(
            VoxelGrid(vals, BOX),
            BOX,
            TraceSettings(
                step=1.0,
                precision="float64",
                lanes=4,
                adjoint=mode,
                checkpoint_every=0 if mode == "continuous" else 10,
            ),
        )
        monkeypatch.setattr(cl, "Buffer", spy)
        sizes.clear()
        eng.loss_and_grad(o, d, target, env)
        monkeypatch.setattr(cl, "Buffer", real)
        totals[mode] = sum(sizes)
        per_ray = eng.state_bytes_per_ray()
    assert per_ray == 8 * (6 * (eng.tracer.max_steps // 10) + 9 * 10)
    # the same buffers but for the checkpoints and the scratch (64 rays: no padding)
    assert totals["discrete"] - totals["continuous"] == 64 * per_ray


def test_bad_adjoint_options_are_refused():
    vals = lens_scene(n_rays=1)[0]
    with pytest.raises(ClrefractError, match="adjoint must be one of"):
        GradientEngine(VoxelGrid(vals, BOX), BOX, TraceSettings(adjoint="exact"))
    with pytest.raises(ClrefractError, match="reverses rkn4 steps"):
        Tracer(VoxelGrid(vals, BOX), BOX, TraceSettings(integrator="rk4", adjoint="discrete"))


def test_fit_config_takes_the_adjoint_mode():
    from clrefract.fit import load_config

    assert load_config(None, {}).adjoint == "continuous"
    assert load_config(None, {"adjoint": "discrete"}).adjoint == "discrete"
    with pytest.raises(ClrefractError, match="adjoint must be one of"):
        load_config(None, {"adjoint": "exact"})


def test_hashgrid_discrete_adjoint_matches_finite_differences():
    """Hash grid + MLP (the shared MLP weights summed per work-item): table and MLP
    directions. Measured 1.4e-9 and 1e-10 at eps 1e-6 (the continuous adjoint: 1e-2 at this
    step); the central difference's own error grows as 1/eps below (4e-7 at 1e-8) and as
    eps above (8e-5 at 1e-5)."""
    from test_adjoint_hashgrid import SMALL, hg_scene, lively

    from clrefract.fields.hashgrid import HashGridConfig

    field = lively(HashGridConfig(**SMALL))
    o, d, env, target = hg_scene(n_rays=100)
    lanes = field.lanes_on(default_runtime(), 4)
    eng = GradientEngine(
        field, BOX, TraceSettings(step=2.0, precision="float64", lanes=lanes, adjoint="discrete")
    )
    res = eng.loss_and_grad(o, d, target, env)
    p0 = field.data().copy()
    rng = np.random.default_rng(1)
    for sl in (field.table_slice, field.mlp_slice):
        u = np.zeros_like(p0)
        u[sl] = rng.normal(size=sl.stop - sl.start)
        errs = directional_errors(eng, o, d, env, target, res.grad, p0, [u], 1e-6)
        assert errs.max() < EXACT, (sl, errs)
    assert res.drift.max() < 1e-10


def test_growth_cap_truncates_the_discrete_adjoint():
    """growth_max stops a ray's reversal once |vbar| grew past it, as in the continuous pass:
    a cap of 1 keeps only the steps before any growth, so the gradient changes; growth
    reports max |vbar| / |vbar(T)| >= 1."""
    vals, o, d, env, target = lens_scene(n_rays=100)
    out = {}
    for cap in (0.0, 1.0):
        eng = GradientEngine(
            VoxelGrid(vals, BOX),
            BOX,
            TraceSettings(
                step=2.0, precision="float64", lanes=4, adjoint="discrete", growth_max=cap
            ),
        )
        out[cap] = eng.loss_and_grad(o, d, target, env)
    full, cut = out[0.0], out[1.0]
    # measured: up to 16.6 uncapped, 1.06 with the cap (the step that crossed it counts)
    assert full.growth.min() >= 1.0 and full.growth.max() > 5.0
    assert cut.growth.max() < 1.2
    assert np.abs(cut.grad - full.grad).max() > 1e-3 * np.abs(full.grad).max()
    assert np.abs(cut.grad).max() < np.abs(full.grad).max()


def test_tiny_fit_with_the_discrete_adjoint(tmp_path):
    """`clrefract fit --adjoint discrete` on a graded-index blob: the loss falls, and the run
    records the mode (a resume keeps it)."""
    import json

    from clrefract.cli import main
    from clrefract.fields.analytic import Blobs
    from clrefract.synth import MakeOptions, make_dataset

    blob = Blobs(centers=[[0, 0, 0]], amplitudes=[0.05], sigmas=[12])
    ds = tmp_path / "blob"
    make_dataset("blob", ds, MakeOptions(views=6, res=24, env_width=256, volume_res=16), obj=blob)
    run = tmp_path / "run"
    args = ["fit", str(ds), "--out", str(run), "--adjoint", "discrete", "--field", "voxel"]
    args += ["--init", "empty", "--res", "8", "--step", "2", "--iterations", "12"]
    args += ["--lr", "0.003", "--test-views", "1", "--interp", "smoothstep"]
    assert main(args) == 0
    lines = (run / "metrics.jsonl").read_text().splitlines()
    losses = [json.loads(ln)["loss"] for ln in lines]
    assert np.mean(losses[-3:]) < 0.7 * np.mean(losses[:2]), losses
    assert 'adjoint = "discrete"' in (run / "config.toml").read_text()


def test_levelset_discrete_adjoint_matches_finite_differences():
    """A level set (B-spline distances and one shared index n, summed per work-item):
    distance and index directions; measured 4e-10 and 3e-10 at eps 1e-6."""
    from test_levelset import BOX as LBOX
    from test_levelset import ellipsoid

    f = ellipsoid()
    rng = np.random.default_rng(3)
    n = 60
    o = np.column_stack([rng.uniform(-18, 18, (n, 2)), np.full(n, -150.0)])
    d = np.column_stack([rng.normal(0, 0.03, (n, 2)), np.ones(n)])
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    env = smooth_env()
    target = env.lookup(d + rng.normal(0, 0.02, d.shape)).astype(np.float64)
    eng = GradientEngine(
        f, LBOX, TraceSettings(step=1.0, precision="float64", lanes=4, adjoint="discrete")
    )
    res = eng.loss_and_grad(o, d, target, env)
    p0 = f.data().copy()
    dirs = [np.append(rng.normal(size=f.phi.size), 0.0), np.eye(len(p0))[-1]]
    errs = directional_errors(eng, o, d, env, target, res.grad, p0, dirs, 1e-6)
    assert errs.max() < EXACT, errs
    assert res.grad[-1] != 0
