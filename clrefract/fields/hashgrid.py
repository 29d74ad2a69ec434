"""Multi-resolution hash grid + MLP index field (the paper's Vertex-Net, after instant-ngp).

Layout, shared with kernels_cl/field_hashgrid.cl:

- Encoding. The box is normalised to the unit cube, u = (x - box.lo) / box.size, clamped to
  [0, 1]^3 (clamped coordinates have zero derivative). Level l (0 <= l < L) has resolution
  N_l = floor(N_min b^l), b = exp((ln N_max - ln N_min) / (L - 1)) (b = 1 when L = 1), and
  grid vertices 0..N_l per axis at p = u N_l. The cell holding p is c = min(floor(p), N_l - 1)
  and t = p - c in [0, 1]; the corner weights per axis are 1 - s(t) and s(t), with
  s(t) = 3t^2 - 2t^3 ("smoothstep", C1, the default: the adjoint pass needs second
  derivatives) or s(t) = t ("trilinear", C0). Vertex (i, j, k) of level l has table index
      dense (when (N_l + 1)^3 <= T):  (i (N_l + 1) + j) (N_l + 1) + k
      hashed (otherwise):             (i * 1 ^ j * 2654435761 ^ k * 805459861) & (T - 1)
  in uint32 arithmetic (T = 2^log2_table). Feature f of level l is the interpolation of the
  table entries tables[l, index, f]; the L*F features are ordered (l, f), level slowest.
- MLP. features (L*F) -> `layers` hidden layers of width `hidden` with softplus -> 1 output o.
  g = 1 + (eta_max - 1) sigmoid(o) in [1, eta_max] (output "sigmoid"), or
  g = 1 + (eta_max - 1) S((o + 1) / 2) with S the C2 quintic of the level sets (output
  "ramp": exactly 1 below o = -1 and eta_max above 1, kinks that rendering steps land on);
  eta = 1 + W(x) (g - 1) with W the box window, so rays leave the box in straight lines.
  The gradient is exact (forward mode).
- Parameters: ONE flat float64 vector (data(), fd on the device):
      tables  L*T*F  as tables[l, index, f] in C order, offset 0 (`table_slice`)
      MLP     layer by layer: W (out x in, row-major) then b (out), for the hidden layers and
              the output layer (out = 1), offset L*T*F (`mlp_slice`)
- Small parameters (params(), fp on the device): [eta_max, N_0 .. N_{L-1},
  dense_0 .. dense_{L-1}] (dense_l = 1.0 for a directly indexed level, 0.0 for a hashed one).
- Build defines: FIELD_HASHGRID, HG_LEVELS, HG_FEATURES, HG_LOG2T, HG_HIDDEN, HG_LAYERS,
  HG_SMOOTH, HG_RAMP and HG_MLP_OFFSET (= L*T*F, where the MLP starts in fd).
- Backward pass (kernels_cl/hashgrid_adjoint.cl, reference `adjoint_terms`): eta, grad eta,
  Hess(eta) mu by second-order forward mode, then reverse mode of the splat
  w d/dtheta [eta (mu . grad eta)] into the parameters. Table entries get atomic adds; the
  MLP (`n_shared` parameters from `shared_offset`) is summed per work-item over its rays
  into the engine's `partial` buffer. Fit with smoothstep: trilinear weights have Dirac
  second derivatives on the cell faces that a pointwise adjoint misses.
"""

from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass, fields
from pathlib import Path

import numpy as np

from ..errors import ClrefractError
from ..imageio import atomic_path
from .base import Box, Field, box_window, smoother, smoother_d, smoother_dd

INTERPS = ("smoothstep", "trilinear")
OUTPUTS = ("sigmoid", "ramp")
PRIMES = (1, 2654435761, 805459861)  # spatial-hash multipliers of x, y, z (instant-ngp)
_CHUNK = 1 << 15  # points per block in the NumPy reference (bounds temporary memory)


# fit_surface: the output's slope across the surface, per interface width (a 10-90% ramp of
# 0.27 width; the fit steps w/8 through it), and its value far outside (eta - 1 there: 8e-7
# of the index's)
SURFACE_SLOPE = 16.0
SURFACE_FAR = 14.0
SURFACE_LR = (1e-1, 1e-2)  # Adam rates of tables and MLP
SURFACE_GRAD_WEIGHT = 16.0  # of grad o's squared error (width units) against o's
# the same for the ramp output (o = -2 phi / width across the interface); air is held
# below RAMP_FLOOR, a margin under the ramp's foot at -1
RAMP_LR = (1e-1, 1e-2)
RAMP_GRAD_WEIGHT = 16.0
RAMP_FLOOR = -1.25


@dataclass(frozen=True)
class HashGridConfig:
    """Shape of the encoding and the MLP (defaults: instant-ngp's, two hidden layers of 64)."""

    levels: int = 16
    features: int = 2
    log2_table: int = 19
    n_min: int = 16
    n_max: int = 512
    hidden: int = 64
    layers: int = 2
    eta_max: float = 1.6
    interp: str = "smoothstep"
    output: str = "sigmoid"

    def __post_init__(self):
        ints = ("levels", "features", "log2_table", "n_min", "n_max", "hidden", "layers")
        for name in ints:
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int | np.integer):
                raise ClrefractError(f"hash grid {name} must be an integer, got {v!r}")
            object.__setattr__(self, name, int(v))
        if self.levels < 1 or self.features < 1 or self.hidden < 1:
            raise ClrefractError("hash grid levels, features and hidden must be at least 1")
        if not 1 <= self.log2_table <= 26:
            raise ClrefractError(f"hash grid log2_table must be in 1..26, got {self.log2_table}")
        if not 1 <= self.n_min <= self.n_max:
            raise ClrefractError(
                f"hash grid needs 1 <= n_min <= n_max, got n_min={self.n_min}, n_max={self.n_max}"
            )
        if self.n_max > 1 << 20:
            raise ClrefractError(f"hash grid n_max must be at most 2^20, got {self.n_max}")
        if self.layers not in (1, 2):
            raise ClrefractError(f"hash grid layers must be 1 or 2, got {self.layers}")
        if not (math.isfinite(self.eta_max) and self.eta_max > 1):
            raise ClrefractError(f"hash grid eta_max must be > 1, got {self.eta_max!r}")
        object.__setattr__(self, "eta_max", float(self.eta_max))
        if self.interp not in INTERPS:
            raise ClrefractError(f"hash grid interp must be one of {INTERPS}, got {self.interp!r}")
        if self.output not in OUTPUTS:
            raise ClrefractError(f"hash grid output must be one of {OUTPUTS}, got {self.output!r}")
        if self.n_table_params >= 1 << 31:
            raise ClrefractError(
                f"hash grid tables of {self.n_table_params} entries exceed 2^31 (kernel indices)"
            )

    @property
    def table_size(self) -> int:
        return 1 << self.log2_table

    @property
    def n_features(self) -> int:
        return self.levels * self.features

    @property
    def n_table_params(self) -> int:
        return self.levels * self.table_size * self.features

    @property
    def growth(self) -> float:
        """b = exp((ln N_max - ln N_min) / (L - 1)), 1 for a single level."""
        if self.levels == 1:
            return 1.0
        return math.exp((math.log(self.n_max) - math.log(self.n_min)) / (self.levels - 1))

    @property
    def resolutions(self) -> list[int]:
        """N_l = floor(N_min b^l); the tolerance keeps N_{L-1} = N_max against rounding."""
        b = self.growth
        return [
            int(math.floor(self.n_min * b**level * (1 + 1e-12))) for level in range(self.levels)
        ]

    @property
    def dense(self) -> list[bool]:
        """Whether each level indexes its vertices directly ((N_l + 1)^3 <= T)."""
        return [(n + 1) ** 3 <= self.table_size for n in self.resolutions]

    @property
    def layer_shapes(self) -> list[tuple[int, int]]:
        """(out, in) of every MLP layer, the output layer last."""
        shapes, n_in = [], self.n_features
        for _ in range(self.layers):
            shapes.append((self.hidden, n_in))
            n_in = self.hidden
        shapes.append((1, n_in))
        return shapes

    @property
    def n_mlp_params(self) -> int:
        return sum(o * i + o for o, i in self.layer_shapes)

    @property
    def n_params(self) -> int:
        return self.n_table_params + self.n_mlp_params

    @classmethod
    def from_dict(cls, d: dict) -> HashGridConfig:
        known = {f.name for f in fields(cls)}
        unknown = set(d) - known
        if unknown:
            raise ClrefractError(f"unknown hash grid config keys: {', '.join(sorted(unknown))}")
        return cls(**d)


def hash_index(i, j, k, log2_table: int) -> np.ndarray:
    """Spatial hash of integer vertices: (i * 1 ^ j * 2654435761 ^ k * 805459861) mod 2^log2T,
    in uint32 arithmetic (the products wrap modulo 2^32)."""
    u = [np.asarray(a).astype(np.uint32) for a in (i, j, k)]
    h = (
        (u[0] * np.uint32(PRIMES[0]))
        ^ (u[1] * np.uint32(PRIMES[1]))
        ^ (u[2] * np.uint32(PRIMES[2]))
    )
    return (h & np.uint32((1 << log2_table) - 1)).astype(np.int64)


def dense_index(i, j, k, n: int) -> np.ndarray:
    """Direct index of vertex (i, j, k) on a level of n cells per axis (x slowest)."""
    s = n + 1
    return (np.asarray(i, np.int64) * s + np.asarray(j, np.int64)) * s + np.asarray(k, np.int64)


def softplus_sigmoid(h):
    """softplus(h) and its derivative sigmoid(h), sharing one exponential."""
    e = np.exp(-np.abs(h))
    r = 1.0 / (1.0 + e)
    return np.maximum(h, 0.0) + np.log1p(e), np.where(h >= 0, r, e * r)


def _sigmoid(h):
    e = np.exp(-np.abs(h))
    return np.where(h >= 0, 1.0 / (1.0 + e), e / (1.0 + e))


def _output_map(o, k: float, ramp: bool):
    """G(o) = g - 1 and its first two derivatives in o: k sigmoid(o), or k S((o + 1) / 2)
    with S the C2 quintic (exactly 0 below o = -1 and k above 1, as a level set's ramp)."""
    if ramp:
        t = 0.5 * (o + 1)
        return k * smoother(t), 0.5 * k * smoother_d(t), 0.25 * k * smoother_dd(t)
    so = _sigmoid(o)
    g0 = k * so
    g1 = g0 * (1 - so)
    return g0, g1, g1 * (1 - 2 * so)


def _smoother_inverse(y: float) -> float:
    """t in [0, 1] with S(t) = y, 0 < y < 1 (S the C2 quintic, increasing)."""
    from scipy.optimize import brentq

    return float(brentq(lambda t: float(smoother(t)) - y, 0.0, 1.0, xtol=1e-14))


def _axis_weights(t, smooth: bool):
    """s(t), s'(t), s''(t) of the high corner's weight along one axis."""
    if smooth:
        return t * t * (3 - 2 * t), 6 * t * (1 - t), 6 - 12 * t
    return t, np.ones_like(t), np.zeros_like(t)


def _window_hessian(box: Box, pts: np.ndarray):
    """Box window W (n,), its gradient (n, 3) and Hessian (n, 3, 3) (base.box_window's W)."""
    lo, hi, m = np.asarray(box.lo), np.asarray(box.hi), box.margin
    d0, d1 = (pts - lo) / m - 1, (hi - pts) / m - 1

    s, ds, dds = smoother, smoother_d, smoother_dd
    a = s(d0) * s(d1)  # per-axis factors (n, 3) and their derivatives in x
    da = (ds(d0) * s(d1) - s(d0) * ds(d1)) / m
    dda = (dds(d0) * s(d1) - 2 * ds(d0) * ds(d1) + s(d0) * dds(d1)) / m**2
    grad = np.empty_like(pts)
    hess = np.empty((len(pts), 3, 3))
    for r in range(3):
        f = a.copy()
        f[:, r] = da[:, r]
        grad[:, r] = f.prod(axis=1)
        for q in range(3):
            f = a.copy()
            if r == q:
                f[:, r] = dda[:, r]
            else:
                f[:, r], f[:, q] = da[:, r], da[:, q]
            hess[:, r, q] = f.prod(axis=1)
    return a.prod(axis=1), grad, hess


class HashGridField(Field):
    """eta(x) from a multi-resolution hash encoding and a small MLP (module docstring: layout).

    config: HashGridConfig; box: the field's box (its walls get the window);
    params: the flat parameter vector (copied), or None for instant-ngp's initialisation:
            tables uniform(-1e-4, 1e-4), hidden layers Kaiming-uniform with zero biases, the
            output layer small with bias -6 so that the initial eta is close to 1;
    seed: seed of that initialisation.
    """

    kind = "hashgrid"
    source = "field_hashgrid.cl"
    adjoint_source = "hashgrid_adjoint.cl"
    device_checked = True
    # NVIDIA's OpenCL compiler (driver 580, H100) gets eta wrong by about 1e-2 and the
    # gradient non-finite in the 4- to 16-lane kernels, which PoCL runs right; one lane, a
    # GPU's own layout, matches the reference (tools/suite_on_devices.py).
    gpu_lanes = 1

    def __init__(
        self,
        config: HashGridConfig | None = None,
        box: Box | None = None,
        params: np.ndarray | None = None,
        seed: int = 0,
    ):
        self.config = config or HashGridConfig()
        self.box = box or Box()
        if params is None:
            self.params_vec = self.initial_params(self.config, seed)
        else:
            self.params_vec = self._checked(params)

    # --- parameters -------------------------------------------------------------------------
    @staticmethod
    def initial_params(config: HashGridConfig, seed: int = 0) -> np.ndarray:
        rng = np.random.default_rng(seed)
        p = np.empty(config.n_params)
        p[: config.n_table_params] = rng.uniform(-1e-4, 1e-4, config.n_table_params)
        off = config.n_table_params
        shapes = config.layer_shapes
        for n, (o, i) in enumerate(shapes):
            last = n == len(shapes) - 1
            bound = (1.0 / math.sqrt(i)) if last else math.sqrt(6.0 / i)
            p[off : off + o * i] = rng.uniform(-bound, bound, o * i)
            off += o * i
            p[off : off + o] = -6.0 if last else 0.0
            off += o
        return p

    def _checked(self, params) -> np.ndarray:
        p = np.array(params, dtype=np.float64).reshape(-1)
        if p.size != self.config.n_params:
            raise ClrefractError(
                f"hash grid with this config has {self.config.n_params} parameters "
                f"({self.config.n_table_params} table + {self.config.n_mlp_params} MLP), "
                f"got {p.size}"
            )
        if not np.all(np.isfinite(p)):
            raise ClrefractError(
                f"hash grid parameters contain {int(np.sum(~np.isfinite(p)))} non-finite values"
            )
        return p

    @property
    def table_slice(self) -> slice:
        """Where the hash tables lie in the flat parameter vector."""
        return slice(0, self.config.n_table_params)

    @property
    def mlp_slice(self) -> slice:
        """Where the MLP weights and biases lie in the flat parameter vector."""
        return slice(self.config.n_table_params, self.config.n_params)

    @property
    def tables(self) -> np.ndarray:
        """View (L, T, F) of the tables inside the parameter vector."""
        c = self.config
        return self.params_vec[self.table_slice].reshape(c.levels, c.table_size, c.features)

    def mlp_layers(self, params: np.ndarray | None = None) -> list[tuple[np.ndarray, np.ndarray]]:
        """Views (W (out, in), b (out,)) of every layer, the output layer last."""
        p = self.params_vec if params is None else params
        out, off = [], self.config.n_table_params
        for o, i in self.config.layer_shapes:
            w = p[off : off + o * i].reshape(o, i)
            off += o * i
            out.append((w, p[off : off + o]))
            off += o
        return out

    @property
    def n_shared(self) -> int:
        """Parameters shared by every ray (the MLP): the backward pass sums their gradient
        per work-item into a buffer the host adds up, instead of global atomics."""
        return self.config.n_mlp_params

    @property
    def shared_offset(self) -> int:
        return self.config.n_table_params

    def set_data(self, params: np.ndarray) -> None:
        """Take a new flat parameter vector (copied)."""
        self.params_vec = self._checked(params)

    def param_groups(self, lr: float = 1e-3, lr_table: float | None = None, lr_mlp=None, **_):
        """Adam groups: the tables (sparse, as instant-ngp) and the MLP, each its own rate."""
        from ..adam import ParamGroup

        t, m = self.table_slice, self.mlp_slice
        return [
            ParamGroup("tables", t.start, t.stop, lr if lr_table is None else lr_table, True),
            ParamGroup("mlp", m.start, m.stop, lr if lr_mlp is None else lr_mlp),
        ]

    # --- what the tracer needs ---------------------------------------------------------------
    def defines(self) -> dict:
        c = self.config
        return {
            "FIELD_HASHGRID": 1,
            "HG_LEVELS": c.levels,
            "HG_FEATURES": c.features,
            "HG_LOG2T": c.log2_table,
            "HG_HIDDEN": c.hidden,
            "HG_LAYERS": c.layers,
            "HG_SMOOTH": int(c.interp == "smoothstep"),
            "HG_RAMP": int(c.output == "ramp"),
            "HG_MLP_OFFSET": c.n_table_params,
        }

    def params(self) -> np.ndarray:
        """[eta_max, N_0 .. N_{L-1}, dense_0 .. dense_{L-1}] (fp in the kernel)."""
        c = self.config
        return np.array([c.eta_max, *c.resolutions, *map(float, c.dense)], np.float64)

    def data(self) -> np.ndarray:
        """The flat parameter vector: tables, then the MLP (fd in the kernel)."""
        return self.params_vec

    def uses_window(self) -> bool:
        return True

    @property
    def eta_max(self) -> float:
        return self.config.eta_max

    @property
    def suggested_step(self) -> float:
        """Half the finest level's cell (a step does not jump over its features), at most 0.5."""
        cell = float(self.box.size.min()) / self.config.resolutions[-1]
        return float(min(0.5, 0.5 * cell))

    def to_dict(self) -> dict:
        """Metadata only (the parameters live in the .npz file)."""
        return {"kind": self.kind, **asdict(self.config), "box": self.box.to_dict()}

    # --- NumPy reference ---------------------------------------------------------------------
    def _corner_indices(self, cell: np.ndarray, level: int) -> np.ndarray:
        """Table indices (n, 8) of the corners of cells (n, 3) of one level: per axis the
        low and high vertex, combined by broadcasting (corner 4a + 2b + d: a, b, d
        low or high along x, y, z)."""
        c = self.config
        v = cell[:, :, None] + np.arange(2)  # (n, 3, 2): low and high vertex per axis
        x, y, z = v[:, 0, :, None, None], v[:, 1, None, :, None], v[:, 2, None, None, :]
        if c.dense[level]:
            idx = dense_index(x, y, z, c.resolutions[level])
        else:
            idx = hash_index(x, y, z, c.log2_table)
        return idx.reshape(len(cell), 8)

    def _level_corners(self, u: np.ndarray, inside: np.ndarray, level: int, second=False):
        """The 8 corners of the cell holding normalised points u (n, 3) on one level.

        Returns table indices (n, 8), the corner weights and their gradient in x as one
        array W (n, 4, 8) (row 0 the weights, rows 1-3 their x, y, z derivatives: features
        and their gradient are then one product W @ values) and, with `second`, their
        Hessian in x ddw (n, 8, 3, 3). Each is a product of one factor per axis (1 - s or
        s, and their derivatives), formed as an outer product of the axes' (low, high)
        pairs."""
        c = self.config
        n = len(u)
        n_l = c.resolutions[level]
        p = u * n_l
        cell = np.clip(np.floor(p).astype(np.int64), 0, n_l - 1)
        s, ds, dds = _axis_weights(p - cell, c.interp == "smoothstep")
        scale = n_l / self.box.size  # dp/dx per axis
        ds = ds * scale * inside  # clamped coordinates have zero derivative
        a = np.stack([1.0 - s, s], axis=2)  # (n, 3, 2): low and high factor per axis
        da = np.stack([-ds, ds], axis=2)

        def outer(fx, fy, fz):  # (n, 2) per axis -> (n, 8)
            return (fx[:, :, None, None] * fy[:, None, :, None] * fz[:, None, None, :]).reshape(
                n, 8
            )

        ax, ay, az = a[:, 0], a[:, 1], a[:, 2]
        dx, dy, dz = da[:, 0], da[:, 1], da[:, 2]
        yz = (ay[:, :, None] * az[:, None, :]).reshape(n, 1, 4)
        w = np.empty((n, 4, 2, 4))
        w[:, 0] = ax[:, :, None] * yz
        w[:, 1] = dx[:, :, None] * yz
        w[:, 2] = ax[:, :, None] * (dy[:, :, None] * az[:, None, :]).reshape(n, 1, 4)
        w[:, 3] = ax[:, :, None] * (ay[:, :, None] * dz[:, None, :]).reshape(n, 1, 4)
        w = w.reshape(n, 4, 8)
        idx = self._corner_indices(cell, level)
        if not second:
            return idx, w
        dds = dds * scale**2 * inside
        dda = np.stack([-dds, dds], axis=2)
        f, df, ddf = (ax, ay, az), (dx, dy, dz), (dda[:, 0], dda[:, 1], dda[:, 2])
        ddw = np.empty((n, 8, 3, 3))
        for r in range(3):
            for q in range(r, 3):
                g = list(f)
                if r == q:
                    g[r] = ddf[r]
                else:
                    g[r], g[q] = df[r], df[q]
                ddw[..., r, q] = ddw[..., q, r] = outer(*g)
        return idx, w, ddw

    def _normalised(self, pts: np.ndarray):
        u = (pts - np.asarray(self.box.lo)) / self.box.size
        uc = np.clip(u, 0.0, 1.0)
        return uc, (u == uc).astype(np.float64)

    def encode(self, pts: np.ndarray, params: np.ndarray | None = None):
        """Features (n, L*F) and their gradient d features / dx (n, L*F, 3) at points (n, 3).
        The 8 corners are contracted along z, then y, then x (fewer operations than
        weighting every corner by a product of three factors)."""
        pts = np.asarray(pts, np.float64).reshape(-1, 3)
        c = self.config
        tab = (self.params_vec if params is None else params)[self.table_slice]
        tab = tab.reshape(c.levels, c.table_size, c.features)
        n = len(pts)
        feat = np.empty((n, c.n_features))
        dfeat = np.empty((n, c.n_features, 3))
        u, inside = self._normalised(pts)
        for level in range(c.levels):
            n_l = c.resolutions[level]
            p = u * n_l
            cell = np.clip(np.floor(p).astype(np.int64), 0, n_l - 1)
            s, ds, _ = _axis_weights(p - cell, c.interp == "smoothstep")
            ds = ds * (n_l / self.box.size) * inside
            s, ds = s[:, :, None, None, None], ds[:, :, None, None, None]
            v = tab[level][self._corner_indices(cell, level)].reshape(n, 2, 2, 2, -1)
            # corner c = 4a + 2b + d, (a, b, d) low/high along (x, y, z)
            dv = v[:, :, :, 1] - v[:, :, :, 0]
            vz, gz = v[:, :, :, 0] + dv * s[:, 2], dv * ds[:, 2]  # (n, 2, 2, F)
            dv = vz[:, :, 1] - vz[:, :, 0]
            vy, gy = vz[:, :, 0] + dv * s[:, 1, 0], dv * ds[:, 1, 0]  # (n, 2, F)
            gz = gz[:, :, 0] + (gz[:, :, 1] - gz[:, :, 0]) * s[:, 1, 0]
            sx, dsx = s[:, 0, 0, 0], ds[:, 0, 0, 0]  # (n, 1)
            sl = slice(level * c.features, (level + 1) * c.features)
            feat[:, sl] = vy[:, 0] + (vy[:, 1] - vy[:, 0]) * sx
            dfeat[:, sl, 0] = (vy[:, 1] - vy[:, 0]) * dsx
            dfeat[:, sl, 1] = gy[:, 0] + (gy[:, 1] - gy[:, 0]) * sx
            dfeat[:, sl, 2] = gz[:, 0] + (gz[:, 1] - gz[:, 0]) * sx
        return feat, dfeat

    def mlp(self, feat: np.ndarray, dfeat: np.ndarray, params: np.ndarray | None = None):
        """Output o (n,) and its gradient (n, 3) by forward mode: value and the 3 directional
        derivatives pushed through every layer (dh = W df; d softplus(h) = sigmoid(h) dh)."""
        layers = self.mlp_layers(params)
        n = len(feat)
        # derivatives as (3 n, k) rows: every layer is one matrix product
        a, da = feat, np.moveaxis(dfeat, 2, 0).reshape(3 * n, -1)
        for w, b in layers[:-1]:
            h = a @ w.T + b
            a, sg = softplus_sigmoid(h)
            da = (da @ w.T).reshape(3, n, -1)
            da *= sg
            da = da.reshape(3 * n, -1)
        w, b = layers[-1]
        return a @ w[0] + b[0], (da @ w[0]).reshape(3, n).T

    def _output(self, o):
        """G(o) = g - 1 and its first two derivatives (the config's output map)."""
        c = self.config
        return _output_map(o, c.eta_max - 1.0, c.output == "ramp")

    def eval(self, pts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        pts = np.asarray(pts, np.float64).reshape(-1, 3)
        eta = np.empty(len(pts))
        grad = np.empty((len(pts), 3))
        for a in range(0, len(pts), _CHUNK):
            p = pts[a : a + _CHUNK]
            o, do = self.mlp(*self.encode(p))
            g1, dg, _ = self._output(o)
            dg1 = dg[:, None] * do
            w, dw = box_window(self.box, p)
            eta[a : a + _CHUNK] = 1.0 + w * g1
            grad[a : a + _CHUNK] = dw * g1[:, None] + w[:, None] * dg1
        return eta, grad

    # --- backward pass and regulariser (float64 references) -----------------------------
    def forward2(self, pts, mu, params, hessian=True):
        """Second-order forward mode at points (n, 3) along mu (n, 3): o, grad o and
        Hess(o) mu (mu is only needed with `hessian`; zero without), with what the reverse
        pass needs (`tape`: every layer's input and its gradient, whatever mu the reverse
        pass then takes). Derivatives are (3, n, k): every layer is three matrix products."""
        c = self.config
        tab = params[self.table_slice].reshape(c.levels, c.table_size, c.features)
        n = len(pts)
        f = np.empty((n, c.n_features))
        fg = np.empty((3, n, c.n_features))
        fh = np.zeros((3, n, c.n_features))
        u, inside = self._normalised(pts)
        corners = []
        for level in range(c.levels):
            idx, w, *ddw = self._level_corners(u, inside, level, second=hessian)
            v = tab[level][idx]  # (n, 8, F)
            sl = slice(level * c.features, (level + 1) * c.features)
            fw = w @ v  # (n, 4, F): features, then their x, y, z derivatives
            f[:, sl] = fw[:, 0]
            fg[:, :, sl] = np.moveaxis(fw[:, 1:], 1, 0)
            if hessian:
                for d in range(3):
                    hw = ddw[0][..., d, :] @ mu[:, :, None]  # (n, 8, 1): row d of Hess w, mu
                    fh[d, :, sl] = np.einsum("nc,ncf->nf", hw[..., 0], v)
            corners.append((idx, w))
        layers = self.mlp_layers(params)
        mut = mu.T[:, :, None] if hessian else None  # (3, n, 1)
        a, ag, ah = f, fg, fh
        tape = []
        for wm, b in layers[:-1]:
            h = a @ wm.T + b
            hg = ag @ wm.T
            a_new, s = softplus_sigmoid(h)
            tape.append((a, ag, s, hg))
            if hessian:
                q = s * (1 - s) * (mut * hg).sum(0)
                ah = q * hg + s * (ah @ wm.T)
            a, ag = a_new, s * hg
        wo, bo = layers[-1]
        tape.append((a, ag, None, None))
        oh = (ah @ wo[0]).T if hessian else np.zeros((n, 3))
        return a @ wo[0] + bo[0], (ag @ wo[0]).T, oh, (corners, tape)

    def reverse2(self, ob, omb, mu, tape, params) -> np.ndarray:
        """sum_n ob_n do/dtheta + omb_n do_mu/dtheta (o_mu = mu_n . grad o) over the points
        of a forward2 tape: reverse mode through the (value, mu-tangent) pairs."""
        c = self.config
        corners, acts = tape
        grad = np.zeros(c.n_params)
        offsets, off = [], c.n_table_params
        for o, i in c.layer_shapes:
            offsets.append(off)
            off += o * i + o
        layers = self.mlp_layers(params)
        mut = mu.T[:, :, None]  # (3, n, 1)
        hb, hmb = ob[:, None], omb[:, None]  # adjoints of the output layer's h and h_mu
        for k in range(len(layers) - 1, -1, -1):
            wm, _ = layers[k]
            a, ag, _, _ = acts[k]
            o, i = wm.shape
            grad[offsets[k] : offsets[k] + o * i] = (hb.T @ a + hmb.T @ (mut * ag).sum(0)).ravel()
            grad[offsets[k] + o * i : offsets[k] + o * i + o] = hb.sum(0)
            ab, amb = hb @ wm, hmb @ wm  # adjoints of this layer's inputs
            if k > 0:  # through the softplus of the layer below: a = sp(h), a_mu = s h_mu
                _, _, s, hg = acts[k - 1]
                q = s * (1 - s) * (mut * hg).sum(0)
                hb, hmb = ab * s + amb * q, amb * s
        # table entries: tb = fb w + fmb (mu . grad w) per corner, summed in one bincount
        flat, vals = [], []
        for level, (idx, w) in enumerate(corners):
            wmu = (w[:, 1:] * mu[:, :, None]).sum(1)  # mu . grad of the corner weights
            sl = slice(level * c.features, (level + 1) * c.features)
            # per corner and feature: w ab + wmu amb, one product of (n, 8, 2) by (n, 2, F)
            vals.append(np.stack([w[:, 0], wmu], 2) @ np.stack([ab[:, sl], amb[:, sl]], 1))
            flat.append(
                (level * c.table_size + idx[:, :, None]) * c.features + np.arange(c.features)
            )
        grad[: c.n_table_params] = np.bincount(
            np.concatenate(flat, axis=None),
            np.concatenate(vals, axis=None),
            minlength=c.n_table_params,
        )
        return grad

    def adjoint_terms(self, pts, mu, w=None, params=None):
        """What the backward kernel computes, in float64: at points (n, 3) with adjoint
        mu (n, 3) and weights w (n,), eta (n,), grad eta (n, 3), Hess(eta) mu (n, 3) and
        the parameter gradient sum_n w_n d/dtheta [eta (mu_n . grad eta)](x_n)."""
        p = self.params_vec if params is None else np.asarray(params, np.float64)
        pts = np.asarray(pts, np.float64).reshape(-1, 3)
        mu = np.asarray(mu, np.float64).reshape(-1, 3)
        w = np.ones(len(pts)) if w is None else np.asarray(w, np.float64)
        o, og, oh, tape = self.forward2(pts, mu, p)
        g0, g1, g2 = self._output(o)  # G(o) = g - 1, and its derivatives G', G''
        win, gw, hw = _window_hessian(self.box, pts)
        eta = 1 + win * g0
        ge = g0[:, None] * gw + (win * g1)[:, None] * og
        om = np.einsum("nd,nd->n", mu, og)
        mw = np.einsum("nd,nd->n", mu, gw)
        hm = (
            mw[:, None] * g1[:, None] * og
            + g0[:, None] * np.einsum("nde,ne->nd", hw, mu)
            + (g1 * om)[:, None] * gw
            + win[:, None] * ((g2 * om)[:, None] * og + g1[:, None] * oh)
        )
        me = np.einsum("nd,nd->n", mu, ge)
        ob = w * (me * win * g1 + eta * (mw * g1 + win * g2 * om))
        omb = w * eta * win * g1
        return eta, ge, hm, self.reverse2(ob, omb, mu, tape, p)

    def _distil(
        self,
        pts,
        residual,
        iterations: int,
        batch: int,
        seed: int,
        lr=(3e-2, 3e-3),
        progress=None,
        device=None,
    ) -> None:
        """Adam on a least-squares fit over n points: residual(i, o, grad o) gives, for the
        points i of a batch, d loss / d o and d loss / d grad o. `progress`: a bar
        (clrefract.progress) told of each iteration. `device`: (runtime, precision) runs
        the passes as OpenCL kernels there, else they run in NumPy on the host's cores
        (clrefract/fields/hashgrid_passes.py)."""
        from .hashgrid_passes import DevicePasses, HostPasses

        rng = np.random.default_rng(seed)
        size = min(batch, len(pts))
        passes = DevicePasses(self, *device) if device else HostPasses(self, size)
        with passes:
            passes.begin(self.params_vec, self.param_groups(lr_table=lr[0], lr_mlp=lr[1]))
            for it in range(iterations):
                i = rng.integers(0, len(pts), size=size)
                passes.train_step(
                    pts[i], lambda o, og, i=i: residual(i, o, og), 0.1 ** (it / iterations)
                )
                if progress is not None:
                    progress.update()
            self.set_data(passes.result())

    def eta_rms(self, pts: np.ndarray, eta: np.ndarray, device=None) -> float:
        """RMS error of eta against values at points; `device` as _distil's (NumPy takes
        4 s for the 400,000 points of a refit)."""
        if device is None:
            fit = [self.eval(pts[a : a + _CHUNK])[0] for a in range(0, len(pts), _CHUNK)]
        else:
            from .hashgrid_passes import DevicePasses

            with DevicePasses(self, *device) as passes:
                o = passes.o_at(self.params_vec, pts, _CHUNK)
            fit = [1.0 + box_window(self.box, pts)[0] * self._output(o)[0]]
        return float(np.sqrt(np.mean((np.concatenate(fit) - eta) ** 2)))

    def fit_values(
        self,
        pts: np.ndarray,
        eta: np.ndarray,
        grad: np.ndarray | None = None,
        scale: float = 1.0,
        iterations: int = 300,
        batch: int = 8192,
        seed: int = 0,
        progress=None,
        device=None,
    ) -> float:
        """Fit the field to eta values at points, and to their gradient (scaled by `scale`
        mm: refraction follows the normals, which values alone leave rough), by least
        squares with Adam: the start of a fit from a simpler field. Returns the RMS error
        of eta over all the points."""
        pts = np.asarray(pts, np.float64).reshape(-1, 3)
        eta = np.asarray(eta, np.float64).reshape(-1)
        win, gwin, _ = _window_hessian(self.box, pts)

        def residual(i, o, og):
            w, gw = win[i], gwin[i]
            g0, g1, g2 = self._output(o)
            ob = 2.0 / len(i) * (1.0 + w * g0 - eta[i]) * w * g1
            omb = np.zeros(len(i))
            mu = np.zeros((len(i), 3))
            if grad is not None:  # d|ge - target|^2 = 2 r . d ge, r held fixed
                ge = g0[:, None] * gw + (w * g1)[:, None] * og
                mu = 2.0 * scale**2 / len(i) * (ge - grad[i])
                om = np.einsum("nd,nd->n", mu, og)
                mw = np.einsum("nd,nd->n", mu, gw)
                ob = ob + mw * g1 + w * g2 * om
                omb = w * g1
            return ob, omb, mu

        self._distil(pts, residual, iterations, batch, seed, progress=progress, device=device)
        return self.eta_rms(pts, eta, device)

    def fit_surface(
        self,
        pts: np.ndarray,
        phi: np.ndarray,
        grad_phi: np.ndarray,
        eta: float,
        width: float,
        iterations: int = 1000,
        batch: int = 8192,
        seed: int = 0,
        rate: float = 1.0,
        progress=None,
        device=None,
    ) -> None:
        """Fit the field to a solid of index `eta` bounded by the zero set of a signed
        distance phi (mm, negative inside; its gradient grad_phi) with an interface of
        about `width` mm. The MLP's output o is fitted, value and gradient, to
        -T tanh(SURFACE_SLOPE phi / (width T)): a distance near the surface, whose
        direction is the normal, and flat beyond it, at T = logit((eta - 1) / (eta_max - 1))
        inside (eta there is the index) and SURFACE_FAR outside (eta 1 to 1e-6). A smooth
        ramp is far easier for the grid than eta's own sharp step: on the quick protocol's
        sphere the normals come out 0.3 deg off at the median instead of 1.4 (README).
        With the ramp output, o is fitted to -2 phi / width instead (`_fit_ramp`). `rate`
        scales the Adam rates; `device` as _distil's."""
        pts = np.asarray(pts, np.float64).reshape(-1, 3)
        phi = np.asarray(phi, np.float64).reshape(-1)
        if self.config.output == "ramp":
            lr = (RAMP_LR[0] * rate, RAMP_LR[1] * rate)
            self._fit_ramp(
                pts, phi, grad_phi, eta, width, iterations, batch, seed, lr, progress, device
            )
            return
        # the interior's output: eta there is the index (as saturated as the far side if the
        # index is at eta_max; unused when there is no interior)
        lim = 1.0 / (1.0 + math.exp(SURFACE_FAR))
        frac = min(max((eta - 1.0) / (self.config.eta_max - 1.0), lim), 1.0 - lim)
        t_in = math.log(frac / (1.0 - frac))
        far = np.where(phi > 0, SURFACE_FAR, t_in)
        t = np.tanh(SURFACE_SLOPE / width * phi / far)
        target = -far * t
        grad_target = (-SURFACE_SLOPE / width * (1 - t * t))[:, None] * grad_phi

        # where the target is flat, past it is as good: air only needs o low enough, glass
        # high enough, and the grid's effort goes to the surface
        flat = np.abs(t) > 0.99
        outside = phi > 0

        def residual(i, o, og):
            n = len(i)
            r = o - target[i]
            past = flat[i] & ((r < 0) == outside[i])
            r = np.where(past, 0.0, r)
            mu = 2.0 * SURFACE_GRAD_WEIGHT * width**2 / n * (og - grad_target[i])
            return 2.0 / n * r, np.ones(n), mu

        lr = (SURFACE_LR[0] * rate, SURFACE_LR[1] * rate)
        self._distil(pts, residual, iterations, batch, seed, lr, progress, device)

    def _fit_ramp(
        self, pts, phi, grad_phi, eta, width, iterations, batch, seed, lr, progress, device
    ) -> None:
        """fit_surface for the ramp output: o = -2 phi / width, so that eta follows the
        level set's ramp S(1/2 - phi / width) exactly, up to o_in inside (eta there is the
        index) and down to RAMP_FLOOR outside; past those only the side counts."""
        # at eta_max inside (the index there), o is held above the ramp's top as it is held
        # below its foot outside: eta is then exactly flat, where a lower index leaves
        # the interior on the ramp's shoulder, whose noise bends every ray crossing it
        frac = (eta - 1.0) / (self.config.eta_max - 1.0)
        o_in = 2.0 * _smoother_inverse(frac) - 1.0 if frac < 1.0 - 1e-9 else -RAMP_FLOOR
        lin = -2.0 * phi / width
        target = np.clip(lin, RAMP_FLOOR, o_in)
        low, high = lin <= RAMP_FLOOR, lin >= o_in
        ramp = ~(low | high)
        grad_target = (-2.0 / width) * grad_phi

        def residual(i, o, og):
            n = len(i)
            r = o - target[i]
            past = (low[i] & (r < 0)) | (high[i] & (r > 0))
            r = np.where(past, 0.0, r)
            mu = (2.0 * RAMP_GRAD_WEIGHT * width**2 / n) * (og - grad_target[i])
            mu[~ramp[i]] = 0.0
            return 2.0 / n * r, np.ones(n), mu

        self._distil(pts, residual, iterations, batch, seed, lr, progress, device)

    def regularizer(self, params: np.ndarray) -> tuple[float, np.ndarray]:
        """Mean over fixed points where the window is 1 of (cell * d eta / dx_a)^2 over the axes,
        cell = the finest level's cell (a discrete squared gradient in the voxel grid's
        units), and its gradient with respect to params. The points (a jittered 16^3
        lattice, fixed seed) do not change between calls: a resumed fit repeats exactly."""
        p = np.asarray(params, np.float64)
        pts = self._regularizer_points()
        o, og, _, tape = self.forward2(pts, None, p, hessian=False)
        g0, g1, g2 = self._output(o)
        win, gw, _ = _window_hessian(self.box, pts)
        ge = g0[:, None] * gw + (win * g1)[:, None] * og
        scale = (float(self.box.size.min()) / self.config.resolutions[-1]) ** 2 / 3 / len(pts)
        # d|ge|^2 = 2 ge . d ge: the mu-derivative terms with mu = ge held fixed
        om = np.einsum("nd,nd->n", ge, og)
        mw = np.einsum("nd,nd->n", ge, gw)
        ob = 2 * scale * (mw * g1 + win * g2 * om)
        omb = 2 * scale * win * g1
        return float(scale * (ge * ge).sum()), self.reverse2(ob, omb, ge, tape, p)

    def _regularizer_points(self) -> np.ndarray:
        if getattr(self, "_reg_pts", None) is None:
            m = 16
            rng = np.random.default_rng(12345)
            cells = np.stack(np.meshgrid(*[np.arange(m)] * 3, indexing="ij"), -1).reshape(-1, 3)
            u = (cells + rng.uniform(size=cells.shape)) / m
            # where the window is 1: the learned field's oscillation, not the window's ramp
            lo = np.asarray(self.box.lo) + 2 * self.box.margin
            self._reg_pts = lo + u * (self.box.size - 4 * self.box.margin)
        return self._reg_pts

    # --- files ------------------------------------------------------------------------------
    def save(self, path) -> None:
        """Write an .npz (kind, config as JSON, box lo/hi/margin, params) atomically."""
        path = Path(path)
        with atomic_path(path) as tmp, tmp.open("wb") as f:
            np.savez_compressed(
                f,
                kind="hashgrid",
                config=json.dumps(asdict(self.config)),
                lo=np.asarray(self.box.lo, np.float64),
                hi=np.asarray(self.box.hi, np.float64),
                margin=self.box.margin,
                params=self.params_vec,
            )

    @classmethod
    def load(cls, path) -> HashGridField:
        """Read a field written by save(); every problem is a ClrefractError naming the file."""
        path = Path(path)
        if not path.is_file():
            raise ClrefractError(f"{path}: hash grid file not found")
        keys = ("config", "lo", "hi", "margin", "params")
        try:
            with np.load(path, allow_pickle=False) as z:
                missing = [k for k in ("kind", *keys) if k not in z.files]
                if missing:
                    raise ClrefractError(
                        f"{path}: not a hash grid file (missing {', '.join(missing)})"
                    )
                kind = str(z["kind"])
                if kind != "hashgrid":
                    raise ClrefractError(f"{path}: holds a {kind!r} field, not a hash grid")
                config = json.loads(str(z["config"]))
                lo, hi = np.asarray(z["lo"], np.float64), np.asarray(z["hi"], np.float64)
                margin = float(z["margin"])
                params = np.asarray(z["params"], np.float64)
        except ClrefractError:
            raise
        except Exception as exc:  # noqa: BLE001 - any unreadable file is the user's to fix
            raise ClrefractError(f"{path}: cannot read hash grid ({exc})") from None
        if lo.shape != (3,) or hi.shape != (3,):
            raise ClrefractError(
                f"{path}: box lo and hi must have 3 entries, got shapes {lo.shape} and {hi.shape}"
            )
        try:
            if not isinstance(config, dict):
                raise ClrefractError("config is not a JSON object")
            cfg = HashGridConfig.from_dict(config)
            box = Box(tuple(lo.tolist()), tuple(hi.tolist()), margin)
            return cls(cfg, box, params)
        except ClrefractError as exc:
            raise ClrefractError(f"{path}: {exc}") from None
        except TypeError as exc:
            raise ClrefractError(f"{path}: bad hash grid config ({exc})") from None
