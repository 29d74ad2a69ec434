"""Level-set index field: a solid of one index n bounded by the zero set of a signed distance.

eta = 1 + W (n - 1) S(1/2 - phi / w): phi is a tricubic B-spline on a node grid (the layout
of fields/voxel.py, "bspline"; negative inside, in mm), S the C2 quintic smoothstep, w the
interface width and W the box window. The surface is as sharp as w whatever the grid
spacing, which a grid of eta values cannot be: a 64^3 grid of phi holds a glass sphere that
a 256^3 grid of eta barely does. It is the shape of the analytic solids (SmoothSolid), so a
phi equal to their signed distance reproduces them.

Parameters (fd in the kernels): the phi nodes in C order, then n; fp holds w (data, so that
one program serves every width). The backward pass (voxel_adjoint.cl) splats phi's gradient
like the B-spline grid's and sums n's per work-item (a shared parameter). Only the band
|phi| < w/2 has a gradient: nothing else can move the surface.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import ClrefractError
from ..imageio import atomic_path
from .base import Box, Field, box_window, smoother, smoother_d
from .voxel import grid_defines, grid_nodes, grid_shape, interpolate


class LevelSetField(Field):
    """A solid of index `eta` whose surface is the zero set of `phi` (node values, mm,
    negative inside), ramped across `width` mm."""

    kind = "levelset"
    source = "field_voxel.cl"
    adjoint_source = "voxel_adjoint.cl"

    def __init__(
        self,
        phi,
        box: Box | None = None,
        eta: float = 1.5,
        width: float = 1.0,
        eta_max: float | None = None,
    ):
        phi = np.array(phi, dtype=np.float64, order="C")
        if phi.ndim != 3 or min(phi.shape) < 4:
            raise ClrefractError(
                f"level set needs a 3-D phi with at least 4 nodes per axis, got {phi.shape}"
            )
        if not (np.isfinite(width) and width > 0):
            raise ClrefractError(f"level-set interface width must be positive, got {width!r}")
        self.box = box or Box()
        self.width = float(width)
        self.eta_bound = None if eta_max is None else float(eta_max)
        self.phi = phi
        self.eta = 1.0
        self.set_data(np.concatenate([phi.ravel(), [eta]]))

    # --- what the tracer needs ---------------------------------------------------------------
    @property
    def shape(self) -> tuple[int, int, int]:
        return tuple(int(n) for n in self.phi.shape)

    @property
    def values(self) -> np.ndarray:  # the node grid, as for voxel grids (its shape)
        return self.phi

    @property
    def spacing(self) -> np.ndarray:
        return self.box.size / (np.asarray(self.phi.shape) - 1)

    def defines(self) -> dict:
        return {
            **grid_defines(self.shape, "bspline"),
            "VOX_LEVELSET": 1,
        }

    def params(self) -> np.ndarray:
        return np.array([self.width])

    def nodes(self) -> tuple[int, int, int]:
        return self.shape

    def data(self) -> np.ndarray:
        return np.concatenate([self.phi.ravel(), [self.eta]])

    def uses_window(self) -> bool:
        return True

    @property
    def eta_max(self) -> float:
        return float(self.eta)

    @property
    def suggested_step(self) -> float:
        """A quarter of the interface: coarser steps jump over it (see bench_sharp_interface)."""
        return self.width / 4

    def sdf(self, pts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """phi (mm, negative inside) and its gradient at points, as a solid's truth gives."""
        return interpolate(self.phi, self.box, np.asarray(pts, np.float64), "bspline")

    def eval(self, pts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        pts = np.asarray(pts, np.float64)
        g, dg = self.sdf(pts)
        s = 0.5 - g / self.width
        dn = self.eta - 1.0
        f = dn * smoother(s)
        df = (-dn * smoother_d(s) / self.width)[:, None] * dg
        w, dw = box_window(self.box, pts)
        return 1.0 + w * f, dw * f[:, None] + w[:, None] * df

    def to_dict(self) -> dict:
        return {
            "kind": self.kind,
            "shape": list(self.shape),
            "box": self.box.to_dict(),
            "eta": self.eta,
            "width": self.width,
        }

    # --- fitting ----------------------------------------------------------------------------
    @property
    def n_shared(self) -> int:
        return 1  # n: every ray's gradient sums into it

    @property
    def shared_offset(self) -> int:
        return self.phi.size

    def set_data(self, params: np.ndarray) -> None:
        """Take new parameters (phi nodes, then n). With an eta_max bound, n is first
        projected onto [1, eta_max] in place."""
        params = np.asarray(params)
        if params.shape != (self.phi.size + 1,):
            raise ClrefractError(
                f"level set has {self.phi.size + 1} parameters, got shape {params.shape}"
            )
        if not np.all(np.isfinite(params)):
            raise ClrefractError("level-set parameters contain non-finite values")
        hi = self.eta_bound if self.eta_bound is not None else np.inf
        if params.flags.writeable:
            params[-1] = min(max(params[-1], 1.0), hi)
        eta = float(params[-1])
        if not 1.0 <= eta <= hi:
            raise ClrefractError(f"level-set index must lie in [1, {hi}], got {eta}")
        self.phi = np.array(params[:-1], np.float64).reshape(self.phi.shape)
        self.eta = eta

    def param_groups(self, lr_phi: float = 0.00125, lr_index: float = 3e-4, **_) -> list:
        from ..adam import ParamGroup

        n = self.phi.size
        return [ParamGroup("phi", 0, n, lr_phi), ParamGroup("eta", n, n + 1, lr_index)]

    def regularizer(self, params: np.ndarray) -> tuple[float, np.ndarray]:
        """Eikonal penalty mean((|grad phi|^2 - 1)^2) over the interior nodes (central
        differences), and its gradient: it keeps phi a distance, so the interface keeps its
        width w while the surface moves."""
        phi = np.asarray(params[:-1], np.float64).reshape(self.phi.shape)
        h = self.spacing

        def shifted(ax: int, side: slice) -> tuple:  # interior nodes' neighbours along ax
            sl = [slice(1, -1)] * 3
            sl[ax] = side
            return tuple(sl)

        up, down = slice(2, None), slice(0, -2)
        g = [(phi[shifted(a, up)] - phi[shifted(a, down)]) / (2 * h[a]) for a in range(3)]
        r = g[0] ** 2 + g[1] ** 2 + g[2] ** 2 - 1.0
        grad = np.zeros_like(phi)
        for a in range(3):
            c = 4 * r * g[a] / (2 * h[a]) / r.size
            grad[shifted(a, up)] += c
            grad[shifted(a, down)] -= c
        return float((r * r).mean()), np.concatenate([grad.ravel(), [0.0]])

    def node_points(self) -> np.ndarray:
        return grid_nodes(self.box, self.shape)

    @classmethod
    def from_sdf(
        cls, sdf, box: Box, res, eta: float, width: float = 1.0, eta_max: float | None = None
    ) -> LevelSetField:
        """phi sampled from a signed distance function sdf(pts) -> (n,) at the nodes of a
        res^3 grid over box (the samples are the control points)."""
        shape = grid_shape(res)
        pts = grid_nodes(box, shape)
        return cls(np.asarray(sdf(pts), np.float64).reshape(shape), box, eta, width, eta_max)

    # --- files ------------------------------------------------------------------------------
    def save(self, path) -> None:
        path = Path(path)
        with atomic_path(path) as tmp, tmp.open("wb") as f:
            np.savez_compressed(
                f,
                kind=self.kind,
                phi=self.phi,
                eta=self.eta,
                width=self.width,
                lo=np.asarray(self.box.lo),
                hi=np.asarray(self.box.hi),
                margin=self.box.margin,
            )

    @classmethod
    def load(cls, path) -> LevelSetField:
        path = Path(path)
        try:
            with np.load(path, allow_pickle=False) as z:
                missing = [
                    k for k in ("phi", "eta", "width", "lo", "hi", "margin") if k not in z.files
                ]
                if missing:
                    raise ClrefractError(
                        f"{path}: not a level-set file (missing {', '.join(missing)})"
                    )
                phi, eta, width = z["phi"], float(z["eta"]), float(z["width"])
                box = Box(tuple(z["lo"].tolist()), tuple(z["hi"].tolist()), float(z["margin"]))
        except ClrefractError:
            raise
        except Exception as exc:  # noqa: BLE001 - any unreadable file is the user's to fix
            raise ClrefractError(f"{path}: cannot read level-set field ({exc})") from None
        try:
            return cls(phi, box, eta, width)
        except ClrefractError as exc:
            raise ClrefractError(f"{path}: {exc}") from None
