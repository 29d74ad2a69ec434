"""The adjoint backward pass against central finite differences of the discretised forward
renderer (float64), its convergence with the step, memory, and queue independence."""

import numpy as np
import pytest

from clrefract.fields.base import Box
from clrefract.fields.voxel import VoxelGrid
from clrefract.gradcheck import directional_errors, lens_scene, smooth_env
from clrefract.gradient import GradientEngine
from clrefract.runtime import Runtime
from clrefract.tracer import TraceSettings

BOX = Box(margin=4.0)


def fd_errors(interp, step, n_dirs=3, seed=1, checkpoint_every=0, eps=1e-6, z_nodes=None):
    """Relative errors of the adjoint gradient along random directions.
    eps: 1e-6 lets some exit directions cross a texel edge of the bilinear environment (a
    kink in the loss), a floor of ~5e-5 under the error; 1e-7 goes below it.
    z_nodes: keep only these z-planes of the scene's grid."""
    vals, o, d, env, target = lens_scene()
    if z_nodes is not None:
        vals = np.ascontiguousarray(vals[:, :, z_nodes])
    field = VoxelGrid(vals, BOX, interp)
    eng = GradientEngine(
        field,
        BOX,
        TraceSettings(step=step, precision="float64", lanes=4, checkpoint_every=checkpoint_every),
    )
    res = eng.loss_and_grad(o, d, target, env)
    p0 = vals.ravel().copy()
    rng = np.random.default_rng(seed)
    dirs = [rng.normal(size=p0.shape) for _ in range(n_dirs)]
    return directional_errors(eng, o, d, env, target, res.grad, p0, dirs, eps), res


def test_voxel_adjoint_matches_finite_differences_and_converges_with_step():
    coarse, r_coarse = fd_errors("smoothstep", 2.0)
    fine, r_fine = fd_errors("smoothstep", 0.5)
    # continuous adjoint = discrete gradient up to discretisation error, shrinking with step
    # every direction, not a median: one bad direction must fail (measured max 8.5e-5 at
    # step 0.5, 6.5e-4 at step 2)
    assert np.max(fine) < 2e-4, fine
    assert np.max(fine) < np.max(coarse) / 4, (coarse, fine)
    # backward re-integration drift (RK4 is not time-reversible) also shrinks with the step
    assert r_fine.drift.max() < r_coarse.drift.max() / 10
    assert r_fine.drift.max() < 1e-3


def test_checkpoints_bound_the_drift_and_keep_the_gradient():
    plain, r_plain = fd_errors("smoothstep", 2.0)
    ckpt, r_ckpt = fd_errors("smoothstep", 2.0, checkpoint_every=4)
    assert r_ckpt.drift.max() < r_plain.drift.max() / 5, (r_plain.drift.max(), r_ckpt.drift.max())
    assert np.max(ckpt) < 2 * np.max(plain) + 1e-5, (plain, ckpt)  # measured 8.6e-4, 6.5e-4


def test_checkpoints_tame_the_drift_through_a_sharp_interface():
    """A smoothed glass sphere: constant-memory re-integration wanders off, the checkpointed
    one stays within the last segment's drift."""
    from clrefract.fields.analytic import Sphere

    vals = VoxelGrid.from_field(Sphere(radius=20, eta=1.5, width=3.0), BOX, 48).values
    rng = np.random.default_rng(3)
    n = 400
    o = np.column_stack([rng.uniform(-25, 25, (n, 2)), np.full(n, -150.0)])
    d = np.tile([0.0, 0.0, 1.0], (n, 1))
    env = smooth_env()
    target = env.lookup(d).astype(np.float64)
    p99 = []
    for every in (0, 16, 4):
        eng = GradientEngine(
            VoxelGrid(vals, BOX),
            BOX,
            TraceSettings(step=1.0, precision="float64", checkpoint_every=every),
        )
        p99.append(np.percentile(eng.loss_and_grad(o, d, target, env).drift, 99))
    # drift measured where the ray restarts from a checkpoint: it shrinks with the segment
    assert p99[0] > 10.0 and p99[1] < p99[0] / 10 and p99[2] < p99[1] / 5, p99
    assert p99[2] < 0.1, p99


def test_trilinear_grid_misses_the_face_hessian():
    """With C0 trilinear weights grad eta jumps at cell faces; the pointwise adjoint misses
    those Dirac masses, so its gradient stays wrong however small the step (why fitting
    uses smoothstep weights)."""
    errs, _ = fd_errors("trilinear", 0.5, n_dirs=5)
    smooth, _ = fd_errors("smoothstep", 0.5, n_dirs=5)
    assert errs.max() > 0.05 and errs.max() > 100 * smooth.max(), (errs, smooth)


def test_gradient_does_not_depend_on_the_number_of_queues():
    vals, o, d, env, target = lens_scene(n_rays=500)
    grads = []
    for q in (1, 3):
        rt = Runtime(queues=q)
        eng = GradientEngine(
            VoxelGrid(vals, BOX),
            BOX,
            TraceSettings(step=1.0, precision="float64", queues=q),
            runtime=rt,
        )
        r = eng.loss_and_grad(o, d, target, env)
        grads.append(r.grad)
    assert np.abs(grads[0] - grads[1]).max() < 1e-12 * np.abs(grads[0]).max()


@pytest.mark.parametrize("precision", ["float32", "float64"])
def test_device_buffers_do_not_grow_with_the_step_count(precision, monkeypatch):
    """The backward pass allocates the same buffers whatever the number of steps."""
    import pyopencl as cl

    sizes = []
    real = cl.Buffer

    def spy(ctx, flags, size=0, hostbuf=None):
        sizes.append(hostbuf.nbytes if hostbuf is not None else size)
        return (
            real(ctx, flags, size, hostbuf)
            if hostbuf is None
            else real(ctx, flags, hostbuf=hostbuf)
        )

    vals, o, d, env, target = lens_scene(n_rays=200)
    totals = []
    for step in (2.0, 0.25):
        eng = GradientEngine(
            VoxelGrid(vals, BOX), BOX, TraceSettings(step=step, precision=precision)
        )
        monkeypatch.setattr(cl, "Buffer", spy)
        sizes.clear()
        r = eng.loss_and_grad(o, d, target, env)
        monkeypatch.setattr(cl, "Buffer", real)
        totals.append((sum(sizes), r.steps))
    assert totals[1][1] > 6 * totals[0][1]  # eight times the steps ...
    assert totals[0][0] == totals[1][0]  # ... and the same bytes


# --- tricubic B-spline voxel grid ----------------------------------------------------------


def test_bspline_voxel_adjoint_matches_finite_differences_and_converges_with_step():
    """C2 weights: Hess(eta) is continuous, so the continuous adjoint converges to the discrete
    gradient fast (measured median 1.3e-4 at step 2, 3e-7 at step 0.5)."""
    coarse, r_coarse = fd_errors("bspline", 2.0, eps=1e-7)
    fine, r_fine = fd_errors("bspline", 0.5, eps=1e-7)
    assert np.max(fine) < 1e-5, fine  # measured max 5.3e-7
    assert np.max(fine) < np.max(coarse) / 20, (coarse, fine)  # coarse max 2.6e-4
    assert r_fine.drift.max() < r_coarse.drift.max() / 10
    # the original harness (perturbation 1e-6) agrees within its floor
    errs, _ = fd_errors("bspline", 1.0)
    assert np.max(errs) < 2e-4, errs  # measured max 2.2e-5


def test_bspline_adjoint_is_the_same_for_every_lane_width_and_precision():
    """64-tap private accumulators with LANES = 1, 4, 8 (float64) and 1, 16 (float32, the CPU
    default): the same gradient up to rounding; the clamped border nodes get splats too."""
    vals, o, d, env, target = lens_scene(n_rays=500)
    grads = {}
    for precision, lanes in [("float64", 4), ("float64", 1), ("float64", 8), ("float32", 16)]:
        eng = GradientEngine(
            VoxelGrid(vals, BOX, "bspline"),
            BOX,
            TraceSettings(step=1.0, precision=precision, lanes=lanes),
        )
        grads[precision, lanes] = eng.loss_and_grad(o, d, target, env).grad
    ref = grads["float64", 4]
    scale = np.abs(ref).max()
    assert np.abs(grads["float64", 1] - ref).max() < 1e-12 * scale
    assert np.abs(grads["float64", 8] - ref).max() < 1e-12 * scale
    assert np.abs(grads["float32", 16] - ref).max() < 1e-4 * scale  # measured 2e-6
    g = ref.reshape(vals.shape)
    assert np.abs(g[:, :, 0]).max() > 0  # rays enter through z = -50: border nodes splatted


def test_bspline_adjoint_with_3_nodes_along_z():
    """Under 4 nodes along z the kernels gather and splat clamped taps one by one."""
    errs, _ = fd_errors("bspline", 0.5, eps=1e-7, z_nodes=[0, 5, 11])
    assert np.max(errs) < 3e-5, errs  # measured max 5.3e-6


def test_a_terminal_loss_of_exit_directions_has_the_finite_difference_gradient():
    """loss_and_grad's terminal hook: the squared distance of exit directions from fixed
    ones (no environment texels, so no kinks) against central differences."""
    from clrefract.loss import direction_loss

    vals, o, d, env, target = lens_scene()
    field = VoxelGrid(vals, BOX, "smoothstep")
    eng = GradientEngine(field, BOX, TraceSettings(step=0.5, precision="float64", lanes=4))
    aim = d + np.random.default_rng(0).normal(scale=0.05, size=d.shape)
    aim /= np.linalg.norm(aim, axis=1, keepdims=True)

    def terminal(status, velocity):
        return direction_loss(velocity, aim, (status == 0).astype(float))

    res = eng.loss_and_grad(o, d, target, env, terminal=terminal)
    assert res.loss > 0 and not np.allclose(res.grad, 0)
    p0 = vals.ravel().copy()

    def loss(p):
        eng.set_params(p)
        tr = eng.tracer.trace(o, d)
        return terminal(tr.status, tr.last_velocity)[0]

    eps, rng = 1e-6, np.random.default_rng(1)
    for _ in range(3):
        u = rng.normal(size=p0.shape)
        fd = (loss(p0 + eps * u) - loss(p0 - eps * u)) / (2 * eps)
        # the continuous adjoint's discretisation error: measured 2e-5 to 2.5e-4 at step 0.5
        assert abs(fd - res.grad @ u) < 1e-3 * abs(fd), (fd, res.grad @ u)


def test_the_queues_trace_side_by_side(monkeypatch):
    """With two queues, the second queue's rays are launched while the first queue's are
    still in flight: pyopencl waits for a copy into host memory whose event is dropped, and
    dropping them ran the queues one after another. The first launch's copies (a second of
    work: 4,000 rays at 0.02 mm steps) are found unfinished when the second is enqueued."""
    import pyopencl as cl

    from clrefract.tracer import Tracer

    vals, o, d, env, target = lens_scene(n_rays=4000)
    rt = Runtime(queues=2)
    eng = GradientEngine(
        VoxelGrid(vals, BOX), BOX, TraceSettings(step=0.02, precision="float64", queues=2),
        runtime=rt,
    )  # fmt: skip
    eng.forward(o[:64], d[:64])  # built and warm
    real, launches, seen = Tracer.enqueue, [], []

    def spy(self, *args, **kw):
        seen.append([e.command_execution_status for ln in launches for e in ln.events])
        launches.append(real(self, *args, **kw))
        return launches[-1]

    monkeypatch.setattr(Tracer, "enqueue", spy)
    eng.forward(o, d)
    assert len(seen) == 2 and seen[1], seen
    assert any(s != cl.command_execution_status.COMPLETE for s in seen[1]), seen
    assert all(not ln.events for ln in launches)  # finished, and let go
