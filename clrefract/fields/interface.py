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

import numpy as np

from ..errors import ClrefractError
from .base import Box, Field
from .levelset import LevelSetField
from .voxel import grid_defines


def sharp_eta(phi: np.ndarray, eta: float) -> tuple[np.ndarray, np.ndarray]:
    """eta of a solid with a zero-width surface at points of signed distance phi (the
    gradient is zero almost everywhere)."""
    return np.where(phi < 0, eta, 1.0), np.zeros((len(phi), 3))


class InterfaceField(LevelSetField):
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
        from skimage.measure import marching_cubes

        b = self.box
        axes = [np.linspace(b.lo[k], b.hi[k], res) for k in range(3)]
        pts = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
        vol = np.concatenate(
            [self.sdf(pts[a : a + 262144])[0] for a in range(0, len(pts), 262144)]
        ).reshape((res,) * 3)
        if not vol.min() < 0 < vol.max():
            return None
        spacing = tuple((b.hi[k] - b.lo[k]) / (res - 1) for k in range(3))
        verts, faces, _, _ = marching_cubes(vol, 0.0, spacing=spacing)
        return verts + np.asarray(b.lo), faces

    @classmethod
    def from_levelset(cls, ls: LevelSetField) -> InterfaceField:
        return cls(ls.phi.copy(), ls.box, ls.eta, ls.width, ls.eta_bound)


class SphereInterface(Field):
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
        return length - self._p[3], r / length[:, None]

    def eval(self, pts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return sharp_eta(self.sdf(pts)[0], self.eta)

    def lipschitz(self) -> float:
        return 1.0

    def min_step(self) -> float:
        return float(self._p[3]) * 1e-3

    def uses_window(self) -> bool:
        return True

    def to_dict(self) -> dict:
        c = self._p
        return {"kind": self.kind, "centre": c[:3].tolist(), "radius": c[3], "eta": c[4]}
