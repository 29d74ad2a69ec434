"""Ground truth for the family shapes: exact Snell refraction at a signed-distance surface.

The OpenCL kernel (kernels_cl/snell_sdf.cl) brackets each crossing by sphere tracing and
bisects it; `snell_sdf_numpy` is a float64 per-ray reference of the same event loop that finds
crossings independently, by dense sampling of the segment and bisection, so the tests check the
kernel's marching (no crossing skipped) as well as its C copies of the SDFs. Neither calls the
eikonal tracer. Results and status codes are those of clrefract.snell.
"""

from __future__ import annotations

import math

import numpy as np

from .errors import ClrefractError
from .family import SdfSolid, central_grad
from .fields.base import Box
from .runtime import Runtime
from .snell import (
    OFFSET_REL,
    TOL_REL,
    SnellRenderer,
    SnellResult,
    trace_events,
)

CLIP_REL = 1.01  # rays march in a sphere this much larger than the bound (as the kernel)
MAX_EVENTS = 32  # family shapes (bowl, two bodies) bounce more than the paper's solids


def _check_shape(shape) -> None:
    if not isinstance(shape, SdfSolid):
        raise ClrefractError(
            f"the SDF Snell renderer needs a family shape, got {type(shape).__name__}"
        )


class SdfSnellRenderer(SnellRenderer):
    """Exact Snell tracing through a family shape (clrefract.family) on one OpenCL device.

    precision: "float64", "float32", or None for float64 where the device has it.
    max_events: surface events allowed per ray; a ray that needs more gets Status.TRAPPED.
    """

    def __init__(
        self,
        shape: SdfSolid,
        box: Box | None = None,
        precision: str | None = None,
        max_events: int = MAX_EVENTS,
        runtime: Runtime | None = None,
    ):
        _check_shape(shape)
        self._setup(shape, box, precision, max_events, runtime)
        self._build("snell_sdf.cl", shape.kernel_defines(), shape.kernel_params())

    def _inside(self, pts: np.ndarray) -> np.ndarray:
        return self.solid.inside(pts)


# ----------------------------------------------------------------- NumPy reference (float64)


def _hit_dense(shape: SdfSolid, o, d, inside: bool, spacing: float):
    """First crossing along o + t d (local frame) inside the bounding sphere: samples every
    `spacing` mm, then bisection to the kernel's tolerance; the normal as the kernel's."""
    rb = shape.bounding_radius
    b, c = float(o @ d), float(o @ o) - (CLIP_REL * rb) ** 2
    disc = b * b - c
    if disc <= 0:
        return None
    sq = math.sqrt(disc)
    t0, t1 = max(-b - sq, 0.0), -b + sq
    if t1 <= t0:
        return None
    s = np.linspace(t0, t1, max(int(math.ceil((t1 - t0) / spacing)) + 1, 2))
    f = shape.local_distance(o[None] + s[:, None] * d[None])
    other = f > 0 if inside else f < 0
    if not other.any():
        return None
    i = int(np.argmax(other))
    lo, hi = (s[i - 1], s[i]) if i > 0 else (s[0], s[0])
    tol = TOL_REL * rb
    for _ in range(200):
        if hi - lo <= tol:
            break
        mid = 0.5 * (lo + hi)
        fm = float(shape.local_distance((o + mid * d)[None])[0])
        if (fm > 0) if inside else (fm < 0):
            hi = mid
        else:
            lo = mid
    t = 0.5 * (lo + hi)
    g = central_grad(shape.local_distance, (o + t * d)[None], shape.grad_step)[0]
    return t, g / np.linalg.norm(g)


def snell_sdf_numpy(
    shape: SdfSolid, origins, dirs, max_events: int = MAX_EVENTS, box: Box | None = None
) -> SnellResult:
    """Float64 per-ray reference of the kernel's event loop (slow: for tests)."""
    _check_shape(shape)
    box = box or Box()
    c, m = np.asarray(shape.center, float), shape.world_to_local
    origins = np.asarray(origins, float).reshape(-1, 3)
    dirs = np.asarray(dirs, float).reshape(-1, 3)
    eta, rb = float(shape.eta), shape.bounding_radius
    eps, spacing = OFFSET_REL * rb, rb / 4000

    def hit(o, d, inside):
        return _hit_dense(shape, o, d, inside, spacing)

    return trace_events(origins, dirs, c, m, eta, eps, hit, max_events, box)
