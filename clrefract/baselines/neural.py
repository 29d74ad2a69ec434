"""The Meridian-style baseline's neural field: density and colour at points from a
multi-resolution hash encoding and a small MLP with a 4-unit head, rendered by straight rays
(clrefract.baselines.composite) with the environment behind.

    o = MLP(features(x)),  sigma = softplus(o_0) per mm,  rgb = sigmoid(o_1..3) (linear).

The encoding is the hash grid's (clrefract.fields.hashgrid: same levels, hashing, table layout
and NumPy reference), trilinear: straight rays need no spatial derivatives. Parameters: one
flat vector, the tables, the hidden layers (W out x in, then b) and the head W (4 x hidden),
b (4). The device evaluates and differentiates the field (kernels_cl/straight_neural.cl);
the host composites in float64. `reference` is the float64 NumPy forward pass.
"""

from __future__ import annotations

import json
import math
from dataclasses import asdict
from pathlib import Path

import numpy as np

from ..errors import ClrefractError
from ..fields.base import Box
from ..fields.hashgrid import HashGridConfig, HashGridField, softplus_sigmoid
from ..imageio import atomic_path
from .composite import composite, composite_backward, ray_samples
from .volume import render_view

DENSITY_BIAS = -5.0  # the head's start: sigma = softplus(-5) = 0.007/mm, nearly clear
_LAUNCH = 1 << 20  # points per kernel launch (bounds device memory)


def _sigmoid(h):
    return 0.5 * (1.0 + np.tanh(0.5 * h))


class NeuralField:
    """Density and colour of a hash encoding + MLP (module docstring: layout)."""

    def __init__(self, config: HashGridConfig, box: Box, params=None, seed: int = 0):
        if config.interp != "trilinear":
            config = HashGridConfig(**{**asdict(config), "interp": "trilinear"})
        self.config, self.box = config, box
        self.encoding = HashGridField(config, box, np.zeros(config.n_params))
        self.shapes = config.layer_shapes[:-1] + [(4, config.hidden)]
        self.n_params = config.n_table_params + sum(o * i + o for o, i in self.shapes)
        self.params = self.initial_params(seed) if params is None else self._checked(params)

    def _checked(self, params) -> np.ndarray:
        p = np.array(params, np.float64).reshape(-1)
        if p.size != self.n_params:
            raise ClrefractError(f"neural field needs {self.n_params} parameters, got {p.size}")
        if not np.all(np.isfinite(p)):
            raise ClrefractError("neural field parameters are not all finite")
        return p

    def initial_params(self, seed: int) -> np.ndarray:
        """instant-ngp's start: tiny tables, Kaiming-uniform hidden layers, zero biases; the
        head small, nearly clear and grey."""
        rng = np.random.default_rng(seed)
        c = self.config
        p = np.empty(self.n_params)
        p[: c.n_table_params] = rng.uniform(-1e-4, 1e-4, c.n_table_params)
        off = c.n_table_params
        for n, (o, i) in enumerate(self.shapes):
            head = n == len(self.shapes) - 1
            bound = 1.0 / math.sqrt(i) if head else math.sqrt(6.0 / i)
            p[off : off + o * i] = rng.uniform(-bound, bound, o * i)
            off += o * i
            p[off : off + o] = [DENSITY_BIAS, 0, 0, 0] if head else 0.0
            off += o
        return p

    def layers(self, params=None) -> list[tuple[np.ndarray, np.ndarray]]:
        """Views (W, b) of every layer, the head last."""
        p = self.params if params is None else params
        out, off = [], self.config.n_table_params
        for o, i in self.shapes:
            out.append((p[off : off + o * i].reshape(o, i), p[off + o * i : off + o * i + o]))
            off += o * i + o
        return out

    def reference(self, pts: np.ndarray, params=None) -> tuple[np.ndarray, np.ndarray]:
        """sigma (n,) and rgb (n, 3) at points (n, 3), float64 NumPy."""
        p = self.params if params is None else np.asarray(params, np.float64)
        a, _ = self.encoding.encode(np.asarray(pts, np.float64).reshape(-1, 3), p)
        *hidden, (wo, bo) = self.layers(p)
        for w, b in hidden:
            a = softplus_sigmoid(a @ w.T + b)[0]
        o = a @ wo.T + bo
        return softplus_sigmoid(o[:, 0])[0], _sigmoid(o[:, 1:])

    def to_dict(self) -> dict:
        return {k: v for k, v in asdict(self.config).items() if k not in ("eta_max", "interp")}


class NeuralRenderer:
    """The field on the device and straight-ray compositing over it, with the interface of
    clrefract.baselines.volume.StraightRenderer (upload, render, backward)."""

    def __init__(self, field: NeuralField, step: float, precision="float32", runtime=None):
        from ..runtime import default_runtime

        self.runtime = runtime or default_runtime()
        self.field, self.box, self.step, self.precision = field, field.box, float(step), precision
        self.dtype = self.runtime.real_dtype(precision)
        self.lanes = self.runtime.default_lanes(precision)
        enc = field.encoding
        defines = {**enc.defines(), "GEO_AT": len(enc.params()), "LANES": self.lanes}
        sources = ["common.h", "field_hashgrid.cl", "straight_neural.cl"]
        self.k = self.runtime.build(sources, defines, precision)
        self._fp = self._buffer(enc.kernel_params(field.box))
        self._fd = None
        self._last = None  # (origins, samples, sigma, rgb) of the last render, for backward
        self.upload(field.params)

    def _buffer(self, a, write=False):
        cl = self.runtime.cl
        mf = cl.mem_flags
        flags = (mf.READ_WRITE if write else mf.READ_ONLY) | mf.COPY_HOST_PTR
        return cl.Buffer(self.runtime.context, flags, hostbuf=np.ascontiguousarray(a, self.dtype))

    def upload(self, params: np.ndarray) -> None:
        self.field.params = np.asarray(params, np.float64).reshape(-1)
        self._fd = self._buffer(self.field.params)

    def _points(self, pts):
        """Structure-of-arrays buffers of points padded to whole lane groups."""
        n = len(pts)
        n_pad = -(-max(n, 1) // self.lanes) * self.lanes
        soa = np.zeros((3, n_pad), self.dtype)
        soa[:, :n] = pts.T
        return n_pad, [self._buffer(soa[a]) for a in range(3)]

    def eval(self, pts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """sigma (n,) and rgb (n, 3) at points on the device."""
        pts = np.asarray(pts, np.float64).reshape(-1, 3)
        out = np.empty((4, len(pts)))
        cl, q = self.runtime.cl, self.runtime.queue
        for s in range(0, len(pts), _LAUNCH):
            chunk = pts[s : s + _LAUNCH]
            n_pad, xyz = self._points(chunk)
            res = np.empty(4 * n_pad, self.dtype)
            b = cl.Buffer(self.runtime.context, cl.mem_flags.WRITE_ONLY, res.nbytes)
            g = n_pad // self.lanes
            self.k.nf_eval(q, (g,), None, self._fp, self._fd, *xyz, np.int32(g), np.int32(n_pad), b)
            cl.enqueue_copy(q, res, b)
            out[:, s : s + len(chunk)] = res.reshape(4, n_pad)[:, : len(chunk)]
        return out[0], out[1:].T

    def eval_backward(self, pts, d_sigma, d_rgb) -> np.ndarray:
        """sum over points of d_sigma dsigma/dtheta + d_rgb . drgb/dtheta (n_params,)."""
        pts = np.asarray(pts, np.float64).reshape(-1, 3)
        f = self.field
        n_shared = f.n_params - f.config.n_table_params
        grad = np.zeros(f.n_params)
        cl, q = self.runtime.cl, self.runtime.queue
        for s in range(0, len(pts), _LAUNCH):
            sl = slice(s, s + _LAUNCH)
            n_pad, xyz = self._points(pts[sl])
            adj = np.zeros((4, n_pad))
            adj[0, : len(pts[sl])] = d_sigma[sl]
            adj[1:, : len(pts[sl])] = np.asarray(d_rgb)[sl].T
            groups = n_pad // self.lanes
            # work-items, each with its own slot of the MLP's gradient: a few per CPU core
            # loop over many point groups; a GPU needs many
            items = min(groups, 256 if self.lanes > 1 else 16384)
            g_tab = self._buffer(np.zeros(f.config.n_table_params), write=True)
            part = np.empty(items * n_shared, self.dtype)
            b_part = cl.Buffer(self.runtime.context, cl.mem_flags.WRITE_ONLY, part.nbytes)
            self.k.nf_backward(
                q, (items,), None, self._fp, self._fd, *xyz,
                np.int32(groups), np.int32(n_pad), self._buffer(adj), g_tab, b_part,
            )  # fmt: skip
            tab = np.empty(f.config.n_table_params, self.dtype)
            cl.enqueue_copy(q, tab, g_tab)
            cl.enqueue_copy(q, part, b_part)
            grad[: f.config.n_table_params] += tab
            grad[f.config.n_table_params :] += part.reshape(items, n_shared).sum(0, np.float64)
        return grad

    def render(self, origins, dirs, bg):
        """Colour (n, 3) and light left (n,) of rays with unit directions."""
        s = ray_samples(origins, dirs, self.box, self.step)
        sigma, rgb = self.eval(s.points)
        self._last = (origins, s, sigma, rgb)
        return composite(sigma, rgb, s, np.asarray(bg, np.float64))

    def backward(self, origins, dirs, bg, colour, dl_dc) -> np.ndarray:
        """dLoss/dparams given each ray's colour and dLoss/dcolour (n, 3)."""
        if self._last is not None and self._last[0] is origins:
            _, s, sigma, rgb = self._last
        else:
            s = ray_samples(origins, dirs, self.box, self.step)
            sigma, rgb = self.eval(s.points)
        d_sigma, d_rgb, live = composite_backward(sigma, rgb, s, colour, np.asarray(dl_dc))
        return self.eval_backward(s.points[live], d_sigma[live], d_rgb[live])


class NeuralModel:
    """A fitted neural straight-ray model, for `clrefract eval` (StraightModel's interface)."""

    kind = "straight"
    slice_label = "density, 1/mm"

    def __init__(self, field: NeuralField, step: float, surface_res: int = 128, runtime=None):
        self.field, self.box, self.surface_res = field, field.box, int(surface_res)
        self.renderer = NeuralRenderer(field, step, runtime=runtime)
        self._nodes = None

    @property
    def params(self) -> np.ndarray:
        return self.field.params

    def node_density(self) -> np.ndarray:
        """Density on the surface_res^3 nodes over the box (x slowest), once."""
        if self._nodes is None:
            r = self.surface_res
            axes = [np.linspace(lo, hi, r) for lo, hi in zip(self.box.lo, self.box.hi)]
            pts = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
            self._nodes = self.renderer.eval(pts)[0].reshape(r, r, r)
        return self._nodes

    @property
    def surface_rule(self) -> str:
        from .surface import density_level

        level = density_level(self.node_density())
        return (
            f"marching cubes of density on {self.surface_res}^3 nodes at half its 99.9th "
            f"percentile, {level:.4g}/mm"
        )

    def surface(self, box):
        from .surface import density_surface

        return density_surface(self.node_density(), self.box)

    def render(self, cam, env) -> np.ndarray:
        return render_view(self.renderer, cam, env, block=1 << 14)  # ~1M samples a block

    def eta(self, pts):
        return None  # no index: eta RMSE is not applicable

    def density(self, pts: np.ndarray) -> np.ndarray:
        return self.renderer.eval(pts)[0]

    slices_of = density

    def save(self, path: Path) -> None:
        with atomic_path(path, suffix=".npz") as tmp, open(tmp, "wb") as f:
            np.savez(
                f,
                kind="neural",
                config=json.dumps(self.field.to_dict()),
                params=self.field.params,
                step=self.renderer.step,
                surface_res=self.surface_res,
                box=json.dumps(self.box.to_dict()),
            )

    @classmethod
    def from_npz(cls, path: Path, z, runtime=None) -> NeuralModel:
        """From an open straight.npz of kind "neural"; a damaged one is the user's to know."""
        try:
            cfg = HashGridConfig(**json.loads(str(z["config"])), interp="trilinear")
            box = Box.from_dict(json.loads(str(z["box"])))
            field = NeuralField(cfg, box, np.asarray(z["params"], np.float64))
            step, res = float(z["step"]), int(z["surface_res"])
        except ClrefractError as exc:
            raise ClrefractError(f"{path}: {exc}") from None
        except Exception as exc:  # noqa: BLE001
            raise ClrefractError(f"{path}: cannot read the neural field ({exc})") from None
        return cls(field, step, res, runtime=runtime)
