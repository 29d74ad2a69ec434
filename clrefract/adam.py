"""Adam over one flat parameter vector, with per-group learning rates and sparse groups.

Sparse groups (hash tables) skip entries whose gradient is exactly zero, as instant-ngp does:
their moments stay and their own step count does not advance.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class ParamGroup:
    name: str
    start: int
    stop: int
    lr: float
    sparse: bool = False


# the moments' decay rates and the denominator's floor, on the host and on a device alike
BETA1, BETA2, EPS = 0.9, 0.99, 1e-15


class Adam:
    def __init__(
        self,
        n: int,
        groups: list[ParamGroup],
        beta1: float = BETA1,
        beta2: float = BETA2,
        eps: float = EPS,
    ):
        self.groups, self.beta1, self.beta2, self.eps = groups, beta1, beta2, eps
        self.m = np.zeros(n)
        self.v = np.zeros(n)
        self.t = np.zeros(n, np.int64)

    def step(self, params: np.ndarray, grad: np.ndarray, lr_scale: float = 1.0) -> None:
        """Update params in place."""
        b1, b2 = self.beta1, self.beta2
        for g in self.groups:
            sl = slice(g.start, g.stop)
            gr = grad[sl]
            idx = np.flatnonzero(gr) if g.sparse else np.arange(g.stop - g.start)
            if idx.size == 0:
                continue
            gi = gr[idx]
            j = idx + g.start
            self.t[j] += 1
            self.m[j] = b1 * self.m[j] + (1 - b1) * gi
            self.v[j] = b2 * self.v[j] + (1 - b2) * gi * gi
            t = self.t[j]
            mhat = self.m[j] / (1 - b1**t)
            vhat = self.v[j] / (1 - b2**t)
            params[j] -= g.lr * lr_scale * mhat / (np.sqrt(vhat) + self.eps)

    def state(self) -> dict:
        return {"adam_m": self.m, "adam_v": self.v, "adam_t": self.t}

    def load_state(self, d: dict) -> None:
        self.m, self.v, self.t = (
            np.array(d["adam_m"], float),
            np.array(d["adam_v"], float),
            np.array(d["adam_t"], np.int64),
        )


class DeviceAdam:
    """Adam.step on a parameter buffer that lives on an OpenCL device, its moments beside it
    (kernels_cl/adam.cl, built into the caller's program as `kernel`): a hash grid's
    distillation then keeps its million table entries off the host between steps."""

    def __init__(self, runtime, dtype, kernel, n: int, groups: list[ParamGroup]):
        cl, ctx, q = runtime.cl, runtime.context, runtime.queue
        self.queue, self.groups, self._k = q, groups, kernel
        self._real = np.dtype(dtype).type
        self._consts = tuple(self._real(x) for x in (BETA1, BETA2, EPS))
        n = max(n, 1)
        rw = cl.mem_flags.READ_WRITE
        self._m, self._v = (cl.Buffer(ctx, rw, n * np.dtype(dtype).itemsize) for _ in "mv")
        self._t = cl.Buffer(ctx, rw, n * 4)
        for buf in (self._m, self._v, self._t):
            cl.enqueue_fill_buffer(
                q, buf, np.int32(0) if buf is self._t else self._real(0), 0, buf.size
            )

    def step(self, params, grad, lr_scale: float = 1.0) -> None:
        """Update the device buffer `params` in place from the device buffer `grad`."""
        for g in self.groups:
            if g.stop > g.start:
                self._k(
                    self.queue,
                    (g.stop - g.start,),
                    None,
                    params,
                    self._m,
                    self._v,
                    self._t,
                    grad,
                    np.int32(g.start),
                    self._real(g.lr * lr_scale),
                    *self._consts,
                    np.int32(g.sparse),
                )
