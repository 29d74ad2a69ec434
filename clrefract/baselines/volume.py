"""Straight-ray emission-absorption rendering of a density + colour node grid on the device
(kernels_cl/straight_volume.cl), forward and its exact reverse."""

from __future__ import annotations

import numpy as np

from ..fields.base import Box


class StraightRenderer:
    """Renders rays through a (4, res^3) grid: channel 0 density per mm, 1..3 linear RGB.

    step: sample spacing in mm (each ray's crossing of the box is cut into equal segments no
    longer than this)."""

    def __init__(self, box: Box, res: int, step: float, precision: str = "float32", runtime=None):
        from ..runtime import default_runtime

        self.runtime = runtime or default_runtime()
        self.box, self.res, self.step, self.precision = box, int(res), float(step), precision
        self.dtype = self.runtime.real_dtype(precision)
        self.k = self.runtime.build(
            ["common.h", "straight_volume.cl"], {"RES": self.res}, precision
        )
        self.spacing = box.size / (self.res - 1)
        self._vol = None

    def upload(self, vol: np.ndarray) -> None:
        cl = self.runtime.cl
        self._vol = cl.Buffer(
            self.runtime.context,
            cl.mem_flags.READ_ONLY | cl.mem_flags.COPY_HOST_PTR,
            hostbuf=np.ascontiguousarray(vol, self.dtype).ravel(),
        )

    def _geometry(self):
        r = self.dtype
        lo = [r(v) for v in self.box.lo]
        return [*lo, *(r(h) for h in self.spacing), r(self.step)]

    def _in(self, a):
        cl = self.runtime.cl
        return cl.Buffer(
            self.runtime.context,
            cl.mem_flags.READ_ONLY | cl.mem_flags.COPY_HOST_PTR,
            hostbuf=np.ascontiguousarray(a, self.dtype).ravel(),
        )

    def render(self, origins, dirs, bg):
        """Colour (n, 3) and light left (n,) of rays with unit directions in front of the
        background radiance bg (n, 3)."""
        cl, q = self.runtime.cl, self.runtime.queue
        n = len(origins)
        out = np.empty((n, 3), self.dtype)
        trans = np.empty(n, self.dtype)
        mf, ctx = cl.mem_flags, self.runtime.context
        b_out = cl.Buffer(ctx, mf.WRITE_ONLY, out.nbytes)
        b_tr = cl.Buffer(ctx, mf.WRITE_ONLY, trans.nbytes)
        args = [self._in(origins), self._in(dirs), self._in(bg), self._vol, *self._geometry()]
        self.k.straight_render(q, (n,), None, *args, np.int32(n), b_out, b_tr)
        cl.enqueue_copy(q, out, b_out)
        cl.enqueue_copy(q, trans, b_tr)
        return out.astype(np.float64), trans.astype(np.float64)

    def backward(self, origins, dirs, bg, colour, dl_dc) -> np.ndarray:
        """dLoss/dgrid (4 * res^3,) given each ray's colour and dLoss/dcolour (n, 3)."""
        cl, q = self.runtime.cl, self.runtime.queue
        n = len(origins)
        grad = np.zeros(4 * self.res**3, self.dtype)
        mf, ctx = cl.mem_flags, self.runtime.context
        b_g = cl.Buffer(ctx, mf.READ_WRITE | mf.COPY_HOST_PTR, hostbuf=grad)
        args = [self._in(origins), self._in(dirs), self._in(bg), self._vol, *self._geometry()]
        extra = [np.int32(n), self._in(colour), self._in(dl_dc), b_g]
        self.k.straight_backward(q, (n,), None, *args, *extra)
        cl.enqueue_copy(q, grad, b_g)
        return grad


def render_view(renderer, cam, env, block: int = 1 << 18) -> np.ndarray:
    """A camera's (H, W, 3) image through a straight-ray renderer, in blocks of rays."""
    o, d = cam.rays()
    d = d / np.linalg.norm(d, axis=1, keepdims=True)
    rgb = np.empty((len(o), 3))
    for s in range(0, len(o), block):
        sl = slice(s, s + block)
        rgb[sl] = renderer.render(o[sl], d[sl], env.lookup(d[sl]))[0]
    return rgb.reshape(cam.height, cam.width, 3)
