"""What every index field gives the tracer: build defines, parameters, and a NumPy reference."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import ClrefractError


@dataclass(frozen=True)
class Box:
    """Axis-aligned bounding box in mm; learned fields are 1 within `margin` of its walls."""

    lo: tuple[float, float, float] = (-50.0, -50.0, -50.0)
    hi: tuple[float, float, float] = (50.0, 50.0, 50.0)
    margin: float = 4.0

    def __post_init__(self):
        lo, hi = np.asarray(self.lo, float), np.asarray(self.hi, float)
        if lo.shape != (3,) or hi.shape != (3,) or not np.all(hi > lo):
            raise ClrefractError(f"box must have lo < hi on every axis, got {self.lo}, {self.hi}")
        if not 0 < 2 * self.margin < float(np.min(hi - lo)) / 2:
            raise ClrefractError(f"box margin {self.margin} must be positive and small")

    @property
    def size(self) -> np.ndarray:
        return np.asarray(self.hi, float) - np.asarray(self.lo, float)

    def ray_span(self, origins: np.ndarray, dirs: np.ndarray):
        """(near, far): the ray parameters t where each ray o + t d enters and leaves the box
        (slabs; far <= near for a miss). A direction parallel to a wall from inside its slab
        bounds nothing on that axis."""
        lo, hi = self.slabs(origins, dirs)
        return lo.max(axis=1), hi.min(axis=1)

    def slabs(self, origins: np.ndarray, dirs: np.ndarray):
        """(n, 3) each: per axis, the ray parameters t where each ray o + t d crosses the
        box's two walls, nearer first; a direction parallel to an axis bounds nothing there
        (-inf, inf)."""
        with np.errstate(divide="ignore", invalid="ignore"):
            t1 = (np.asarray(self.lo, float) - origins) / dirs
            t2 = (np.asarray(self.hi, float) - origins) / dirs
        lo, hi = np.minimum(t1, t2), np.maximum(t1, t2)
        return np.where(np.isnan(lo), -np.inf, lo), np.where(np.isnan(hi), np.inf, hi)

    def geometry(self, nodes=(0, 0, 0)) -> np.ndarray:
        """What the kernels read of the box and of a node grid over it (kernels_cl/common.h),
        as data at the end of their parameters, from GEO_AT on: lo, hi, the margin, the node
        counts, the node spacing and its inverse (0 without a grid), the margin's inverse."""
        n = np.asarray(nodes, np.float64)
        h = np.divide(self.size, n - 1, out=np.zeros(3), where=n > 1)
        ih = np.divide(1.0, h, out=np.zeros(3), where=h > 0)
        return np.concatenate([self.lo, self.hi, [self.margin], n, h, ih, [1 / self.margin]])

    def to_dict(self) -> dict:
        return {"lo": list(self.lo), "hi": list(self.hi), "margin": self.margin}

    @classmethod
    def from_dict(cls, d: dict) -> Box:
        return cls(tuple(map(float, d["lo"])), tuple(map(float, d["hi"])), float(d["margin"]))


def smoother(t):
    t = np.clip(t, 0.0, 1.0)
    return t * t * t * (t * (t * 6 - 15) + 10)


def smoother_d(t):
    inside = (t > 0) & (t < 1)
    return np.where(inside, 30 * t * t * (t * (t - 2) + 1), 0.0)


def smoother_dd(t):
    inside = (t > 0) & (t < 1)
    return np.where(inside, 60 * t * (1 - t) * (1 - 2 * t), 0.0)


def box_window(box: Box, pts: np.ndarray):
    """W(x) and grad W: 0 within margin of a wall, 1 beyond twice the margin (C2)."""
    lo, hi, m = np.asarray(box.lo), np.asarray(box.hi), box.margin
    d0 = (pts - lo) / m - 1
    d1 = (hi - pts) / m - 1
    s0, s1 = smoother(d0), smoother(d1)
    a = s0 * s1  # (n, 3) per-axis factors
    ga = (smoother_d(d0) * s1 - s0 * smoother_d(d1)) / m
    w = a.prod(axis=1)
    grad = np.stack(
        [ga[:, 0] * a[:, 1] * a[:, 2], a[:, 0] * ga[:, 1] * a[:, 2], a[:, 0] * a[:, 1] * ga[:, 2]],
        axis=1,
    )
    return w, grad


class Field:
    """An index-of-refraction field eta(x) with an OpenCL and a NumPy implementation."""

    kind: str = ""
    source: str = ""
    # the most lanes its kernels give right answers at on devices other than CPUs (None: any)
    gpu_lanes: int | None = None
    # its kernels are checked against eval() once per device and build (device_check.py): a
    # driver has computed them wrong where it computed the others right
    device_checked: bool = False
    # what traces it (tracing.py): "eikonal" RK steps through a continuous eta, or
    # "interface" straight segments between refractions at a sharp surface
    traced_by: str = "eikonal"

    def lanes_on(self, runtime, lanes: int) -> int:
        """`lanes`, capped at gpu_lanes on a device that is not a CPU."""
        cap = self.gpu_lanes
        return lanes if cap is None or runtime.info.kind == "cpu" else min(lanes, cap)

    def defines(self) -> dict:
        raise NotImplementedError

    def params(self) -> np.ndarray:
        """Small parameter vector (fp in the kernels), float64. Its length is fixed by the
        build defines: programs are built with GEO_AT = len(params()) (kernel_params)."""
        raise NotImplementedError

    def nodes(self) -> tuple[int, int, int]:
        """Node counts of the field's grid over its box (0 for a field without one)."""
        return (0, 0, 0)

    def kernel_params(self, box: Box, params=None) -> np.ndarray:
        """fp as the kernels read it: params() (or `params`, as long), then from GEO_AT the
        geometry of `box` and of the field's grid."""
        p = self.params() if params is None else params
        return np.concatenate([p, box.geometry(self.nodes())])

    def data(self) -> np.ndarray:
        """Bulk data (fd in the kernels): grid values, tables, weights."""
        return np.zeros(1)

    @property
    def eta_max(self) -> float:
        raise NotImplementedError

    def eval(self, pts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Float64 reference: eta (n,) and grad eta (n, 3) at points (n, 3)."""
        raise NotImplementedError

    def to_dict(self) -> dict:
        raise NotImplementedError

    def uses_window(self) -> bool:
        return False

    def tracing_box(self, box: Box) -> Box:
        """The box to trace this field in: a learned field is 1 outside its own box (its
        window), so rays fly straight to that; an analytic one uses `box`."""
        return self.box if self.uses_window() else box

    @property
    def suggested_step(self) -> float:
        """A step (mm) that resolves the field's finest feature; steps much larger than a
        sharp interface trap grazing rays in spurious orbits."""
        return 0.5
