"""Forward curved-ray tracing of a field on one OpenCL device."""

from __future__ import annotations

import math
from dataclasses import dataclass
from enum import IntEnum

import numpy as np

from .device_check import check_once, check_points
from .errors import ClrefractError
from .fields.base import Box, Field
from .limits import check_count, check_device_buffer, max_steps_for
from .runtime import Launch, Runtime, default_runtime

INTEGRATORS = ("rkn4", "rk4", "euler", "dopri5")
# field evaluations per step (per attempted step for the adaptive pair)
EVALS_PER_STEP = {"rkn4": 3, "rk4": 4, "euler": 1, "dopri5": 7}


@dataclass
class Out:
    """A kernel argument written by the device and copied back."""

    array: np.ndarray


@dataclass
class InOut:
    """A kernel argument copied to the device, updated there, and copied back."""

    array: np.ndarray


class Status(IntEnum):
    EXITED = 0
    MISSED = 1
    TRAPPED = 2
    NONFINITE = 3


def work_group_size(items: int, runtime: Runtime) -> int | None:
    """Work-group size of a launch of `items` work-items. On CPUs PoCL runs a work-group as
    a loop over its work-items, each with its own copy of the private arrays on one
    thread's stack: the driver's choice of thousands of work-items overflows it (crashes
    seen: the backward pass's 4 KB of accumulators at 2,500 work-items in float64, a
    skipping trace's gathers at 4,096, a hash grid's distillation at one lane). At most 32
    there, whatever the lanes; on GPUs the driver's."""
    if runtime.info.kind != "cpu":
        return None
    g = 32
    while items % g:
        g //= 2
    return g


def device_args(runtime: Runtime, args) -> tuple[list, list]:
    """Kernel arguments on the device: numpy arrays copied in, Out and InOut arrays given
    buffers, other arguments as they are; and the (array, buffer) pairs to copy back."""
    cl = runtime.cl
    mf, ctx = cl.mem_flags, runtime.context
    bufs, back = [], []
    for a in args:
        if isinstance(a, Out):
            b = cl.Buffer(ctx, mf.WRITE_ONLY, max(a.array.nbytes, 1))
            back.append((a.array, b))
        elif isinstance(a, InOut):
            b = cl.Buffer(ctx, mf.READ_WRITE | mf.COPY_HOST_PTR, hostbuf=a.array)
            back.append((a.array, b))
        elif isinstance(a, np.ndarray):
            b = cl.Buffer(ctx, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=a)
        else:
            b = a
        bufs.append(b)
    return bufs, back


def renders_black(status: np.ndarray) -> np.ndarray:
    """Rays that no light reaches the camera along: trapped or non-finite."""
    return (status == Status.TRAPPED) | (status == Status.NONFINITE)


@dataclass
class TraceResult:
    position: np.ndarray  # (n, 3) exit point on the box, or the origin for missed rays
    direction: np.ndarray  # (n, 3) unit exit direction
    speed: np.ndarray  # (n,) |v| at exit: equals eta there (1 on the box) up to drift
    status: np.ndarray  # (n,) Status codes
    steps: np.ndarray  # (n,) integration steps taken
    last_position: np.ndarray  # (n, 3) last integrated point inside the box
    last_velocity: np.ndarray  # (n, 3) v there (equal to the exit v: the margin is eta = 1)


@dataclass(frozen=True)
class TraceSettings:
    """How rays are traced: a Tracer's settings, and a GradientEngine's (which passes them
    to its tracer). Variants: dataclasses.replace.

    step: the increment of sigma (arc length / eta) per integrator step, in mm.
    integrator: one of INTEGRATORS (a GradientEngine: rkn4 only).
    lanes: rays per work-item; None picks the device's default (16 on CPUs, 1 on GPUs).
    max_steps: the cap of steps per ray; None: a few box diagonals (limits.max_steps_for).
    adjoint: also build the backward-pass kernel (fields with parameters only):
        "continuous" the adjoint-state pass, "discrete" also the exact discrete adjoint
        (adjoint_discrete.cl: rkn4 only); None or "": forward only (a GradientEngine takes
        that for "continuous").
    tol: with integrator "dopri5", the local error per step (mm of position, and of v) that
        its adaptive step keeps to; `step` is then the largest step, and TraceResult.steps
        counts attempted steps (rejected ones cost evaluations too). Forward only: the
        backward pass replays fixed steps, so an adjoint refuses it.
    skip_empty: rays fly straight through the cells of an occupancy_res^3 grid where eta is
        constant (clrefract/occupancy.py), instead of stepping, in whole steps so that they
        stay on the lattice of steps they would have taken. The continuous backward pass
        flies back the same way (adjoint.cl); the discrete adjoint refuses it. A fit replaces
        the occupancy as the field trains (Tracer.set_occupancy).
    interface_steps: shorten steps that would cross a field's known kink (analytic fields:
        the Luneburg surface, a solid's band edges; a level set's band edges) so that they
        land on it and the scheme keeps its order there; False integrates across it (first
        order at the kink). Off with adjoint (fits): the backward passes take fixed steps.
    compensated: sum each step into x and v compensated (Kahan) or plainly; None: where
        rounding calls for it (compensated_sums: every float32 trace, no float64 one).
    queues, checkpoint_every, growth_max: the GradientEngine's (a Tracer ignores them):
        command queues to spread the rays over; forward states kept every so many steps
        for the backward pass (0: none, constant memory; the discrete adjoint's default
        segment); the factor of growth of a ray's adjoint that stops its backward pass
        (0: never).
    """

    step: float = 0.5
    integrator: str = "rkn4"
    precision: str = "float32"
    lanes: int | None = None
    max_steps: int | None = None
    adjoint: str | None = None
    interface_steps: bool = True
    tol: float | None = None
    skip_empty: bool = False
    occupancy_res: int = 32
    compensated: bool | None = None
    queues: int = 1
    checkpoint_every: int = 0
    growth_max: float = 0.0


ADJOINT_KINDS = (None, "", "continuous", "discrete")  # TraceSettings.adjoint's values

# float32's and float64's unit roundoff, and the rounding a plain sum may add to a ray
UNIT_ROUNDOFF = {"float32": 2.0**-24, "float64": 2.0**-53}
ROUNDING_BUDGET = 2.0**-22


def compensated_sums(precision: str, max_steps: int, extent: float, step: float) -> bool:
    """Whether the tracer sums x += dx and v += dv compensated (Kahan). A plain sum of x
    rounds each step by up to u |x| (u the unit roundoff), u |x| / step of the step, and
    one of v drifts as a random walk, about u sqrt(N) of |v| over N steps: compensated
    where u (sqrt(max_steps) + extent / step) passes 2^-22 (2.4e-7, the float32 exit
    direction's floor on the Luneburg lens with compensated sums), `extent` the largest
    |coordinate| the kernels see. So float32 always (plain sums took the trade study's
    Luneburg float32 error at 0.25 mm from 3.6e-7 to 1.9e-6); float64 only where
    sqrt(max_steps) or extent / step passes 2^31, which no box and step allowed reach."""
    u = UNIT_ROUNDOFF[precision]
    return u * (math.sqrt(max_steps) + extent / step) > ROUNDING_BUDGET


class Tracer:
    """Traces rays through `field` inside `box` with a fixed step of the optical-path
    parameter, as `settings` (TraceSettings) say. occupancy: with skip_empty, the grid to
    start from (occupancy.empty_distance's), else built from the field."""

    def __init__(
        self,
        field: Field,
        box: Box | None = None,
        settings: TraceSettings | None = None,
        *,
        runtime: Runtime | None = None,
        occupancy: np.ndarray | None = None,
    ):
        settings = settings or TraceSettings()
        self.settings = settings
        step, integrator, precision = settings.step, settings.integrator, settings.precision
        lanes, max_steps, adjoint = settings.lanes, settings.max_steps, settings.adjoint
        tol, skip_empty, occupancy_res = settings.tol, settings.skip_empty, settings.occupancy_res
        interface_steps = settings.interface_steps
        box = box or Box()
        # a ray bent inside the box rarely travels more than a few diagonals
        default_cap = max_steps_for(step, float(np.linalg.norm(box.size)))
        if integrator not in INTEGRATORS:
            raise ClrefractError(f"integrator must be one of {INTEGRATORS}, got {integrator!r}")
        self.runtime = runtime or default_runtime()
        self.runtime.check_precision(precision)
        self.field, self.box, self.step = field, box, float(step)
        self.integrator, self.precision = integrator, precision
        self.lanes = lanes or field.lanes_on(self.runtime, self.runtime.default_lanes(precision))
        self.runtime.check_lanes(self.lanes, precision)
        if field.lanes_on(self.runtime, self.lanes) != self.lanes:
            raise ClrefractError(
                f"{field.kind} fields run at most {field.gpu_lanes} lane(s) on "
                f"{self.runtime.info.name} (its multi-lane kernels come out wrong on this "
                "driver); leave --lanes unset"
            )
        if tol is not None and max_steps is None:
            # the adaptive pair's steps shrink where the field needs it: room for attempts
            default_cap = max_steps_for(step / 64, float(np.linalg.norm(box.size)))
        self.max_steps = default_cap if max_steps is None else check_count("max_steps", max_steps)
        # trace's first pass: one box diagonal at the default cap (4 diagonals), time enough
        # for any ray that crosses the box about straight (a step moves eta x step mm)
        self.long_ray_steps = -(-self.max_steps // 4)
        self.dtype = self.runtime.real_dtype(precision)
        # Rays are traced relative to the box centre where the field can move with it
        # (analytic fields, forward only): float32 positions 1e4 mm from the world origin
        # would otherwise resolve only ~1e-3 mm. Learned fields and the backward pass keep
        # world coordinates (gradient.py launches the kernels with them).
        centre = 0.5 * (np.asarray(box.lo, float) + np.asarray(box.hi, float))
        shiftable = hasattr(field, "params_shifted") and not adjoint
        self.offset = centre if shiftable else np.zeros(3)
        # the box as the kernels see it (fp's geometry, uploaded with the parameters)
        self.kbox = kbox = Box(tuple(box.lo - self.offset), tuple(box.hi - self.offset), box.margin)
        defines = {**field.defines(), "GEO_AT": len(field.params()), "LANES": self.lanes}
        defines[f"INTEGRATOR_{integrator.upper()}"] = 1
        # Kahan sums where rounding may pass 2^-22: u (sqrt(cap) + max|x| / step) > 2^-22
        finest = float(step) * (1e-4 if tol is not None else 1.0)  # dopri5's floor: 1e-4 step
        extent = float(np.abs(np.concatenate([kbox.lo, kbox.hi])).max())
        self.compensated = settings.compensated
        if self.compensated is None:
            self.compensated = compensated_sums(precision, self.max_steps, extent, finest)
        if self.compensated:
            defines["TRACE_COMPENSATED"] = 1
        self.tol = None if tol is None else float(tol)
        if self.tol is not None:
            if integrator != "dopri5":
                raise ClrefractError(
                    f"tol needs the adaptive integrator dopri5, not {integrator!r}"
                )
            if adjoint:
                raise ClrefractError(
                    "the adaptive integrator (dopri5 with tol) is forward only: the backward "
                    "pass replays fixed steps; fit with rkn4 or rk4"
                )
            if not (np.isfinite(self.tol) and self.tol > 0):
                raise ClrefractError(f"tol must be a positive number, got {tol!r}")
            if precision == "float32" and self.tol < 1e-9:
                # below float32's rounding of a step the error estimate never passes:
                # every step shrinks to the floor (measured: 60x the evaluations at 1e-10)
                raise ClrefractError(f"tol {tol:g} is below float32's rounding; use float64")
            defines["ADAPTIVE_TOL"] = repr(self.tol)
        # fits keep them off: the adjoints do not differentiate step lengths; a field that
        # declares itself smooth (no kinks) builds without them
        smooth = getattr(field, "smooth", False)
        self.interface_steps = bool(interface_steps) and not adjoint and not smooth
        if not self.interface_steps:
            defines["NO_INTERFACE_STEPS"] = 1
        self.skip_empty = bool(skip_empty)
        if self.skip_empty:
            if adjoint == "discrete":
                raise ClrefractError(
                    "empty-space skipping and the discrete adjoint do not mix: it replays "
                    "every step; use adjoint = 'continuous' or skip_empty = false"
                )
            if integrator != "rkn4" and adjoint:
                raise ClrefractError("the backward pass with skip_empty reverses rkn4 steps")
            res = check_count("occupancy_res", occupancy_res, 1, 1024)
            if occupancy is not None and np.shape(occupancy) != (res,) * 3:
                raise ClrefractError(f"occupancy must have shape {(res,) * 3}")
            self.occupancy = np.full((res,) * 3, 0, np.int32)  # every cell live until set
            defines.update(SKIP_EMPTY=1, OCC_N=res)
        sources = ["common.h", field.source, "trace.cl"]
        if adjoint not in ADJOINT_KINDS:
            raise ClrefractError(
                f"adjoint must be 'continuous', 'discrete' or None (forward only), got {adjoint!r}"
            )
        if adjoint == "discrete" and integrator != "rkn4":
            raise ClrefractError(f"the discrete adjoint reverses rkn4 steps, not {integrator!r}")
        if adjoint:
            adj = getattr(field, "adjoint_source", None)
            if adj is None:
                raise ClrefractError(
                    f"field {field.kind!r} has no backward pass yet, so it cannot be fitted "
                    "(fitting supports: voxel, hashgrid)"
                )
            sources = ["common.h", field.source, adj, "trace.cl", "adjoint.cl"]
            if adjoint == "discrete":
                sources.append("adjoint_discrete.cl")
        self.kernels = prg = self.runtime.build(sources, defines, precision)
        self.trace_kernel = prg.trace_rays
        self._k_propagate = prg.propagate_rays
        self._k_eval = prg.eval_field
        cl = self.runtime.cl
        self._no_ckpt = cl.Buffer(self.runtime.context, cl.mem_flags.READ_WRITE, 64)
        self.skip_args = []
        self.launch_bytes = 0  # device buffers the last launch used (bench's memory column)
        self.upload_field()
        if field.device_checked:
            self._check_kernels()
        if self.skip_empty:
            self.set_occupancy(self.field_occupancy() if occupancy is None else occupancy)

    def _check_kernels(self) -> None:
        """eta from the device against the field's NumPy eval, once per device and build
        (device_check.py)."""
        box = getattr(self.field, "box", self.box)
        pts = check_points(box)
        check_once(
            self.runtime,
            self.kernels,
            self.precision,
            f"the {self.field.kind} field's eta",
            lambda: (self.eval_field(pts)[0], self.field.eval(pts)[0]),
        )

    def field_occupancy(self) -> np.ndarray:
        """The occupancy (occupancy.empty_distance's) of the field as uploaded, sampled by
        the device's own kernel; for a field whose parameters changed, set_occupancy it."""
        from .occupancy import empty_distance

        res = self.occupancy.shape[0]
        return empty_distance(self.field, self.box, res, eval_fn=self.eval_field)

    def set_occupancy(self, distance: np.ndarray) -> None:
        """Replace the occupancy (empty_distance's grid, same resolution) with a new one."""
        if not self.skip_empty:
            raise ClrefractError("set_occupancy needs a tracer built with skip_empty")
        if distance.shape != self.occupancy.shape:
            raise ClrefractError(
                f"occupancy must have shape {self.occupancy.shape}, got {distance.shape}"
            )
        cl = self.runtime.cl
        mf = cl.mem_flags
        self.occupancy = np.ascontiguousarray(distance, np.int32)
        self.skip_args = [
            cl.Buffer(
                self.runtime.context,
                mf.READ_ONLY | mf.COPY_HOST_PTR,
                hostbuf=self.occupancy.reshape(-1),
            )
        ]

    def checkpoint_buffer(self, n_padded: int, every: int):
        """Device buffer for the states the forward pass keeps every `every` steps."""
        if every <= 0:
            return self._no_ckpt
        cl = self.runtime.cl
        slots = max(self.max_steps // every, 1)
        nbytes = slots * 6 * n_padded * np.dtype(self.dtype).itemsize
        check_device_buffer(
            f"step {self.step:g} mm: the backward pass's states of {n_padded} rays every "
            f"{every} steps",
            nbytes,
            self.runtime.info,
        )
        return cl.Buffer(self.runtime.context, cl.mem_flags.READ_WRITE, nbytes)

    def upload_field(self) -> None:
        """Copy the field's current parameters, and the geometry after them, to the device
        (after the field changed)."""
        cl = self.runtime.cl
        mf = cl.mem_flags
        ctx = self.runtime.context
        self._fp = cl.Buffer(
            ctx,
            mf.READ_ONLY | mf.COPY_HOST_PTR,
            hostbuf=self._real(self.field.kernel_params(self.kbox, self._field_params())),
        )
        self._fd = cl.Buffer(
            ctx,
            mf.READ_ONLY | mf.COPY_HOST_PTR,
            hostbuf=self._real(np.append(self.field.data(), 0.0)),
        )

    def _field_params(self) -> np.ndarray:
        if np.any(self.offset):
            return self.field.params_shifted(self.offset)
        return self.field.params()

    def _real(self, a) -> np.ndarray:
        return np.ascontiguousarray(a, dtype=self.dtype)

    def _local(self, a, what: str) -> np.ndarray:
        """World points to the kernels' frame, in float64 before any rounding."""
        a = np.asarray(a, dtype=np.float64)
        if a.ndim != 2 or a.shape[1] != 3:
            raise ClrefractError(f"{what} must have shape (n, 3), got {a.shape}")
        return a - self.offset

    def padded_columns(self, a: np.ndarray, what: str) -> tuple[list[np.ndarray], int]:
        a = np.asarray(a, dtype=np.float64)
        if a.ndim != 2 or a.shape[1] != 3:
            raise ClrefractError(f"{what} must have shape (n, 3), got {a.shape}")
        if not np.all(np.isfinite(a)):
            raise ClrefractError(f"{what} contain non-finite values")
        n = len(a)
        pad = (-n) % self.lanes
        if pad:
            a = np.concatenate([a, np.repeat(a[-1:], pad, axis=0)])
        return [self._real(a[:, k]) for k in range(3)], n

    def enqueue(self, kernel, n_items: int, args, queue=None, local: int | None = None) -> Launch:
        """Launch with numpy inputs copied in, Out/InOut arrays copied back (non-blocking);
        returns the Launch, to be finished by the caller. local: work-group size (it must
        divide n_items), else work_group_size's."""
        cl = self.runtime.cl
        q = queue or self.runtime.queue
        bufs, back = device_args(self.runtime, args)
        local = local or work_group_size(n_items, self.runtime)
        kernel(q, (n_items,), None if local is None else (local,), self._fp, self._fd, *bufs)
        self.launch_bytes = sum(
            b.size for b in (self._fp, self._fd, *bufs) if isinstance(b, cl.MemoryObject)
        )
        return Launch(q, [cl.enqueue_copy(q, a, b, is_blocking=False) for a, b in back])

    def _run(self, kernel, n_items: int, args, queue=None) -> None:
        self.enqueue(kernel, n_items, args, queue).finish()

    def trace(self, origins: np.ndarray, directions: np.ndarray) -> TraceResult:
        """Trace rays to the box's exit. In two passes: every ray up to `long_ray_steps`,
        then the rays still going, packed together, from their start with the full cap.
        A work-item's lanes run until its longest ray ends, so one trapped ray among 16
        held the other 15 lanes' time: on a faceted glass start with 88 of 8,192 rays
        trapped, one pass took 1.6x as long as two. Each ray's result is its single
        pass's, to the bit where a ray's rounding does not hang on its launch (not at 1
        lane in float32 on pip's PoCL, which rounds by the launch's size, passes or not)."""
        o, n = self.padded_columns(self._local(origins, "ray origins"), "ray origins")
        d, _ = self.padded_columns(directions, "ray directions")
        if len(d[0]) != len(o[0]):
            raise ClrefractError("ray origins and directions differ in number")
        if np.any((d[0] == 0) & (d[1] == 0) & (d[2] == 0)):
            raise ClrefractError("ray directions contain a zero vector")
        cols, status, steps = self._trace_columns(o, d, self.long_ray_steps)
        if self.long_ray_steps < self.max_steps:
            going = np.flatnonzero(status[:n] == Status.TRAPPED)
            if len(going):
                first = self.launch_bytes
                self._retrace(o, d, going, cols, status, steps)
                self.launch_bytes = max(first, self.launch_bytes)
        p, v, last = cols[:3], cols[3:6], cols[6:]
        vel = np.stack(v, axis=1)[:n].astype(np.float64)
        speed = np.linalg.norm(vel, axis=1)
        return TraceResult(
            position=np.stack(p, axis=1)[:n].astype(np.float64) + self.offset,
            direction=vel / speed[:, None],
            speed=speed,
            status=status[:n].copy(),
            steps=steps[:n].copy(),
            last_position=np.stack(last, axis=1)[:n].astype(np.float64) + self.offset,
            last_velocity=vel,
        )

    def _trace_columns(self, o: list, d: list, cap: int):
        """One pass of the trace kernel over padded columns, at most `cap` steps a ray:
        (exit point, exit v, last point inside) columns, status, steps."""
        m = len(o[0])
        cols = [np.empty(m, self.dtype) for _ in range(9)]
        status = np.empty(m, np.int32)
        steps = np.empty(m, np.int32)
        outs = [Out(a) for a in cols[:6] + [status, steps] + cols[6:]]
        scal = [self.dtype(self.step), np.int32(cap)]
        no_ckpt = [np.int32(0), self._no_ckpt]
        lattice = [Out(np.empty(m, np.int32))] if self.skip_empty else []
        args = scal + o + d + outs + no_ckpt + self.skip_args + lattice
        self._run(self.trace_kernel, m // self.lanes, args)
        return cols, status, steps

    def _retrace(self, o, d, rays, cols, status, steps) -> None:
        """Trace `rays` again with the full cap, into the first pass's outputs. Padded to a
        power of two of lanes (PoCL builds a kernel per launch size) with a ray that misses
        the box, so that the padding costs nothing."""
        m = self.lanes
        while m < len(rays):
            m *= 2
        lo, hi = np.asarray(self.box.lo) - self.offset, np.asarray(self.box.hi) - self.offset
        miss_o = [hi[0] + (hi[0] - lo[0]), (lo[1] + hi[1]) / 2, (lo[2] + hi[2]) / 2]
        pad = m - len(rays)
        o2 = [np.append(a[rays], np.full(pad, miss_o[k], self.dtype)) for k, a in enumerate(o)]
        d2 = [
            np.append(a[rays], np.full(pad, 1.0 if k == 0 else 0.0, self.dtype))
            for k, a in enumerate(d)
        ]
        again, st, sp = self._trace_columns(o2, d2, self.max_steps)
        k = len(rays)
        for a, b in zip(cols, again):
            a[rays] = b[:k]
        status[rays], steps[rays] = st[:k], sp[:k]

    def propagate(self, x: np.ndarray, v: np.ndarray, n_steps: int):
        """Advance states (x, v) by n_steps integrator steps, ignoring the box."""
        xs, n = self.padded_columns(self._local(x, "positions"), "positions")
        vs, _ = self.padded_columns(v, "velocities")
        args = [self.dtype(self.step), np.int32(n_steps)] + [InOut(a) for a in xs + vs]
        self._run(self._k_propagate, len(xs[0]) // self.lanes, args)
        return (
            np.stack(xs, axis=1)[:n].astype(np.float64) + self.offset,
            np.stack(vs, axis=1)[:n].astype(np.float64),
        )

    def eval_field(self, pts: np.ndarray):
        """eta (n,) and grad eta (n, 3) computed by the device kernel."""
        xs, n = self.padded_columns(self._local(pts, "points"), "points")
        m = len(xs[0])
        outs = [np.empty(m, self.dtype) for _ in range(4)]
        self._run(self._k_eval, m // self.lanes, xs + [Out(a) for a in outs])
        return outs[0][:n].astype(np.float64), np.stack(outs[1:], axis=1)[:n].astype(np.float64)
