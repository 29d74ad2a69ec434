"""Tracing and differentiating sharp interfaces (fields/interface.py) on an OpenCL device:
straight segments between crossings found on phi, Snell's law or total internal reflection at
each (kernels_cl/interface.cl), and the gradient of the photometric loss with respect to phi's
parameters and the index through every crossing's point and normal.

`interface_numpy` is the float64 reference of the same event loop. It finds crossings
independently, by sampling each segment densely and bisecting, so the tests check the kernel's
march (no crossing skipped) as well as its spline.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from .errors import ClrefractError
from .fields.base import Box
from .gradient import GradientResult, traced_loss
from .runtime import Launch, Runtime, default_runtime
from .tracer import Out, Status, TraceResult, TraceSettings, device_args, work_group_size

# crossings before a ray counts as trapped (black), as the family's references allow: at 16,
# flat faces lost 0.5 to 0.75 dB and the sphere's start search chose a high index
MAX_EVENTS = 32
MAX_MARCH = 4096  # sphere-tracing steps per segment
# rays that meet the surface at a grazing angle (|cos| below this at any crossing) carry no
# gradient: the hit point's derivative grows as 1 / cos, and on the 64 x 64 sphere their
# few rays turned every descent (Adam or bounded steps) into a climb
GRAZING_COS = 0.3
SOURCES = ["common.h", "snell_common.h", "interface.cl"]


def tolerances(box: Box, precision: str) -> tuple[float, float]:
    """The crossing's tolerance along the ray and the offset off the surface after an event
    (mm): a few ulps of the box's size in float32, far below any pixel's footprint in float64."""
    scale = float(np.linalg.norm(box.size))
    return (1e-14 * scale, 1e-9 * scale) if precision == "float64" else (1e-6 * scale, 1e-5 * scale)


class InterfaceTracer:
    """Traces rays through an interface field as `settings` say (its precision; the step,
    lanes and skipping of eikonal tracers do not apply). grazing_cos: the backward pass's
    cut on grazing crossings (0: none, the exact gradient)."""

    skip_empty = False
    lanes = 1

    def __init__(
        self,
        field,
        box: Box | None = None,
        settings: TraceSettings | None = None,
        *,
        runtime: Runtime | None = None,
        occupancy=None,
        grazing_cos: float = GRAZING_COS,
    ):
        settings = settings or TraceSettings()
        self.settings, self.field = settings, field
        self.runtime = runtime or default_runtime()
        self.precision = settings.precision
        self.runtime.check_precision(self.precision)
        self.dtype = self.runtime.real_dtype(self.precision)
        self.box = field.tracing_box(box or Box())
        self.step = 0.0
        self.max_steps = MAX_MARCH
        self.tol, self.offset = tolerances(self.box, self.precision)
        defines = {
            **field.defines(),
            "GEO_AT": 3,  # fp: tol, offset, min_step, then the geometry (upload_field)
            "LANES": 1,
            "MAX_EVENTS": MAX_EVENTS,
            "MAX_MARCH": MAX_MARCH,
            "ADJ_MIN_COS": repr(float(grazing_cos)),
        }
        self.kernels = self.runtime.build(SOURCES, defines, self.precision)
        self.launch_bytes = 0
        self.upload_field()

    def upload_field(self) -> None:
        """Copy the field's current parameters to the device (after the field changed): fd its
        data, fp the march's tolerances and the geometry (kernels_cl/interface.cl)."""
        cl = self.runtime.cl
        mf = cl.mem_flags
        march = [self.tol, self.offset, self.field.min_step()]
        fp = self.field.kernel_params(self.box, march).astype(self.dtype)
        data = np.append(self.field.data(), 0.0).astype(self.dtype)
        ctx = self.runtime.context
        self._fp = cl.Buffer(ctx, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=fp)
        self._fd = cl.Buffer(ctx, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=data)
        self.lip = self.dtype(self.field.lipschitz())

    def columns(self, a, what: str) -> list[np.ndarray]:
        a = np.asarray(a, np.float64)
        if a.ndim != 2 or a.shape[1] != 3:
            raise ClrefractError(f"{what} must have shape (n, 3), got {a.shape}")
        if not np.all(np.isfinite(a)):
            raise ClrefractError(f"{what} contain non-finite values")
        return [np.ascontiguousarray(a[:, k], self.dtype) for k in range(3)]

    def launch(self, kernel, n: int, args, queue=None):
        """Run `kernel` over n rays (fp, fd, lip, n first), copying Out arrays back; returns
        the Launch, unfinished."""
        cl = self.runtime.cl
        q = queue or self.runtime.queue
        bufs, back = device_args(self.runtime, args)
        items = max(n, 1)
        local = work_group_size(items, self.runtime)
        kernel(
            q,
            (items,),
            None if local is None else (local,),
            self._fp,
            self._fd,
            self.lip,
            np.int32(n),
            *bufs,
        )
        self.launch_bytes = sum(b.size for b in bufs if isinstance(b, cl.MemoryObject))
        return Launch(q, [cl.enqueue_copy(q, a, b, is_blocking=False) for a, b in back])

    def trace(self, origins, directions) -> TraceResult:
        """Rays to the box's exit: TraceResult with steps = the march's phi evaluations."""
        o = self.columns(origins, "ray origins")
        d = self.columns(directions, "ray directions")
        n = len(o[0])
        if len(d[0]) != n:
            raise ClrefractError("ray origins and directions differ in number")
        if np.any((d[0] == 0) & (d[1] == 0) & (d[2] == 0)):
            raise ClrefractError("ray directions contain a zero vector")
        cols = [np.empty(n, self.dtype) for _ in range(6)]
        status, events, work = (np.empty(n, np.int32) for _ in range(3))
        outs = [Out(a) for a in [*cols, status, events, work]]
        self.launch(self.kernels.interface_trace, n, [*o, *d, *outs]).finish()
        pos = np.stack(cols[:3], axis=1).astype(np.float64)
        vel = np.stack(cols[3:], axis=1).astype(np.float64)
        speed = np.linalg.norm(vel, axis=1)
        self.events = events
        return TraceResult(
            position=pos,
            direction=vel / speed[:, None],
            speed=np.ones(n),
            status=status,
            steps=work,
            last_position=pos,
            last_velocity=vel,
        )

    def eval_sdf(self, pts) -> tuple[np.ndarray, np.ndarray]:
        """phi (n,) and its gradient (n, 3) computed by the device."""
        x = self.columns(pts, "points")
        n = len(x[0])
        outs = [np.empty(n, self.dtype) for _ in range(4)]
        cl = self.runtime.cl
        q = self.runtime.queue
        mf, ctx = cl.mem_flags, self.runtime.context
        bufs = [cl.Buffer(ctx, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=a) for a in x]
        obufs = [cl.Buffer(ctx, mf.WRITE_ONLY, a.nbytes) for a in outs]
        self.kernels.interface_eval(q, (n,), None, self._fp, self._fd, np.int32(n), *bufs, *obufs)
        for a, b in zip(outs, obufs):
            cl.enqueue_copy(q, a, b)
        q.finish()
        return outs[0].astype(np.float64), np.stack(outs[1:], axis=1).astype(np.float64)

    def eval_field(self, pts) -> tuple[np.ndarray, np.ndarray]:
        """eta (n,) and its gradient, inside by the device's phi."""
        inside = self.eval_sdf(pts)[0] < 0
        eta, grad = self.field.index(np.asarray(pts, np.float64))
        return np.where(inside, eta, 1.0), np.where(inside[:, None], grad, 0.0)


class InterfaceEngine:
    """The photometric loss of an interface field and its gradient with respect to
    field.data() (phi's parameters and the index), spread over the settings' queues."""

    def __init__(
        self,
        field,
        box: Box,
        settings: TraceSettings | None = None,
        *,
        runtime: Runtime | None = None,
        loss_space: str = "srgb",
        grazing_cos: float = GRAZING_COS,
    ):
        settings = settings or TraceSettings()
        self.settings = replace(settings, adjoint=settings.adjoint or "continuous")
        self.runtime = runtime or Runtime(queues=settings.queues)
        if len(self.runtime.queues) < settings.queues:
            raise ClrefractError(
                f"runtime has {len(self.runtime.queues)} queues, need {settings.queues}"
            )
        self.queues = self.runtime.queues[: settings.queues]
        self.tracer = InterfaceTracer(
            field, box, settings, runtime=self.runtime, grazing_cos=grazing_cos
        )
        self.field, self.box, self.loss_space = field, box, loss_space

    def set_params(self, params: np.ndarray) -> None:
        self.field.set_data(params)
        self.tracer.upload_field()

    def state_bytes_per_ray(self) -> int:
        """Bytes a ray's backward pass keeps: each event's point, directions in and out, side,
        and the curved segment's step count and last step."""
        return MAX_EVENTS * (10 * np.dtype(self.tracer.dtype).itemsize + 8)

    def loss_and_grad(
        self, origins, dirs, targets, env, weights=None, group: int = 1, terminal=None
    ) -> GradientResult:
        """As GradientEngine.loss_and_grad."""
        tr = self.tracer
        t = tr.trace(origins, dirs)
        if terminal is None:
            loss, mu, rad = traced_loss(
                env, t.status, t.direction, targets, weights, self.loss_space, group
            )
        else:
            loss, mu, rad = terminal(t.status, t.direction)
        n_par = len(self.field.data())
        n_int = int(getattr(self.field, "n_shared", 1))  # the index's terms (fields/interior.py)
        rays = np.flatnonzero((t.status == Status.EXITED) & mu.any(axis=1))
        grads = []
        for q, idx in zip(self.queues, np.array_split(rays, len(self.queues))):
            if not len(idx):
                continue
            grad = np.zeros(n_par + 1, tr.dtype)
            geta = np.empty(len(idx) * n_int, tr.dtype)
            gorig = np.empty(len(idx) * 3, tr.dtype)
            cl = tr.runtime.cl
            gbuf = cl.Buffer(
                tr.runtime.context,
                cl.mem_flags.READ_WRITE | cl.mem_flags.COPY_HOST_PTR,
                hostbuf=grad,
            )
            args = [
                *tr.columns(origins[idx], "ray origins"),
                *tr.columns(dirs[idx], "ray directions"),
                *tr.columns(mu[idx], "adjoints"),
                gbuf,
                Out(geta),
                Out(gorig),
            ]
            launch = tr.launch(tr.kernels.interface_adjoint, len(idx), args, q)
            launch.hold(cl.enqueue_copy(q, grad, gbuf, is_blocking=False))
            grads.append((launch, idx, grad, geta, gorig))
        total = np.zeros(n_par)
        n = len(origins)
        origin_grad = np.zeros((n, 3))
        for launch, idx, grad, geta, gorig in grads:
            launch.finish()
            total += grad[:n_par]
            off = self.field.shared_offset
            total[off : off + n_int] += geta.reshape(-1, n_int).astype(np.float64).sum(0)
            origin_grad[idx] = gorig.reshape(-1, 3)
        if not np.isfinite(loss) or not np.all(np.isfinite(total)):
            raise FloatingPointError("non-finite loss or gradient")
        return GradientResult(
            loss, total, rad, t.status, np.zeros(n), int(t.steps.sum()), np.ones(n), origin_grad
        )


# --- the float64 reference ----------------------------------------------------------------------
def refract(d, n, inside: bool, eta: float):
    """Snell refraction (or reflection past the critical angle) of unit d at outward unit n."""
    cd = float(d @ n)
    m = n if cd < 0 else -n
    ci = abs(cd)
    r = eta if inside else 1.0 / eta
    k = 1.0 - r * r * (1.0 - ci * ci)
    out = d + 2 * ci * m if k < 0 else r * d + (r * ci - np.sqrt(k)) * m
    return out / np.linalg.norm(out)


def first_crossing(phi, p, d, start: float, t_hi: float, inside: bool, ds: float):
    """Where phi (seen from `inside`) first turns <= 0 along p + t d, t in [start, t_hi]: by
    sampling every ds and bisecting; None if it does not."""
    ts = np.arange(start, t_hi + ds, ds)
    ts[-1] = min(ts[-1], t_hi)
    side = -1 if inside else 1
    f = phi(p + ts[:, None] * d) * side
    neg = np.flatnonzero(f <= 0)
    if not len(neg):
        return None
    j = neg[0]
    a, b = (ts[j - 1], ts[j]) if j else (ts[0], ts[0])
    for _ in range(80):
        mid = 0.5 * (a + b)
        if phi((p + mid * d)[None])[0] * side > 0:
            a = mid
        else:
            b = mid
    return p + 0.5 * (a + b) * d


def curved_crossing(field, x, d):
    """From x inside along unit d, the eikonal ray x' = v, v' = eta grad eta in the field's
    graded interior (SciPy's DOP853 at rtol 1e-12) to where phi turns 0: (point, direction)."""
    from scipy.integrate import solve_ivp

    def rate(_, y):
        eta, g = field.index(y[None, :3])
        return np.concatenate([y[3:], eta[0] * g[0]])

    def out(_, y):
        return field.sdf(y[None, :3])[0][0]

    out.terminal, out.direction = True, 1
    y0 = np.concatenate([x, field.index(x[None])[0][0] * d])
    span = 10 * float(np.linalg.norm(field.box.size))
    sol = solve_ivp(rate, (0, span), y0, "DOP853", events=out, rtol=1e-12, atol=1e-12)
    if not sol.t_events[0].size:
        return None
    y = sol.y_events[0][0]
    return y[:3], y[3:] / np.linalg.norm(y[3:])


def interface_numpy(field, box: Box, origins, dirs, samples: float = 0.1, curved=False):
    """Per-ray float64 reference: (status, exit direction, events). Crossings are found by
    sampling phi every `samples` of the field's min_step and bisecting the first sign change;
    with `curved`, rays inside follow the graded interior (curved_crossing)."""
    origins = np.asarray(origins, np.float64)
    dirs = np.asarray(dirs, np.float64)
    box = field.tracing_box(box)
    lo, hi = np.asarray(box.lo), np.asarray(box.hi)
    ds = field.min_step() * samples
    phi = lambda p: field.sdf(np.atleast_2d(p))[0]  # noqa: E731
    status = np.empty(len(origins), np.int32)
    out = dirs / np.linalg.norm(dirs, axis=1, keepdims=True)
    events = np.zeros(len(origins), np.int32)
    for i in range(len(origins)):
        o, d = origins[i], out[i].copy()
        t0, t1 = box.ray_span(o[None], d[None])
        t0, t1 = max(float(t0[0]), 0.0), float(t1[0])
        if not t0 < t1:
            status[i] = Status.MISSED
            continue
        p, inside, ev, start = o + t0 * d, False, 0, 0.0
        st = Status.EXITED
        while True:
            if curved and inside:
                hit = curved_crossing(field, p, d)
                x, d = hit if hit is not None else (None, d)
            else:
                with np.errstate(divide="ignore", invalid="ignore"):
                    far = np.where(d > 0, (hi - p) / d, np.where(d < 0, (lo - p) / d, np.inf))
                t_hi = max(float(far.min()), 0.0)
                x = first_crossing(phi, p, d, start, t_hi, inside, ds)
            if x is None:
                st = Status.NONFINITE if inside else Status.EXITED
                break
            if ev >= MAX_EVENTS:
                st = Status.TRAPPED
                break
            g = field.sdf(x[None])[1][0]
            nrm = g / np.linalg.norm(g)
            dn = refract(d, nrm, inside, float(field.index(x[None])[0][0]))
            inside = float(dn @ nrm) < 0
            p, d, ev = x, dn, ev + 1
            start = 1e-9 * np.linalg.norm(box.size) / max(abs(float(dn @ nrm)), 1e-3)
            if curved and inside:
                p = x + start * dn
        status[i], out[i], events[i] = st, d, ev
    return status, out, events
