import numpy as np
import pytest

from clrefract.adam import Adam, ParamGroup


def test_adam_minimises_a_quadratic_with_group_rates():
    target = np.linspace(-1, 1, 10)
    p = np.zeros(10)
    opt = Adam(10, [ParamGroup("a", 0, 5, 0.05), ParamGroup("b", 5, 10, 0.05)])
    for _ in range(500):
        opt.step(p, 2 * (p - target))
    assert np.abs(p - target).max() < 1e-2


def test_sparse_group_skips_zero_gradients_and_keeps_their_moments():
    p = np.ones(4)
    opt = Adam(4, [ParamGroup("table", 0, 4, 0.1, sparse=True)])
    opt.step(p, np.array([1.0, 0.0, -1.0, 0.0]))
    assert list(opt.t) == [1, 0, 1, 0]
    assert p[1] == 1.0 and p[3] == 1.0
    # first Adam step moves by lr in the sign of the gradient
    assert np.allclose(p[[0, 2]], [0.9, 1.1])


@pytest.mark.parametrize("precision, tol", [("float64", 1e-12), ("float32", 1e-5)])
def test_device_adam_takes_the_host_steps(precision, tol):
    """kernels_cl/adam.cl against Adam.step: a sparse group whose entries' gradients are
    zero on some steps (their moments and step counts wait), a dense one, a group's rate
    scaled per step. The parameters agree to rounding, relative to how far they moved."""
    from clrefract.adam import DeviceAdam
    from clrefract.runtime import default_runtime

    rt = default_runtime()
    prg = rt.build(["common.h", "adam.cl"], {}, precision)
    dtype = rt.real_dtype(precision)
    rng = np.random.default_rng(4)
    n = 300
    groups = [ParamGroup("table", 0, 200, 0.02, sparse=True), ParamGroup("mlp", 200, n, 3e-3)]
    start = rng.normal(size=n)
    host, p = Adam(n, groups), start.copy()
    dev = DeviceAdam(rt, dtype, prg.adam_step, n, groups)
    cl, q = rt.cl, rt.queue
    buf = cl.Buffer(
        rt.context,
        cl.mem_flags.READ_WRITE | cl.mem_flags.COPY_HOST_PTR,
        hostbuf=start.astype(dtype),
    )
    grad_buf = cl.Buffer(rt.context, cl.mem_flags.READ_WRITE, n * np.dtype(dtype).itemsize)
    for k in range(12):
        grad = rng.normal(size=n) * 10.0 ** rng.uniform(-6, 0, n)
        grad[rng.random(n) < 0.4] = 0.0
        grad[:10] = 0.0  # never touched: a sparse entry stays put
        grad = grad.astype(dtype).astype(np.float64)
        cl.enqueue_copy(q, grad_buf, grad.astype(dtype))
        scale = 0.1 ** (k / 12)
        host.step(p, grad, scale)
        dev.step(buf, grad_buf, scale)
    got = np.empty(n, dtype)
    cl.enqueue_copy(q, got, buf)
    moved = np.abs(p - start)
    assert np.all(got[:10] == start[:10].astype(dtype))
    assert moved[10:200].min() > 0 and moved[200:].min() > 0
    # float32 also rounds the parameters themselves, at their size
    size = moved.max() + (np.abs(start).max() if precision == "float32" else 0.0)
    assert np.abs(got - p).max() < tol * size
