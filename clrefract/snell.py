"""Ground truth for the solid objects: exact Snell refraction at their analytic surfaces.

Rays are straight lines between surface events. At each event a ray refracts by Snell's law
or, past the critical angle, reflects (total internal reflection); there is no Fresnel split
and no absorption. The sharp surfaces of `Sphere`, `Prism` and `Drop` are used (their smoothing
`width` is ignored). The OpenCL kernel (kernels_cl/snell.cl) never calls the eikonal tracer.

Intersections: the sphere by the robust quadratic; the prism as a convex polyhedron of five
planes (slab clipping to enter, the nearest exiting plane from inside); the drop through its
inside function F = (R^2/4) u w^3 - rho^2 (u = 1 + z/H, w = 1 - z/H), positive exactly
inside, a quartic along a ray whose first crossing the kernel brackets exactly by isolating the
roots of F'' and F' (then bisection). `snell_numpy` is a float64 per-ray reference of the same
event loop; for the drop it finds crossings independently, by dense sampling and bisection.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .errors import ClrefractError
from .fields.analytic import Drop, Prism, Sphere
from .fields.base import Box
from .runtime import Runtime, default_runtime
from .tracer import Status

SOLIDS = (Sphere, Prism, Drop)

# float64 constants shared with the kernel (OFFSET_REL, TOL_REL in snell.cl)
OFFSET_REL = 1e-9
TOL_REL = 1e-12
DROP_BOUND = 0.6505  # bounding half-width of the drop in units of R (max r(t) = 0.6495 R)


@dataclass
class SnellResult:
    """Per ray:

    position: EXITED: where the final straight segment leaves the box; MISSED: the origin;
        TRAPPED: the last event point.
    direction: unit final direction (the input direction for MISSED rays).
    status: Status codes (0 exited, 1 missed, 2 event cap reached, 3 non-finite / lost).
    events: surface events (refractions and total internal reflections) applied.
    surface: the last event point (the origin for missed rays).
    """

    position: np.ndarray
    direction: np.ndarray
    status: np.ndarray
    events: np.ndarray
    surface: np.ndarray


def _check_solid(solid) -> None:
    if not isinstance(solid, SOLIDS):
        raise ClrefractError(
            f"Snell ground truth needs a Sphere, Prism or Drop, got {type(solid).__name__}"
        )
    if not solid.eta >= 1:
        raise ClrefractError(f"{solid.kind}: eta must be at least 1, got {solid.eta}")


def solid_frame(solid) -> tuple[np.ndarray, np.ndarray]:
    """Centre (3,) and world -> local rotation (3, 3) of the solid: local = M (x - centre)."""
    m = solid.world_to_local if isinstance(solid, Prism) else np.eye(3)
    return np.asarray(solid.center, float), np.asarray(m, float)


def solid_params(solid) -> np.ndarray:
    """Parameter vector of kernels_cl/snell.cl: centre, M (row-major), a, b, eta."""
    _check_solid(solid)
    c, m = solid_frame(solid)
    if isinstance(solid, Sphere):
        a, b = solid.radius, 0.0
    elif isinstance(solid, Prism):
        a, b = solid.side, solid.length
    else:
        a, b = solid.R, solid.H
    return np.array([*c, *m.ravel(), a, b, solid.eta], float)


def solid_size(solid) -> float:
    if isinstance(solid, Sphere):
        return float(solid.radius)
    if isinstance(solid, Prism):
        return float(solid.side)
    return float(max(solid.R, solid.H))


_S3 = math.sqrt(3.0) / 2
_PRISM_N = np.array([[0, 1, 0], [-_S3, -0.5, 0], [_S3, -0.5, 0], [0, 0, 1], [0, 0, -1]], float)


def _prism_offsets(solid) -> np.ndarray:
    hs = solid.side / (2 * math.sqrt(3.0))
    return np.array([hs, hs, hs, 0.5 * solid.length, 0.5 * solid.length])


def drop_F(p: np.ndarray, R: float, H: float) -> np.ndarray:
    """Inside function of the drop (local frame), positive exactly inside; p (..., 3)."""
    u, w = (H + p[..., 2]) / H, (H - p[..., 2]) / H
    return 0.25 * R * R * u * w**3 - p[..., 0] ** 2 - p[..., 1] ** 2


def inside_solid(solid, pts: np.ndarray) -> np.ndarray:
    """Strictly-inside mask (n,) of world points."""
    c, m = solid_frame(solid)
    loc = (np.asarray(pts, float) - c) @ m.T
    if isinstance(solid, Sphere):
        return (loc**2).sum(1) < solid.radius**2
    if isinstance(solid, Prism):
        return np.all(loc @ _PRISM_N.T < _prism_offsets(solid), axis=1)
    return drop_F(loc, solid.R, solid.H) > 0


def drop_normal(p: np.ndarray, R: float, H: float) -> np.ndarray:
    """Outward unit normal of the drop at a surface point p (local), from the profile at
    t = acos(z/H): (H sin t, R/2 (cos t - cos 2t)) in the (rho, z) half-plane."""
    u = min(max((H + p[2]) / H, 0.0), 2.0)
    w = min(max((H - p[2]) / H, 0.0), 2.0)
    nr, nz = H * math.sqrt(u * w), 0.5 * R * w * (2 * u - 1)
    rho = math.hypot(p[0], p[1])
    ex, ey = (p[0] / rho, p[1] / rho) if rho > 0 else (0.0, 0.0)
    n = np.array([nr * ex, nr * ey, nz])
    nn = float(np.linalg.norm(n))
    return n / nn if nn > 0 else np.array([0.0, 0.0, 1.0])


# ----------------------------------------------------------------- NumPy reference (float64)


def _hit_sphere(o, d, inside, R):
    b = float(o @ d)
    ll = o - b * d
    disc = R * R - float(ll @ ll)
    c = float(o @ o) - R * R
    if not inside:
        if b >= 0 or disc <= 0:
            return None
        t = max(c / (-b + math.sqrt(disc)), 0.0)
    else:
        sq = math.sqrt(max(disc, 0.0))
        t = max(-b + sq if b <= 0 else -c / (b + sq), 0.0)
    p = o + t * d
    return t, p / np.linalg.norm(p)


def _hit_prism(o, d, inside, hh):
    dn = _PRISM_N @ d
    num = hh - _PRISM_N @ o
    if inside:
        out = dn > 0
        if not out.any():
            return None
        tj = np.where(out, num / np.where(out, dn, 1.0), np.inf)
        k = int(np.argmin(tj))
        return max(float(tj[k]), 0.0), _PRISM_N[k].copy()
    if np.any((dn == 0) & (num < 0)):
        return None
    ent, ext = dn < 0, dn > 0
    if not ent.any():
        return None
    tj = num / np.where(dn == 0, 1.0, dn)
    te = np.where(ent, tj, -np.inf)
    k = int(np.argmax(te))
    tn = float(te[k])
    tf = float(np.min(np.where(ext, tj, np.inf)))
    if tn <= 0 or tn >= tf:
        return None
    return tn, _PRISM_N[k].copy()


def _clip_box(o, d, hb):
    lo, hi = 0.0, np.inf
    for j in range(3):
        if d[j] != 0:
            ta, tb = (-hb[j] - o[j]) / d[j], (hb[j] - o[j]) / d[j]
            lo, hi = max(lo, min(ta, tb)), min(hi, max(ta, tb))
        elif abs(o[j]) > hb[j]:
            return None
    return (lo, hi) if lo < hi else None


def _hit_drop_dense(o, d, inside, R, H):
    """First crossing by dense sampling (spacing min(R, H)/4000) and bisection: independent
    of the kernel's root isolation."""
    clip = _clip_box(o, d, (DROP_BOUND * R, DROP_BOUND * R, H * (1 + 1e-6)))
    if clip is None:
        return None
    s0, s1 = clip
    q = o + s0 * d
    n = int(math.ceil((s1 - s0) / (min(R, H) / 4000))) + 1
    s = np.linspace(0.0, s1 - s0, max(n, 2))
    f = drop_F(q[None] + s[:, None] * d[None], R, H)
    other = f <= 0 if inside else f > 0
    if not other.any():
        return None
    i = int(np.argmax(other))
    lo, hi = (s[i - 1], s[i]) if i > 0 else (0.0, 0.0)
    tol = TOL_REL * max(R, H)
    for _ in range(200):
        if hi - lo <= tol:
            break
        mid = 0.5 * (lo + hi)
        fm = float(drop_F(q + mid * d, R, H))
        if (fm <= 0) if inside else (fm > 0):
            hi = mid
        else:
            lo = mid
    s_hit = 0.5 * (lo + hi)
    return s0 + s_hit, drop_normal(q + s_hit * d, R, H)


def _refract_or_reflect(d, n, inside, eta):
    cd = float(d @ n)
    m = n if cd < 0 else -n
    ci = abs(cd)
    r = eta if inside else 1.0 / eta
    k = 1.0 - r * r * (1.0 - ci * ci)
    if k < 0:
        v = d + 2 * ci * m
    else:
        v = r * d + (r * ci - math.sqrt(k)) * m
    return v / np.linalg.norm(v)


def _box_exit(p, d, box: Box):
    lo, hi = np.asarray(box.lo, float), np.asarray(box.hi, float)
    t = np.inf
    for j in range(3):
        if d[j] > 0:
            t = min(t, (hi[j] - p[j]) / d[j])
        elif d[j] < 0:
            t = min(t, (lo[j] - p[j]) / d[j])
    return p + max(t, 0.0) * d


def snell_numpy(solid, origins, dirs, max_events: int = 16, box: Box | None = None):
    """Float64 per-ray reference of the kernel's event loop; returns a SnellResult."""
    _check_solid(solid)
    box = box or Box()
    c, m = solid_frame(solid)
    origins = np.asarray(origins, float).reshape(-1, 3)
    dirs = np.asarray(dirs, float).reshape(-1, 3)
    eta, eps = float(solid.eta), OFFSET_REL * solid_size(solid)
    if isinstance(solid, Sphere):

        def hit(o, d, inside):
            return _hit_sphere(o, d, inside, solid.radius)
    elif isinstance(solid, Prism):
        hh = _prism_offsets(solid)

        def hit(o, d, inside):
            return _hit_prism(o, d, inside, hh)
    else:

        def hit(o, d, inside):
            return _hit_drop_dense(o, d, inside, solid.R, solid.H)

    return trace_events(origins, dirs, c, m, eta, eps, hit, max_events, box)


def trace_events(origins, dirs, c, m, eta, eps, hit, max_events, box) -> SnellResult:
    """The float64 per-ray event loop of the Snell references, in the solid's frame
    (local = m (x - c)); hit(o, d, inside) -> (t, unit normal) or None."""
    n = len(origins)
    res = SnellResult(
        np.empty((n, 3)),
        np.empty((n, 3)),
        np.empty(n, np.int32),
        np.empty(n, np.int32),
        np.empty((n, 3)),
    )
    for i in range(n):
        dw = dirs[i] / np.linalg.norm(dirs[i])
        o, d = m @ (origins[i] - c), m @ dw
        surf, inside, ev = o, False, 0
        while True:
            h = hit(o, d, inside)
            if h is None:
                st = Status.NONFINITE if inside else (Status.MISSED if ev == 0 else Status.EXITED)
                break
            if ev >= max_events:
                st = Status.TRAPPED
                break
            t, nrm = h
            p = o + t * d
            dn = _refract_or_reflect(d, nrm, inside, eta)
            if not (np.all(np.isfinite(p)) and np.all(np.isfinite(dn))):
                st = Status.NONFINITE
                break
            cn = float(dn @ nrm)
            inside = cn < 0
            o = p + (eps / max(abs(cn), 1e-3)) * dn
            surf, d, ev = p, dn, ev + 1
        if st == Status.MISSED:
            res.direction[i], res.surface[i], res.position[i] = dw, origins[i], origins[i]
        else:
            dwo, sw = m.T @ d, c + m.T @ surf
            res.direction[i], res.surface[i] = dwo, sw
            res.position[i] = _box_exit(sw, dwo, box) if st == Status.EXITED else sw
        res.status[i], res.events[i] = int(st), ev
    return res


# ----------------------------------------------------------------------------- the kernel


def check_max_events(max_events) -> None:
    if isinstance(max_events, bool) or not isinstance(max_events, int | np.integer):
        raise ClrefractError(f"max_events must be an integer, got {max_events!r}")
    if not 1 <= int(max_events) <= 1_000_000:
        raise ClrefractError(f"max_events must be between 1 and 1e6, got {max_events}")


class SnellRenderer:
    """Exact Snell tracing through a Sphere, Prism or Drop on one OpenCL device.

    box: where EXITED rays report their position (default the benchmark's [-50, 50]^3).
    max_events: surface events allowed per ray; a ray that needs more gets Status.TRAPPED.
    """

    def __init__(
        self,
        solid,
        box: Box | None = None,
        precision: str = "float64",
        max_events: int = 16,
        runtime: Runtime | None = None,
    ):
        _check_solid(solid)
        self._setup(solid, box, precision, max_events, runtime)
        self._build("snell.cl", {f"SOLID_{solid.kind.upper()}": 1}, solid_params(solid))

    def _setup(self, solid, box, precision, max_events, runtime) -> None:
        check_max_events(max_events)
        self.solid, self.box, self.max_events = solid, box or Box(), int(max_events)
        self.runtime = runtime or default_runtime()
        if precision is None:  # float64 where the device has it
            precision = "float64" if self.runtime.info.fp64 else "float32"
        self.runtime.check_precision(precision)
        self.precision = precision
        self.dtype = self.runtime.real_dtype(precision)

    def _build(self, shape_source: str, defines: dict, params: np.ndarray) -> None:
        """The shared event-loop kernel (snell_trace.cl) over one shape's hit function; the
        box follows the shape's parameters in sp (common.h's geometry)."""
        self.kernels = self.runtime.build(
            ["common.h", "snell_common.h", shape_source, "snell_trace.cl"],
            {**defines, "GEO_AT": len(params)},
            self.precision,
        )
        self._kernel = self.kernels.snell_trace
        cl = self.runtime.cl
        self._sp = cl.Buffer(
            self.runtime.context,
            cl.mem_flags.READ_ONLY | cl.mem_flags.COPY_HOST_PTR,
            hostbuf=np.concatenate([params, self.box.geometry()]).astype(self.dtype),
        )

    def _inside(self, pts: np.ndarray) -> np.ndarray:
        return inside_solid(self.solid, pts)

    def _columns(self, a, what: str) -> np.ndarray:
        a = np.asarray(a, dtype=np.float64)
        if a.ndim != 2 or a.shape[1] != 3:
            raise ClrefractError(f"{what} must have shape (n, 3), got {a.shape}")
        if not np.all(np.isfinite(a)):
            raise ClrefractError(f"{what} contain non-finite values")
        return a

    def trace(self, origins: np.ndarray, directions: np.ndarray) -> SnellResult:
        o = self._columns(origins, "ray origins")
        d = self._columns(directions, "ray directions")
        if len(o) != len(d):
            raise ClrefractError("ray origins and directions differ in number")
        if np.any(np.all(d == 0, axis=1)):
            raise ClrefractError("ray directions contain a zero vector")
        inside = self._inside(o)
        if inside.any():
            raise ClrefractError(
                f"{int(inside.sum())} ray origin(s) lie inside the {self.solid.kind}: Snell "
                f"ground truth expects cameras outside the object (first: {o[inside][0]})"
            )
        n = len(o)
        if n == 0:
            e3 = np.empty((0, 3))
            return SnellResult(
                e3, e3.copy(), np.empty(0, np.int32), np.empty(0, np.int32), e3.copy()
            )
        cl = self.runtime.cl
        ctx, q = self.runtime.context, self.runtime.queue
        mf = cl.mem_flags
        ins = [
            cl.Buffer(
                ctx,
                mf.READ_ONLY | mf.COPY_HOST_PTR,
                hostbuf=np.ascontiguousarray(a[:, k], dtype=self.dtype),
            )
            for a in (o, d)
            for k in range(3)
        ]
        reals = [np.empty(n, self.dtype) for _ in range(9)]
        ints = [np.empty(n, np.int32) for _ in range(2)]
        outs = [cl.Buffer(ctx, mf.WRITE_ONLY, a.nbytes) for a in reals + ints]
        group = 64
        self._kernel(
            q,
            (-(-n // group) * group,),
            None,
            self._sp,
            np.int32(self.max_events),
            np.int32(n),
            *ins,
            *outs,
        )
        for a, b in zip(reals + ints, outs, strict=True):
            cl.enqueue_copy(q, a, b, is_blocking=False)
        q.finish()
        col = [a.astype(np.float64) for a in reals]
        return SnellResult(
            position=np.column_stack(col[0:3]),
            direction=np.column_stack(col[3:6]),
            status=ints[0],
            events=ints[1],
            surface=np.column_stack(col[6:9]),
        )
