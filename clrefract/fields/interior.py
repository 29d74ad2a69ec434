"""A graded interior inside a sharp surface: glass whose index varies (a graded-index lens, a
rod, a slab) bounded by an interface field's surface, air outside.

`GradedInterface` wraps any interface field (fields/interface.py). Inside its surface the index
is a quadratic polynomial, the form graded-index glass is specified in:

    eta(x) = c_0 + sum_i c_i u_i + sum_ij c_ij u_i u_j,   u = (x - centre) / scale,

ten coefficients, c_0 the surface field's own eta. Ten numbers are what the data of a few
dozen views fix without a smoothness prior, and a constant interior is the special case the
start begins from. Rays inside bend by the eikonal equation (RK4 steps of `step` mm); at the
surface they refract by Snell's law with the local index (kernels_cl/interface.cl,
SDF_GRADED).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import ClrefractError
from ..imageio import atomic_path
from .base import Box, Field

N_COEFFS = 10  # the constant, 3 linear and 6 quadratic terms
TERMS = ("1", "u_x", "u_y", "u_z", "u_x^2", "u_y^2", "u_z^2", "u_x u_y", "u_x u_z", "u_y u_z")
# the interior's RK4 step as a fraction of the box's smallest side: at 1/256 (0.39 mm) the
# graded-glass scenes' exit directions agree with SciPy's DOP853 to 2e-11 rad in float64
# (the index is a quadratic); float32 rounding, 6e-5 to 2.5e-4 rad, is far larger
STEP_FRACTION = 1 / 256


def basis(u: np.ndarray) -> np.ndarray:
    """The ten terms at scaled points u (n, 3): (n, 10)."""
    x, y, z = u[:, 0], u[:, 1], u[:, 2]
    one = np.ones(len(u))
    return np.column_stack([one, x, y, z, x * x, y * y, z * z, x * y, x * z, y * z])


def basis_gradient(u: np.ndarray) -> np.ndarray:
    """d basis / du at scaled points u (n, 3): (n, 10, 3)."""
    n = len(u)
    g = np.zeros((n, N_COEFFS, 3))
    for k in range(3):
        g[:, 1 + k, k] = 1.0
        g[:, 4 + k, k] = 2 * u[:, k]
    for j, (a, b) in enumerate(((0, 1), (0, 2), (1, 2))):
        g[:, 7 + j, a] = u[:, b]
        g[:, 7 + j, b] = u[:, a]
    return g


class GradedInterface(Field):
    """`surface` (an interface field, kept as `solid`) with a quadratic index inside it;
    `coeffs` the nine terms after the constant (zero: the surface's own constant index)."""

    traced_by = "interface"

    def __init__(self, surface, coeffs=None, centre=None, scale: float | None = None, step=None):
        if getattr(surface, "traced_by", None) != "interface":
            raise ClrefractError(
                f"a graded interior needs an interface surface, got {surface.kind}"
            )
        self.solid = surface
        self.box = surface.box
        lo, hi = np.asarray(self.box.lo, float), np.asarray(self.box.hi, float)
        if centre is None or scale is None:  # u spans [-1, 1] over the solid
            mesh = surface.surface(res=64)
            a, b = (lo, hi) if mesh is None else (mesh[0].min(0), mesh[0].max(0))
            centre = (a + b) / 2 if centre is None else centre
            scale = float(np.max(b - a) / 2) if scale is None else scale
        self.centre = np.asarray(centre, np.float64)
        self.scale = float(scale)
        self.step = float(np.min(hi - lo) * STEP_FRACTION if step is None else step)
        if not (self.scale > 0 and self.step > 0):
            raise ClrefractError("a graded interior's scale and step must be positive")
        c = np.zeros(N_COEFFS - 1) if coeffs is None else np.asarray(coeffs, np.float64)
        if c.shape != (N_COEFFS - 1,) or not np.all(np.isfinite(c)):
            raise ClrefractError(f"a graded interior has {N_COEFFS - 1} finite terms, got {c!r}")
        self.coeffs = c.copy()

    @property
    def kind(self) -> str:
        return self.solid.kind

    # --- parameters: the surface's (ending in its eta), then the nine terms ---------------
    def data(self) -> np.ndarray:
        return np.concatenate([self.solid.data(), self.coeffs])

    def set_data(self, params) -> None:
        params = np.asarray(params, np.float64)
        n = len(params) - (N_COEFFS - 1)
        if n <= 0 or not np.all(np.isfinite(params[n:])):
            raise ClrefractError("graded interior parameters are missing or non-finite")
        self.solid.set_data(params[:n])
        self.coeffs = params[n:].copy()

    def params(self) -> np.ndarray:
        return self.solid.params()

    @property
    def n_shared(self) -> int:
        return N_COEFFS

    def all_coeffs(self) -> np.ndarray:
        return np.append(self.solid.eta, self.coeffs)

    def index(self, pts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The interior's polynomial (n,) and its gradient (n, 3), wherever pts lie."""
        u = (np.asarray(pts, np.float64) - self.centre) / self.scale
        c = self.all_coeffs()
        return basis(u) @ c, np.einsum("nkd,k->nd", basis_gradient(u), c) / self.scale

    @property
    def eta_max(self) -> float:
        """The highest index inside, on a 48^3 lattice over the box."""
        b = self.box
        axes = [np.linspace(b.lo[k], b.hi[k], 48) for k in range(3)]
        pts = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
        return float(max(self.eval(pts)[0].max(), 1.0))

    def defines(self) -> dict:
        c = self.centre
        return {
            **self.solid.defines(),
            "SDF_GRADED": 1,
            "INT_CX": repr(float(c[0])),
            "INT_CY": repr(float(c[1])),
            "INT_CZ": repr(float(c[2])),
            "INT_INVL": repr(1.0 / self.scale),
            "INT_STEP": repr(self.step),
        }

    def kernel_params(self, box: Box, params=None) -> np.ndarray:
        return self.solid.kernel_params(box, params)

    def eval(self, pts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        inside = self.sdf(pts)[0] < 0
        eta, grad = self.index(pts)
        return np.where(inside, eta, 1.0), np.where(inside[:, None], grad, 0.0)

    def uses_window(self) -> bool:
        return True

    def tracing_box(self, box: Box) -> Box:
        return self.solid.tracing_box(box)

    def __getattr__(self, name: str):
        # the rest (sdf, surface, eta, shared_offset, lipschitz, planes...) is the surface's:
        # its adapters still apply
        if name == "solid":
            raise AttributeError(name)
        return getattr(self.solid, name)

    # --- fitting ----------------------------------------------------------------------------
    def param_groups(self, lr_index: float = 1e-3, **rates) -> list:
        """The surface's groups, then the interior's terms at lr_index (each term moves the
        index by at most its rate somewhere in the box, as the constant does)."""
        from ..adam import ParamGroup

        groups = self.solid.param_groups(lr_index=lr_index, **rates)
        n = len(self.solid.data())
        return [*groups, ParamGroup("interior", n, n + N_COEFFS - 1, lr_index)]

    def regularizer(self, params: np.ndarray) -> tuple[float, np.ndarray]:
        n = len(params) - (N_COEFFS - 1)
        loss, grad = self.solid.regularizer(params[:n])
        return loss, np.concatenate([grad, np.zeros(N_COEFFS - 1)])

    def save(self, path) -> None:
        """The surface's file, with the interior's keys beside its own."""
        path = Path(path)
        self.solid.save(path)
        with np.load(path, allow_pickle=False) as z:
            arrays = {k: z[k] for k in z.files}
        with atomic_path(path) as tmp, tmp.open("wb") as f:
            np.savez_compressed(
                f,
                **arrays,
                interior=self.coeffs,
                interior_centre=self.centre,
                interior_scale=self.scale,
                interior_step=self.step,
            )

    @classmethod
    def wrap_loaded(cls, surface, path) -> Field:
        """`surface` as loaded from `path`, with the interior that file holds, if any."""
        with np.load(path, allow_pickle=False) as z:
            if "interior" not in z.files:
                return surface
            try:
                return cls(
                    surface,
                    z["interior"],
                    z["interior_centre"],
                    float(z["interior_scale"]),
                    float(z["interior_step"]),
                )
            except (KeyError, ClrefractError) as exc:
                raise ClrefractError(f"{path}: bad graded interior ({exc})") from None

    def to_dict(self) -> dict:
        return {
            "kind": "graded-glass",
            "surface": self.solid.to_dict(),
            "interior": self.coeffs.tolist(),
            "terms": list(TERMS),
            "centre": self.centre.tolist(),
            "scale": self.scale,
            "step": self.step,
        }

    @classmethod
    def from_dict(cls, d: dict) -> GradedInterface:
        """As to_dict wrote it (a scene.json's object)."""
        from .interface import PolytopeInterface, SphereInterface

        try:
            s = dict(d["surface"])
            kind = s.pop("kind")
            if kind == "interface-sphere":
                solid = SphereInterface(s["centre"], s["radius"], s["eta"])
            elif kind == "polytope":
                box = Box.from_dict(s["box"])
                solid = PolytopeInterface(
                    s["planes"], s["eta"], box, s["centre"], rounding=s.get("rounding", 0.0)
                )
            else:
                raise ClrefractError(f"no graded glass of surface kind {kind!r}")
            return cls(solid, d["interior"], d["centre"], float(d["scale"]), float(d["step"]))
        except (KeyError, TypeError, ValueError) as exc:
            raise ClrefractError(f"graded-glass: bad description ({exc})") from None
