"""Interface fields: a solid of one index eta behind a sharp surface, the zero set of phi
(negative inside, mm), air outside. Traced by refraction at the surface (interface.py,
kernels_cl/interface.cl), not by steps through a continuous eta: a glass object costs a few
crossings a ray, however sharp its surface.

`InterfaceField` holds phi as a tricubic B-spline on a node grid, the parameters of a level
set (fields/levelset.py: the phi nodes in C order, then eta), so the level set's starts,
smoothness penalty and files serve it. `SphereInterface` is the closed-form sphere, the
oracle of the tests.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import ClrefractError
from ..imageio import atomic_path
from .base import Box, Field
from .levelset import LevelSetField
from .voxel import grid_defines


def zero_set(sdf, b: Box, res: int):
    """Marching cubes of sdf(pts)[0] at 0 on a res^3 grid over box b: (vertices, faces), or
    None where it has no zero set there."""
    from skimage.measure import marching_cubes

    axes = [np.linspace(b.lo[k], b.hi[k], res) for k in range(3)]
    pts = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    vol = np.concatenate([sdf(pts[a : a + 262144])[0] for a in range(0, len(pts), 262144)]).reshape(
        (res,) * 3
    )
    if not vol.min() < 0 < vol.max():
        return None
    spacing = tuple((b.hi[k] - b.lo[k]) / (res - 1) for k in range(3))
    verts, faces, _, _ = marching_cubes(vol, 0.0, spacing=spacing)
    return verts + np.asarray(b.lo), faces


def sharp_eta(phi: np.ndarray, eta: float) -> tuple[np.ndarray, np.ndarray]:
    """eta of a solid with a zero-width surface at points of signed distance phi (the
    gradient is zero almost everywhere)."""
    return np.where(phi < 0, eta, 1.0), np.zeros((len(phi), 3))


class ConstantInterior:
    """One index inside the surface (fields/interior.py grades it)."""

    def index(self, pts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The index inside (n,) and its gradient (n, 3), wherever pts lie."""
        n = len(pts)
        return np.full(n, float(self.eta)), np.zeros((n, 3))


class InterfaceField(ConstantInterior, LevelSetField):
    """A solid of index `eta` inside the zero set of `phi` (B-spline node values, mm). The
    level set's `width` only sets the band its hull start smooths over."""

    kind = "interface"
    traced_by = "interface"
    source = ""
    adjoint_source = None

    def defines(self) -> dict:
        return {**grid_defines(self.shape, "bspline"), "SDF_GRID": 1}

    def eval(self, pts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return sharp_eta(self.sdf(pts)[0], self.eta)

    def lipschitz(self) -> float:
        """A bound on |grad phi|: along each axis the spline's derivative is a quadratic
        B-spline of the nodes' differences over the spacing, so at most their largest."""
        h = self.spacing
        m = [np.abs(np.diff(self.phi, axis=a)).max() / h[a] for a in range(3)]
        return float(np.sqrt(np.sum(np.square(m)))) or 1.0

    def min_step(self) -> float:
        """The shortest step of the march: surfaces closer than this along a ray are one."""
        return float(np.min(self.spacing)) / 16

    def surface(self, box: Box | None = None, res: int = 128):
        """The zero set of phi as a mesh (vertices, faces): marching cubes on a res^3 grid
        over the field's box, where phi is defined (`box` is not used); None if empty."""
        return zero_set(self.sdf, self.box, res)

    @classmethod
    def from_levelset(cls, ls: LevelSetField) -> InterfaceField:
        return cls(ls.phi.copy(), ls.box, ls.eta, ls.width, ls.eta_bound)


class SphereInterface(ConstantInterior, Field):
    """A glass sphere of radius `radius` about `centre` with a sharp surface, in `box`."""

    kind = "interface-sphere"
    traced_by = "interface"

    def __init__(self, centre=(0.0, 0.0, 0.0), radius: float = 20.0, eta: float = 1.5, box=None):
        self.box = box or Box()
        self.set_data(np.array([*centre, radius, eta], np.float64))

    def set_data(self, params) -> None:
        params = np.asarray(params, np.float64)
        if params.shape != (5,) or not np.all(np.isfinite(params)):
            raise ClrefractError(f"a sphere has 5 finite parameters, got {params!r}")
        if params[3] <= 0 or params[4] < 1:
            raise ClrefractError(f"sphere radius must be > 0 and index >= 1, got {params[3:]}")
        self._p = params.copy()

    def data(self) -> np.ndarray:
        return self._p.copy()

    def params(self) -> np.ndarray:
        return np.zeros(1)

    def defines(self) -> dict:
        return {"SDF_SPHERE": 1}

    @property
    def eta(self) -> float:
        return float(self._p[4])

    @property
    def eta_max(self) -> float:
        return self.eta

    @property
    def shared_offset(self) -> int:
        return 4

    def sdf(self, pts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        r = np.asarray(pts, np.float64) - self._p[:3]
        length = np.linalg.norm(r, axis=1)
        return length - self._p[3], r / np.maximum(length, 1e-300)[:, None]

    def eval(self, pts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return sharp_eta(self.sdf(pts)[0], self.eta)

    def lipschitz(self) -> float:
        return 1.0

    def min_step(self) -> float:
        return float(self._p[3]) * 1e-3

    def surface(self, box: Box | None = None, res: int = 128):
        """Marching cubes of the sphere on a res^3 grid over the field's box."""
        return zero_set(self.sdf, self.box, res)

    def uses_window(self) -> bool:
        return True

    def to_dict(self) -> dict:
        c = self._p
        return {"kind": self.kind, "centre": c[:3].tolist(), "radius": c[3], "eta": c[4]}


# a plane's normal turns (radians) as far as its face moves (mm) at this distance from the
# centre: on the quick prism, Adam at 0.02 mm and 0.002 rad took the start from 32.0 to 41.5 dB
# (the fit's rate: kinds.POLYTOPE_DEFAULTS)
NORMAL_ARM = 10.0


class PolytopeInterface(ConstantInterior, Field):
    """A convex solid of index `eta` bounded by planes: phi(x) = max_j n_j . (x - centre) -
    d_j, with n_j = a_j / |a_j| (`planes`: rows (a_j, d_j), mm). Flat faces and sharp edges
    held exactly, which a spline of any node count smooths; sharp glass of a few faces (a
    prism, a cube, a cut stone) is a few dozen parameters. With `rounding` k > 0 (mm), the
    max becomes k log sum_j exp(v_j / k): the same faces, edges rounded over about k."""

    kind = "polytope"
    traced_by = "interface"

    @property
    def surface_rule(self) -> str:
        if self.rounding > 0:
            return "marching cubes of phi at 0 (the rounded faces)"
        return "the faces, where the planes meet"

    def __init__(
        self,
        planes,
        eta: float,
        box: Box,
        centre=None,
        eta_max: float | None = None,
        rounding: float = 0.0,
    ):
        self.box = box
        if not (np.isfinite(rounding) and rounding >= 0):
            raise ClrefractError(f"a polytope's rounding must be >= 0 mm, got {rounding!r}")
        self.rounding = float(rounding)
        self.centre = np.asarray(
            (np.asarray(box.lo) + np.asarray(box.hi)) / 2 if centre is None else centre, np.float64
        )
        self.eta_bound = eta_max
        planes = np.asarray(planes, np.float64)
        if planes.ndim != 2 or planes.shape[1] != 4 or len(planes) < 4:
            raise ClrefractError(f"a polytope needs at least 4 planes (a, d), got {planes.shape}")
        self.set_data(np.append(planes.ravel(), eta))

    @property
    def n_planes(self) -> int:
        return len(self._p) // 4

    @property
    def planes(self) -> np.ndarray:
        return self._p[:-1].reshape(-1, 4)

    def set_data(self, params) -> None:
        params = np.asarray(params, np.float64)
        if getattr(self, "_p", None) is not None and params.shape != self._p.shape:
            raise ClrefractError(f"polytope has {len(self._p)} parameters, got {params.shape}")
        if not np.all(np.isfinite(params)):
            raise ClrefractError("polytope parameters contain non-finite values")
        a = params[:-1].reshape(-1, 4)[:, :3]
        if np.any(np.linalg.norm(a, axis=1) == 0):
            raise ClrefractError("a polytope's plane has a zero normal")
        hi = self.eta_bound if self.eta_bound is not None else np.inf
        params = params.copy()
        params[-1] = min(max(params[-1], 1.0), hi)
        self._p = params

    def data(self) -> np.ndarray:
        return self._p.copy()

    def params(self) -> np.ndarray:
        return np.zeros(1)

    def defines(self) -> dict:
        c = self.centre
        soft = {"POLY_SOFT": repr(self.rounding)} if self.rounding > 0 else {}
        return {
            "SDF_PLANES": self.n_planes,
            "POLY_CX": repr(float(c[0])),
            "POLY_CY": repr(float(c[1])),
            "POLY_CZ": repr(float(c[2])),
            **soft,
        }

    @property
    def eta(self) -> float:
        return float(self._p[-1])

    @property
    def eta_max(self) -> float:
        return self.eta

    @property
    def n_shared(self) -> int:
        return 1

    @property
    def shared_offset(self) -> int:
        return len(self._p) - 1

    def normals(self) -> np.ndarray:
        a = self.planes[:, :3]
        return a / np.linalg.norm(a, axis=1, keepdims=True)

    def sdf(self, pts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        n = self.normals()
        v = (np.asarray(pts, np.float64) - self.centre) @ n.T - self.planes[:, 3]
        if self.rounding > 0:
            k = self.rounding
            m = v.max(axis=1, keepdims=True)
            e = np.exp((v - m) / k)
            s = e.sum(axis=1, keepdims=True)
            return (m + k * np.log(s))[:, 0], (e / s) @ n
        k = np.argmax(v, axis=1)
        return v[np.arange(len(v)), k], n[k]

    def eval(self, pts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return sharp_eta(self.sdf(pts)[0], self.eta)

    def lipschitz(self) -> float:
        return 1.0

    def min_step(self) -> float:
        return float(np.min(self.box.size)) * 1e-4

    def uses_window(self) -> bool:
        return True

    def surface(self, box: Box | None = None, res: int = 128):
        """The faces as a triangle mesh (vertices, faces), from the planes' intersection
        (scipy's HalfspaceIntersection about the centre); None if the solid is empty. Rounded,
        marching cubes of phi on a res^3 grid over the field's box."""
        from scipy.spatial import ConvexHull, HalfspaceIntersection

        if self.rounding > 0:
            return zero_set(self.sdf, self.box, res)
        n = self.normals()
        halfspaces = np.column_stack([n, -self.planes[:, 3]])  # n . r - d <= 0
        try:
            inner = HalfspaceIntersection(halfspaces, np.zeros(3)).intersections
            hull = ConvexHull(inner)
        except Exception:  # noqa: BLE001 - the centre outside the solid, or a flat solid
            return None
        return hull.points + self.centre, hull.simplices

    # --- fitting ----------------------------------------------------------------------------
    def param_groups(self, lr_phi: float = 0.01, lr_index: float = 1e-3, **_) -> list:
        """The planes' offsets move lr_phi mm a step and their normals as far at
        NORMAL_ARM mm from the centre; the index lr_index."""
        from ..adam import ParamGroup

        k = self.n_planes
        groups = []
        for j in range(k):
            groups += [
                ParamGroup(f"normal{j}", 4 * j, 4 * j + 3, lr_phi / NORMAL_ARM),
                ParamGroup(f"offset{j}", 4 * j + 3, 4 * j + 4, lr_phi),
            ]
        return [*groups, ParamGroup("eta", 4 * k, 4 * k + 1, lr_index)]

    def regularizer(self, params: np.ndarray) -> tuple[float, np.ndarray]:
        return 0.0, np.zeros(len(params))

    def save(self, path) -> None:
        path = Path(path)
        with atomic_path(path) as tmp, tmp.open("wb") as f:
            np.savez_compressed(
                f,
                kind=self.kind,
                planes=self.planes,
                eta=self.eta,
                centre=self.centre,
                rounding=self.rounding,
                lo=np.asarray(self.box.lo),
                hi=np.asarray(self.box.hi),
                margin=self.box.margin,
            )

    @classmethod
    def load(cls, path) -> PolytopeInterface:
        path = Path(path)
        keys = ("planes", "eta", "centre", "lo", "hi", "margin")
        with np.load(path, allow_pickle=False) as z:
            missing = [k for k in keys if k not in z.files]
            if missing:
                raise ClrefractError(f"{path}: not a polytope file (missing {', '.join(missing)})")
            box = Box(tuple(z["lo"].tolist()), tuple(z["hi"].tolist()), float(z["margin"]))
            try:
                rounding = float(z["rounding"]) if "rounding" in z.files else 0.0
                return cls(z["planes"], float(z["eta"]), box, z["centre"], rounding=rounding)
            except ClrefractError as exc:
                raise ClrefractError(f"{path}: {exc}") from None

    def to_dict(self) -> dict:
        return {
            "kind": self.kind,
            "planes": self.planes.tolist(),
            "eta": self.eta,
            "rounding": self.rounding,
            "centre": self.centre.tolist(),
            "box": self.box.to_dict(),
        }
