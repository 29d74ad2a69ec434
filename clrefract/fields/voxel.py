"""Voxel-grid index field: node values of eta, trilinear (C0), smoothstep (C1) or tricubic
B-spline (C2) interpolation.

Layout, shared with kernels_cl/field_voxel.cl and kernels_cl/voxel_adjoint.cl:
- values[i, j, k] belongs to the node box.lo + (i hx, j hy, k hz), h = box.size / (n - 1):
  node 0 lies on the low wall and node n - 1 on the high wall of each axis.
- On the device the values are flattened in NumPy C order (x slowest):
  fd[(i * ny + j) * nz + k] = values[i, j, k]; fp holds only the geometry (the box and the
  node counts, Field.kernel_params).
- Along each axis u = (x - lo) / h is clamped onto [0, n - 1] (a clamped coordinate has zero
  derivative), the cell is i = min(floor(u), n - 2) and t = u - i in [0, 1].
- "trilinear" and "smoothstep" interpolate the cell's 2 nodes per axis with weights
  1 - s(t), s(t): s(t) = t (trilinear, C0) or s(t) = 3t^2 - 2t^3 (smoothstep, C1: continuous
  gradient, non-zero Hessian diagonal). Trilinear has Dirac second derivatives on the cell
  faces that a pointwise adjoint misses; smoothstep's price: s'(0) = s'(1) = 0, so the
  derivative across every node plane is zero and a linear ramp of nodes becomes smooth
  terraces (trilinear reproduces it exactly).
- "bspline" blends the 4 nodes i-1 .. i+2 per axis (64 per point) with the uniform cubic
  B-spline weights (1-t)^3/6, (3t^3 - 6t^2 + 4)/6, (-3t^3 + 3t^2 + 3t + 1)/6, t^3/6; node
  indices outside the grid are clamped onto it (the border node repeats). C2, and it
  reproduces linear functions exactly away from the border cells. Its values are control
  points, not interpolated values: g at a node is (v[i-1] + 4 v[i] + v[i+1]) / 6 per axis, so
  a grid sampled from a field (from_field: the plain node samples, no prefilter) is that
  field slightly smoothed (by a kernel of width about one cell). The weights are non-negative
  and sum to 1, so g stays within the range of the values.
- eta = 1 + W (g - 1), W the box window (1 inside, 0 within the margin of the walls), so rays
  leave the box in straight lines. The gradient is the exact derivative of this expression.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import ClrefractError
from ..imageio import atomic_path
from .base import Box, Field, box_window

INTERPS = ("trilinear", "smoothstep", "bspline")
_CHUNK = 1 << 18  # points per block in the NumPy reference (bounds temporary memory)


def _axis(x, lo, h, n, smooth):
    """Cell index c in [0, n-2], weight s of the high node and ds/dx along one axis."""
    u = (x - lo) / h
    uc = np.clip(u, 0.0, n - 1.0)
    c = np.clip(np.floor(uc).astype(np.int64), 0, n - 2)
    t = uc - c
    if smooth:
        s, ds = t * t * (3 - 2 * t), 6 * t * (1 - t) / h
    else:
        s, ds = t, np.full_like(t, 1.0 / h)
    return c, s, np.where(u == uc, ds, 0.0)


def bspline_weights(t):
    """Uniform cubic B-spline weights of nodes c-1 .. c+2 at t in [0, 1] (arrays (4, n)) and
    their first and second derivatives in t; the same expressions as the kernels."""
    t = np.asarray(t, np.float64)
    s = 1 - t
    t2 = t * t
    t3 = t2 * t
    r6 = 1 / 6
    w = np.stack(
        [s * s * s * r6, (3 * t3 - 6 * t2 + 4) * r6, (-3 * t3 + 3 * t2 + 3 * t + 1) * r6, t3 * r6]
    )
    d = np.stack([-0.5 * s * s, 1.5 * t2 - 2 * t, -1.5 * t2 + t + 0.5, 0.5 * t2])
    dd = np.stack([s, 3 * t - 2, 1 - 3 * t, t])
    return w, d, dd


def _axis4(x, lo, h, n):
    """B-spline along one axis: clamped node indices (4, n), weights, d/dx and d2/dx2."""
    u = (x - lo) / h
    uc = np.clip(u, 0.0, n - 1.0)
    c = np.clip(np.floor(uc).astype(np.int64), 0, n - 2)
    w, d, dd = bspline_weights(uc - c)
    d1 = np.where(u == uc, 1.0 / h, 0.0)  # a clamped coordinate has zero derivative
    idx = np.clip(c[None, :] + np.arange(-1, 3)[:, None], 0, n - 1)
    return idx, w, d * d1, dd * (d1 / h)


def _lerp(a, b, s):
    return a + (b - a) * s


def _interp_bspline(values, lo, h, p):
    """Tricubic B-spline g and grad g at points p (n, 3); sums over z, then y, then x, in
    the kernels' order (they fold the weights of clamped taps at the z border together)."""
    n = values.shape
    ix, wx, dx, _ = _axis4(p[:, 0], lo[0], h[0], n[0])
    iy, wy, dy, _ = _axis4(p[:, 1], lo[1], h[1], n[1])
    iz, wz, dz, _ = _axis4(p[:, 2], lo[2], h[2], n[2])
    g = np.zeros(len(p))
    gx, gy, gz = np.zeros(len(p)), np.zeros(len(p)), np.zeros(len(p))
    for a in range(4):
        y0, y1, y2 = np.zeros(len(p)), np.zeros(len(p)), np.zeros(len(p))
        for b in range(4):
            q = [values[ix[a], iy[b], iz[c]] for c in range(4)]
            zc = q[0] * wz[0] + q[1] * wz[1] + q[2] * wz[2] + q[3] * wz[3]
            zd = q[0] * dz[0] + q[1] * dz[1] + q[2] * dz[2] + q[3] * dz[3]
            y0 += wy[b] * zc
            y1 += dy[b] * zc
            y2 += wy[b] * zd
        g += wx[a] * y0
        gx += dx[a] * y0
        gy += wx[a] * y1
        gz += wx[a] * y2
    return g, np.stack([gx, gy, gz], axis=1)


def interpolate(values, box: Box, pts, interp: str = "trilinear"):
    """The interpolant g of node `values` (no window) and its gradient at points (n, 3);
    interp is one of INTERPS."""
    if interp not in INTERPS:
        raise ClrefractError(f"voxel interp must be one of {INTERPS}, got {interp!r}")
    pts = np.asarray(pts, np.float64)
    lo, h = np.asarray(box.lo, float), box.size / (np.asarray(values.shape) - 1)
    g = np.empty(len(pts))
    grad = np.empty((len(pts), 3))
    smooth = interp == "smoothstep"
    for a in range(0, len(pts), _CHUNK):
        p = pts[a : a + _CHUNK]
        if interp == "bspline":
            g[a : a + _CHUNK], grad[a : a + _CHUNK] = _interp_bspline(values, lo, h, p)
            continue
        i, sx, dsx = _axis(p[:, 0], lo[0], h[0], values.shape[0], smooth)
        j, sy, dsy = _axis(p[:, 1], lo[1], h[1], values.shape[1], smooth)
        k, sz, dsz = _axis(p[:, 2], lo[2], h[2], values.shape[2], smooth)
        v = {
            (di, dj, dk): values[i + di, j + dj, k + dk]
            for di in (0, 1)
            for dj in (0, 1)
            for dk in (0, 1)
        }
        # along z, then y, then x; the same order of operations as the kernel
        v00, v01 = _lerp(v[0, 0, 0], v[0, 0, 1], sz), _lerp(v[0, 1, 0], v[0, 1, 1], sz)
        v10, v11 = _lerp(v[1, 0, 0], v[1, 0, 1], sz), _lerp(v[1, 1, 0], v[1, 1, 1], sz)
        v0, v1 = _lerp(v00, v01, sy), _lerp(v10, v11, sy)
        z0 = _lerp(v[0, 0, 1] - v[0, 0, 0], v[0, 1, 1] - v[0, 1, 0], sy)
        z1 = _lerp(v[1, 0, 1] - v[1, 0, 0], v[1, 1, 1] - v[1, 1, 0], sy)
        g[a : a + _CHUNK] = _lerp(v0, v1, sx)
        grad[a : a + _CHUNK, 0] = (v1 - v0) * dsx
        grad[a : a + _CHUNK, 1] = _lerp(v01 - v00, v11 - v10, sx) * dsy
        grad[a : a + _CHUNK, 2] = _lerp(z0, z1, sx) * dsz
    return g, grad


def grid_defines(shape, interp: str) -> dict:
    """Build defines of a node grid (field_voxel.cl) of this interpolation; of its shape only
    whether a row along z holds the 4 nodes of a vector read (the node counts are data:
    Field.nodes)."""
    return {
        "FIELD_VOXEL": 1,
        "VOX_SMOOTH": int(interp == "smoothstep"),
        "VOX_BSPLINE": int(interp == "bspline"),
        "VOX_ZVEC": int(shape[2] >= 4),
    }


def _check_values(values: np.ndarray, bound: float | None) -> None:
    """Shape and finiteness always; the range [1, bound] where a bound is given."""
    if values.ndim != 3 or min(values.shape) < 2:
        raise ClrefractError(
            f"voxel values must be a 3-D array with at least 2 nodes per axis, got shape "
            f"{values.shape}"
        )
    if not np.all(np.isfinite(values)):
        bad = int(np.sum(~np.isfinite(values)))
        raise ClrefractError(f"voxel values contain {bad} non-finite entries")
    if bound is not None:
        _check_at_least_one(values)
        if values.max() > bound:
            raise ClrefractError(
                f"voxel values exceed eta_max {bound:.6g} (maximum {values.max():.6g})"
            )


def _check_at_least_one(values: np.ndarray) -> None:
    if values.min() < 1.0:
        raise ClrefractError(
            f"voxel values must be at least 1 (eta of the surrounding air), "
            f"minimum is {values.min():.6g}"
        )


class VoxelGrid(Field):
    """eta on a node-centred grid spanning `box` (see the module docstring for the layout).

    values: (nx, ny, nz) array of eta at the nodes, every entry finite.
    interp: "trilinear" (C0), "smoothstep" (C1) or "bspline" (C2; the values are control
            points, not interpolated values).
    eta_max: optional bound. With it the values must lie in [1, eta_max] and set_data()
             projects new values onto that range (a constrained fit); without it they are
             free (any finite value: finite-difference checks, experiments), but only grids
             with every value >= 1 can be saved. The eta_max property is the largest value.
    """

    kind = "voxel"
    source = "field_voxel.cl"
    adjoint_source = "voxel_adjoint.cl"

    def __init__(
        self,
        values,
        box: Box | None = None,
        interp: str = "smoothstep",
        eta_max: float | None = None,
    ):
        if interp not in INTERPS:
            raise ClrefractError(f"voxel interp must be one of {INTERPS}, got {interp!r}")
        if eta_max is not None and not (np.isfinite(eta_max) and eta_max >= 1):
            raise ClrefractError(f"voxel eta_max must be a finite number >= 1, got {eta_max!r}")
        self.values = np.array(values, dtype=np.float64, order="C")
        self.eta_bound = None if eta_max is None else float(eta_max)
        _check_values(self.values, self.eta_bound)
        self.box = box or Box()
        self.interp = interp

    # --- what the tracer needs ---------------------------------------------------------------
    @property
    def smooth(self) -> bool:
        return self.interp == "smoothstep"

    @property
    def shape(self) -> tuple[int, int, int]:
        return tuple(int(n) for n in self.values.shape)

    @property
    def spacing(self) -> np.ndarray:
        """Node spacing (hx, hy, hz) in mm."""
        return self.box.size / (np.asarray(self.values.shape) - 1)

    def defines(self) -> dict:
        return grid_defines(self.shape, self.interp)

    def params(self) -> np.ndarray:
        return np.zeros(1)

    def nodes(self) -> tuple[int, int, int]:
        return self.shape

    def data(self) -> np.ndarray:
        """The node values flattened in C order: index (i * ny + j) * nz + k."""
        return self.values.reshape(-1)

    def uses_window(self) -> bool:
        return True

    @property
    def eta_max(self) -> float:
        return float(self.values.max())

    @property
    def suggested_step(self) -> float:
        """Two steps or more per cell: a step does not jump over a cell's gradient."""
        return float(min(0.5, 0.5 * self.spacing.min()))

    def interpolant(self, pts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """g (n,) and grad g (n, 3) at points (n, 3): the interpolated nodes, no window."""
        return interpolate(self.values, self.box, pts, self.interp)

    def eval(self, pts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        pts = np.asarray(pts, np.float64)
        g, dg = self.interpolant(pts)
        w, dw = box_window(self.box, pts)
        g1 = g - 1.0
        return 1.0 + w * g1, dw * g1[:, None] + w[:, None] * dg

    def to_dict(self) -> dict:
        """Metadata only (the values live in the .npz file)."""
        return {
            "kind": self.kind,
            "interp": self.interp,
            "shape": list(self.shape),
            "box": self.box.to_dict(),
            "eta_max": self.eta_max,
            "eta_bound": self.eta_bound,
        }

    # --- fitting ----------------------------------------------------------------------------
    def set_data(self, params: np.ndarray) -> None:
        """Take new node values (flat, C order). With an eta_max bound they are first
        projected onto [1, eta_max] in place, so the optimiser's copy and the field agree."""
        if params.shape != (self.values.size,):
            raise ClrefractError(
                f"voxel grid has {self.values.size} values, got parameters of shape {params.shape}"
            )
        if not np.all(np.isfinite(params)):
            raise ClrefractError("voxel parameters contain non-finite values")
        if self.eta_bound is not None:
            np.clip(params, 1.0, self.eta_bound, out=params)
        self.values = np.array(params, np.float64).reshape(self.values.shape)

    def param_groups(self, lr: float, **_) -> list:
        from ..adam import ParamGroup

        return [ParamGroup("voxels", 0, self.values.size, lr)]

    def regularizer(self, params: np.ndarray) -> tuple[float, np.ndarray]:
        """Mean squared difference of neighbouring nodes over every grid edge (a discrete
        |grad eta|^2 in units of cells), and its gradient with respect to params."""
        v = np.asarray(params, np.float64).reshape(self.values.shape)
        grad = np.zeros_like(v)
        diffs = [np.diff(v, axis=ax) for ax in range(3)]
        count = sum(d.size for d in diffs)
        for ax, d in enumerate(diffs):
            lo, hi = [slice(None)] * 3, [slice(None)] * 3
            lo[ax], hi[ax] = slice(0, -1), slice(1, None)
            grad[tuple(lo)] -= 2 * d
            grad[tuple(hi)] += 2 * d
        return sum(float((d * d).sum()) for d in diffs) / count, grad.reshape(-1) / count

    def node_points(self, shape=None) -> np.ndarray:
        """Positions (n, 3) of the nodes of a grid of `shape` over this box, C order."""
        return grid_nodes(self.box, self.shape if shape is None else shape)

    def resampled_values(self, a: np.ndarray, res) -> np.ndarray:
        """An array `a` of node values on this grid (eta, Adam moments) resampled trilinearly
        onto a grid of res nodes per axis (int or 3 ints) over the same box. Trilinear even
        for smoothstep grids: it does not copy the smoothstep plateaus at the old nodes. For
        B-spline grids this resamples the control points, not the spline: exact for linear
        fields, otherwise the finer spline is a little less smooth than the old one (no exact
        knot insertion)."""
        shape = grid_shape(res)
        a = np.asarray(a, np.float64).reshape(self.values.shape)
        g, _ = interpolate(a, self.box, grid_nodes(self.box, shape), "trilinear")
        return g.reshape(shape)

    def resampled(self, res) -> VoxelGrid:
        """The same field on a grid of `res` nodes per axis (coarse-to-fine fitting)."""
        return VoxelGrid(
            self.resampled_values(self.values, res), self.box, self.interp, self.eta_bound
        )

    @classmethod
    def from_field(
        cls,
        field: Field,
        box: Box | None = None,
        res=64,
        interp: str = "smoothstep",
        eta_max: float | None = None,
    ) -> VoxelGrid:
        """Sample any field's eta (its NumPy reference) at the nodes of a res^3 grid
        (res: int or 3 ints). The samples become the node values whatever the interp: for
        "bspline" they are used as control points without a prefilter, so the grid's eta is
        the field smoothed over about a cell (it does not pass through the samples)."""
        box = box or Box()
        shape = grid_shape(res)
        pts = grid_nodes(box, shape)
        eta = np.concatenate(
            [field.eval(pts[a : a + _CHUNK])[0] for a in range(0, len(pts), _CHUNK)]
        )
        return cls(eta.reshape(shape), box, interp, eta_max)

    # --- files ------------------------------------------------------------------------------
    def save(self, path) -> None:
        """Write an .npz (values, box lo/hi/margin, interp, eta bound) atomically."""
        path = Path(path)
        try:
            _check_at_least_one(self.values)
        except ClrefractError as exc:
            raise ClrefractError(f"{path}: cannot save: {exc}") from None
        with atomic_path(path) as tmp, tmp.open("wb") as f:
            np.savez_compressed(
                f,
                kind="voxel",
                values=self.values,
                lo=np.asarray(self.box.lo),
                hi=np.asarray(self.box.hi),
                margin=self.box.margin,
                interp=self.interp,
                eta_bound=np.nan if self.eta_bound is None else self.eta_bound,
            )

    @classmethod
    def load(cls, path) -> VoxelGrid:
        """Read a grid written by save(); every problem is a ClrefractError naming the file."""
        path = Path(path)
        if not path.is_file():
            raise ClrefractError(f"{path}: voxel grid file not found")
        keys = ("values", "lo", "hi", "margin")
        try:
            with np.load(path, allow_pickle=False) as z:
                missing = [k for k in keys if k not in z.files]
                if missing:
                    raise ClrefractError(
                        f"{path}: not a voxel grid file (missing {', '.join(missing)})"
                    )
                kind = str(z["kind"]) if "kind" in z.files else "voxel"
                values = np.asarray(z["values"], np.float64)
                lo, hi = np.asarray(z["lo"], np.float64), np.asarray(z["hi"], np.float64)
                margin = float(z["margin"])
                interp = str(z["interp"]) if "interp" in z.files else "smoothstep"
                bound = float(z["eta_bound"]) if "eta_bound" in z.files else np.nan
        except ClrefractError:
            raise
        except Exception as exc:  # noqa: BLE001 - any unreadable file is the user's to fix
            raise ClrefractError(f"{path}: cannot read voxel grid ({exc})") from None
        if kind != "voxel":
            raise ClrefractError(f"{path}: holds a {kind!r} field, not a voxel grid")
        if lo.shape != (3,) or hi.shape != (3,):
            raise ClrefractError(
                f"{path}: box lo and hi must have 3 entries, got shapes {lo.shape} and {hi.shape}"
            )
        try:
            box = Box(tuple(lo.tolist()), tuple(hi.tolist()), margin)
            grid = cls(values, box, interp, None if np.isnan(bound) else bound)
            _check_at_least_one(grid.values)
            return grid
        except ClrefractError as exc:
            raise ClrefractError(f"{path}: {exc}") from None


def grid_shape(res) -> tuple[int, int, int]:
    shape = (int(res),) * 3 if np.ndim(res) == 0 else tuple(int(n) for n in res)
    if len(shape) != 3 or min(shape) < 2:
        raise ClrefractError(f"voxel resolution must be >= 2 nodes per axis, got {res!r}")
    return shape


def grid_nodes(box: Box, shape) -> np.ndarray:
    axes = [np.linspace(lo, hi, n) for lo, hi, n in zip(box.lo, box.hi, shape, strict=True)]
    return np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
