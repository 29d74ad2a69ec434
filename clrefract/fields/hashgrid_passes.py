"""The two passes of a hash grid's distillation (HashGridField._distil): o and grad o at a
batch of points, then the parameter gradient of the batch's residuals,
sum_n ob_n do/dtheta + omb_n d(mu_n . grad o)/dtheta.

HostPasses runs them in float64 NumPy, the batch cut into one piece per core on threads.
DevicePasses runs them as OpenCL kernels (kernels_cl/hashgrid_distil.cl) on a fit's device,
in its precision. Both take the same batches, so a distillation differs between them by
rounding only. Each holds a distillation's parameters and Adam (`begin`, `train_step`,
`result`): DevicePasses keeps them on the device (adam.DeviceAdam), so that a step sends it
only its points, their residuals and the MLP's summed gradient: a host Adam spent a
quarter of a float32 step moving the million table entries and their gradient across and
updating them (tools/bench_distil.py).
"""

from __future__ import annotations

from contextlib import ExitStack

import numpy as np

from ..device_check import check_once, check_points
from ..limits import host_threads
from ..tracer import work_group_size

DISTIL_PIECE_MIN = 1024  # points per thread of a host batch, at least
# work-items of the reverse kernel, at most: each sums the MLP's gradient over its points in
# its own slot of n_shared numbers, which the host then adds up
REVERSE_ITEMS_MAX = 1024


class HostPasses:
    """A batch's forward and reverse passes are cut into pieces run on threads (NumPy
    releases the GIL in its array work), one per core, with BLAS held to one thread each:
    its own threads on top of them made the distillation slower than one piece (README,
    Fitting)."""

    def __init__(self, field, batch: int):
        self.field = field
        self.pieces = max(1, min(host_threads(), batch // DISTIL_PIECE_MIN))

    def __enter__(self):
        from concurrent.futures import ThreadPoolExecutor

        from threadpoolctl import threadpool_limits

        self._stack = ExitStack()
        self.pool = self._stack.enter_context(ThreadPoolExecutor(self.pieces))
        if self.pieces > 1:
            self._stack.enter_context(threadpool_limits(1, user_api="blas"))
        return self

    def __exit__(self, *exc):
        self._stack.close()

    def begin(self, params: np.ndarray, groups) -> None:
        """Hold a distillation's parameters (a copy) and its Adam."""
        from ..adam import Adam

        self._p = params.copy()
        self._adam = Adam(len(params), groups)

    def train_step(self, pts: np.ndarray, residual, lr_scale: float) -> None:
        """One Adam step on the held parameters from the residuals `residual(o, grad o)`
        at `pts`."""
        grad = self.reverse(*residual(*self.forward(self._p, pts)))
        self._adam.step(self._p, grad, lr_scale)

    def result(self) -> np.ndarray:
        return self._p

    def forward(self, params: np.ndarray, pts: np.ndarray):
        f = self.field
        xs = np.array_split(pts, self.pieces)
        fw = list(self.pool.map(lambda x: f.forward2(x, None, params, False), xs))
        self._tapes, self._params = [r[3] for r in fw], params
        return np.concatenate([r[0] for r in fw]), np.concatenate([r[1] for r in fw])

    def reverse(self, ob: np.ndarray, omb: np.ndarray, mu: np.ndarray) -> np.ndarray:
        # the same cuts as the points': array_split cuts equal lengths alike
        cut = [np.array_split(x, self.pieces) for x in (ob, omb, mu)]
        p, f = self._params, self.field
        return sum(self.pool.map(lambda *a: f.reverse2(*a, p), *cut, self._tapes))


class DevicePasses:
    """The passes on an OpenCL device: the parameters are uploaded in the runtime's
    precision at every forward pass, the gradient comes back as float64."""

    def __init__(self, field, runtime, precision: str = "float32", lanes: int | None = None):
        self.field, self.runtime = field, runtime
        self.dtype = runtime.real_dtype(precision)
        self.lanes = field.lanes_on(runtime, lanes or runtime.default_lanes(precision))
        runtime.check_lanes(self.lanes, precision)
        defines = {**field.defines(), "GEO_AT": len(field.params()), "LANES": self.lanes}
        sources = ["common.h", field.source, field.adjoint_source, "hashgrid_distil.cl", "adam.cl"]
        prg = runtime.build(sources, defines, precision)
        self._k_o, self._k_reverse, self._k_adam = (
            prg.hg_points_o,
            prg.hg_points_reverse,
            prg.adam_step,
        )
        cl, ctx = runtime.cl, runtime.context
        mf = cl.mem_flags
        c = field.config
        self.n_params, self.n_tables = c.n_params, c.n_table_params
        self._fp = cl.Buffer(
            ctx, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=self._real(field.kernel_params(field.box))
        )
        # written by the device's Adam step (adam.cl) as well as read by the passes
        self._fd = cl.Buffer(ctx, mf.READ_WRITE, (self.n_params + 1) * self._itemsize)
        # the kernel adds only table entries there (the MLP's gradient goes to `partial`, and
        # from the host into the rest for the device's Adam)
        self._grad = cl.Buffer(ctx, mf.READ_WRITE, self.n_params * self._itemsize)
        self._bufs = {}
        self._adam = None
        pts = check_points(field.box)
        p = field.params_vec
        check_once(
            runtime,
            prg,
            precision,
            "the hash grid's MLP output (distillation)",
            lambda: (self.forward(p, pts)[0], field.forward2(pts, None, p, False)[0]),
        )

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self._bufs.clear()

    def _real(self, a) -> np.ndarray:
        return np.ascontiguousarray(a, dtype=self.dtype)

    def _buffer(self, name: str, n: int):
        """A device buffer of n reals, kept from batch to batch."""
        cl = self.runtime.cl
        buf = self._bufs.get(name)
        nbytes = max(n, 1) * self._itemsize
        if buf is None or buf.size < nbytes:
            buf = cl.Buffer(self.runtime.context, cl.mem_flags.READ_WRITE, nbytes)
            self._bufs[name] = buf
        return buf

    def _columns(self, names, cols: list[np.ndarray], points: bool) -> list:
        """Columns padded to the lanes and copied to the device: points with the last one,
        residuals with zeros (padding then adds nothing)."""
        cl, q = self.runtime.cl, self.runtime.queue
        bufs = []
        for name, col in zip(names, cols):
            if self._pad:
                col = np.concatenate([col, np.repeat(col[-1:] if points else 0.0, self._pad)])
            col = self._real(col)
            buf = self._buffer(name, len(col))
            cl.enqueue_copy(q, buf, col, is_blocking=False)
            bufs.append(buf)
        return bufs

    def begin(self, params: np.ndarray, groups) -> None:
        """Hold a distillation's parameters and its Adam (DeviceAdam) on the device."""
        from ..adam import DeviceAdam

        self._upload(params)
        self._adam = DeviceAdam(self.runtime, self.dtype, self._k_adam, self.n_params, groups)

    def train_step(self, pts: np.ndarray, residual, lr_scale: float) -> None:
        """One Adam step on the held parameters from the residuals `residual(o, grad o)` at
        `pts`: only the points, residuals and the MLP's gradient cross to the device."""
        q = self.runtime.queue
        shared = self._reverse_pass(*residual(*self._points_o(pts)))
        offset = self.field.shared_offset * self._itemsize
        self.runtime.cl.enqueue_copy(
            q, self._grad, self._real(shared), dst_offset=offset, is_blocking=False
        )
        self._adam.step(self._fd, self._grad, lr_scale)

    def result(self) -> np.ndarray:
        """The held parameters, as float64."""
        p = np.empty(self.n_params + 1, self.dtype)
        self.runtime.cl.enqueue_copy(self.runtime.queue, p, self._fd)
        return p[:-1].astype(np.float64)

    def _upload(self, params: np.ndarray) -> None:
        self.runtime.cl.enqueue_copy(
            self.runtime.queue, self._fd, self._real(np.append(params, 0)), is_blocking=False
        )

    def forward(self, params: np.ndarray, pts: np.ndarray):
        self._upload(params)
        return self._points_o(pts)

    def o_at(self, params: np.ndarray, pts: np.ndarray, chunk: int) -> np.ndarray:
        """o at many points, `chunk` a launch, the parameters uploaded once."""
        self._upload(params)
        return np.concatenate(
            [self._points_o(pts[a : a + chunk])[0] for a in range(0, len(pts), chunk)]
        )

    def _points_o(self, pts: np.ndarray):
        cl, q = self.runtime.cl, self.runtime.queue
        n = len(pts)
        self._pad = (-n) % self.lanes
        self._n = n
        self._pts = self._columns("xyz", [pts[:, k] for k in range(3)], True)
        m = n + self._pad
        outs = [self._buffer(name, m) for name in ("o", "ox", "oy", "oz")]
        items = m // self.lanes
        self._k_o(q, (items,), self._group(items), self._fp, self._fd, *self._pts, *outs)
        host = [np.empty(m, self.dtype) for _ in outs]
        for h, b in zip(host, outs):
            cl.enqueue_copy(q, h, b, is_blocking=False)
        q.finish()
        o = host[0][:n].astype(np.float64)
        return o, np.stack(host[1:], axis=1)[:n].astype(np.float64)

    def reverse(self, ob: np.ndarray, omb: np.ndarray, mu: np.ndarray) -> np.ndarray:
        shared = self._reverse_pass(ob, omb, mu)
        tables = np.empty(self.n_tables, self.dtype)
        self.runtime.cl.enqueue_copy(self.runtime.queue, tables, self._grad)
        grad = np.zeros(self.n_params)
        grad[: self.n_tables] = tables
        off = self.field.shared_offset
        grad[off : off + len(shared)] = shared
        return grad

    def _reverse_pass(self, ob: np.ndarray, omb: np.ndarray, mu: np.ndarray) -> np.ndarray:
        """The table entries' gradient into `_grad` on the device; the MLP's, summed."""
        cl, q = self.runtime.cl, self.runtime.queue
        res = self._columns(["ob", "omb", "mx", "my", "mz"], [ob, omb, *mu.T], False)
        n_vec = (self._n + self._pad) // self.lanes
        per = -(-n_vec // REVERSE_ITEMS_MAX)
        items = -(-n_vec // per)
        n_shared = self.field.n_shared
        partial = self._buffer("partial", items * n_shared)
        cl.enqueue_fill_buffer(q, self._grad, self.dtype(0), 0, self.n_tables * self._itemsize)
        self._k_reverse(
            q,
            (items,),
            self._group(items),
            self._fp,
            self._fd,
            np.int32(n_vec),
            np.int32(per),
            *self._pts,
            *res,
            self._grad,
            partial,
        )
        shared = np.empty(items * n_shared, self.dtype)
        cl.enqueue_copy(q, shared, partial)
        return shared.reshape(items, n_shared).astype(np.float64).sum(0)

    def _group(self, items: int):
        """Work-groups small enough for PoCL's stack (tracer.work_group_size)."""
        g = work_group_size(items, self.runtime)
        return None if g is None else (g,)

    @property
    def _itemsize(self) -> int:
        return np.dtype(self.dtype).itemsize
