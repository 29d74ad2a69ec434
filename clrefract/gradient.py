"""Loss and parameter gradient of a parametric field: forward trace, photometric loss,
adjoint backward pass, spread over several command queues.

Two backward passes: "continuous" (the default) integrates the adjoint-state equations
backwards beside a re-integrated ray, in constant memory, and matches the renderer's
gradient up to the integrator's error; "discrete" replays each segment of K steps from
forward checkpoints and reverses every RKN4 step exactly (adjoint_discrete.cl): the
renderer's own gradient to rounding, for a scratch of K steps and max_steps / K
checkpoints per ray, and 3 more field evaluations per step than the continuous pass.

Each queue traces its share of the rays and accumulates into its own gradient buffer; the
host sums the buffers in queue order, so the result does not depend on the number of queues
beyond rounding.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from .envmap import EnvMap
from .errors import ClrefractError
from .fields.base import Box, Field
from .limits import check_device_buffer
from .loss import photometric_loss
from .runtime import Runtime
from .tracer import InOut, Out, Status, Tracer, TraceSettings, renders_black


@dataclass
class GradientResult:
    loss: float
    grad: np.ndarray  # (n_params,) dJ/dtheta
    radiance: np.ndarray  # (n, 3) rendered
    status: np.ndarray  # (n,)
    drift: np.ndarray  # (n,) mm the re-integrated ray strayed: at the entry point, or at the
    # forward checkpoints where it restarted (discrete: the replay's rounding, ~0)
    steps: int
    growth: np.ndarray | None = None  # (n,) max |mu| / |mu(T)| along each ray's backward pass
    origin_grad: np.ndarray | None = None  # (n, 3) dJ/d(ray origin), the directions held
    rays: np.ndarray | None = None  # (n,) the training rays compared (Objective.loss_and_grad)


ADJOINTS = ("continuous", "discrete")


def discrete_segment(max_steps: int) -> int:
    """The default segment K of the discrete adjoint: ceil(sqrt(max_steps)), about the K
    that minimises the checkpoints (max_steps / K states) plus the scratch (K steps) per
    ray."""
    return max(1, math.isqrt(max(max_steps - 1, 0)) + 1)


# reals per replayed step in the discrete adjoint's scratch: the step's start and the points
# of its second and third stages (adjoint_discrete.cl)
SCRATCH_COLS = 9


def backward_state_bytes(max_steps: int, every: int, adjoint: str, itemsize: int) -> int:
    """Bytes per ray the backward pass keeps: 6 reals per checkpoint (max_steps // every of
    them, at least one buffer slot) and, for the discrete adjoint, SCRATCH_COLS per step of
    the segment it replays (every)."""
    if every <= 0:
        return 0
    scratch = SCRATCH_COLS * every if adjoint == "discrete" else 0
    return itemsize * (6 * max(max_steps // every, 1) + scratch)


def box_entry(box: Box, origins: np.ndarray, dirs: np.ndarray) -> np.ndarray:
    """Where each ray enters the box (the origin itself when it starts inside)."""
    d = dirs / np.linalg.norm(dirs, axis=1, keepdims=True)
    tmin = box.ray_span(origins, d)[0]
    return origins + np.maximum(tmin, 0)[:, None] * d


def origin_adjoint(box: Box, origins: np.ndarray, dirs: np.ndarray, at_entry: np.ndarray):
    """dJ/d(origin) from dJ/dx at each ray's entry point x = o + t(o) d: a ray that starts
    outside the box enters it on a wall of normal n, and x slides on that wall as o moves,
    dx/do = I - d n^T / (d . n)."""
    d = dirs / np.linalg.norm(dirs, axis=1, keepdims=True)
    near = box.slabs(origins, d)[0]
    wall = near.argmax(axis=1)  # the wall whose slab the ray enters last: the box's
    rows = np.arange(len(d))
    out = at_entry.copy()
    outside = near[rows, wall] > 0
    slide = (at_entry * d).sum(1) / d[rows, wall]
    out[rows[outside], wall[outside]] -= slide[outside]
    return out


def traced_loss(env, status, velocity, targets, weights=None, space="srgb", group=1):
    """The photometric loss of traced rays as they render: exited rays by the environment
    along their exit velocity, trapped and non-finite ones black (no adjoint), missed rays
    not at all. group: rays compared by blocks (see photometric_loss).
    Returns (loss, dJ/dv, radiance)."""
    dark = renders_black(status)
    weight = ((status == Status.EXITED) | dark).astype(float)
    if weights is not None:
        weight = weight * np.asarray(weights)
    return photometric_loss(
        env, velocity, targets, weight=weight, space=space, dark=dark, group=group
    )


def steps_to_reverse(steps: np.ndarray, status: np.ndarray, mu: np.ndarray) -> np.ndarray:
    """The backward pass's step count per (padded) ray: none for the black rays (trapped,
    non-finite) whose adjoint is zero, nor for the padding beyond mu's rows. The adjoint is
    linear in mu, so they add exactly nothing; a trapped ray held its work-item's lanes to
    the step cap."""
    m = len(mu)
    out = steps.copy()
    out[:m][renders_black(status[:m]) & ~mu.any(axis=1)] = 0
    out[m:] = 0
    return out


class GradientEngine:
    """Photometric loss and its gradient for `field` (its data() are the parameters),
    traced as `settings` (TraceSettings) say: rkn4 steps, and an adjoint of None taken for
    "continuous". loss_space: the photometric loss's colour space (loss.photometric_loss)."""

    def __init__(
        self,
        field: Field,
        box: Box,
        settings: TraceSettings | None = None,
        *,
        runtime: Runtime | None = None,
        loss_space: str = "srgb",
    ):
        settings = settings or TraceSettings()
        settings = replace(settings, adjoint=settings.adjoint or "continuous")
        adjoint, queues = settings.adjoint, settings.queues
        checkpoint_every, growth_max = settings.checkpoint_every, settings.growth_max
        if adjoint not in ADJOINTS:
            raise ClrefractError(f"adjoint must be one of {ADJOINTS}, got {adjoint!r}")
        if settings.integrator != "rkn4":
            raise ClrefractError(
                f"the backward passes reverse rkn4 steps, not {settings.integrator!r}"
            )
        self.settings = settings
        self.runtime = runtime or Runtime(queues=queues)
        if len(self.runtime.queues) < queues:
            raise ClrefractError(f"runtime has {len(self.runtime.queues)} queues, need {queues}")
        self.queues = self.runtime.queues[:queues]
        occupancy = None
        if settings.skip_empty:
            # exact by default: a level set's band (eta is flat off it whatever phi does),
            # else every cell; fits replace it by their rule (fit/occupancy.py)
            from .occupancy import distance_of, exact_live_cells

            occupancy = distance_of(exact_live_cells(field, box, settings.occupancy_res))
        self.tracer = Tracer(field, box, settings, runtime=self.runtime, occupancy=occupancy)
        self.field, self.box, self.loss_space = field, box, loss_space
        if checkpoint_every < 0:
            raise ClrefractError(f"checkpoint_every must be >= 0, got {checkpoint_every}")
        # 0: constant memory; C > 0: forward states kept every C steps bound the drift
        self.checkpoint_every = int(checkpoint_every)
        self.adjoint = adjoint
        if adjoint == "discrete" and not self.checkpoint_every:
            # K = sqrt(max_steps) balances checkpoints against the scratch of one segment
            self.checkpoint_every = discrete_segment(self.tracer.max_steps)
        if not (growth_max >= 0 and np.isfinite(growth_max)):
            raise ClrefractError(f"growth_max must be >= 0 (0: off), got {growth_max}")
        # a ray's backward pass stops once its adjoint grew by this factor (0: never)
        self.growth_max = float(growth_max)
        self._ckpt: dict[int, tuple] = {}
        self._k_adjoint = self.tracer.kernels.adjoint_rays
        if adjoint == "discrete":
            self._k_adjoint = self.tracer.kernels.adjoint_discrete
        self._scratch: dict[int, tuple] = {}
        self.n_shared = int(getattr(field, "n_shared", 0))

    def _checkpoint_buffer(self, queue, size: int):
        """The queue's checkpoint buffer, kept across calls and grown when a batch needs it:
        each queue has its own, as their kernels run at the same time."""
        buf, cap = self._ckpt.get(id(queue), (None, -1))
        if cap < size:
            buf = self.tracer.checkpoint_buffer(size, self.checkpoint_every)
            self._ckpt[id(queue)] = (buf, size)
        return buf

    def _scratch_buffer(self, queue, size: int):
        """The queue's scratch for the discrete adjoint's replayed segment (K steps)."""
        buf, cap = self._scratch.get(id(queue), (None, -1))
        if cap < size:
            tr = self.tracer
            nbytes = self.checkpoint_every * SCRATCH_COLS * size * np.dtype(tr.dtype).itemsize
            check_device_buffer(
                f"the discrete adjoint's segments of {self.checkpoint_every} steps for {size} rays",
                nbytes,
                self.runtime.info,
            )
            cl = self.runtime.cl
            buf = cl.Buffer(self.runtime.context, cl.mem_flags.READ_WRITE, nbytes)
            self._scratch[id(queue)] = (buf, size)
        return buf

    def state_bytes_per_ray(self) -> int:
        """Device bytes per ray that the backward pass keeps beside constant-size state."""
        tr = self.tracer
        itemsize = np.dtype(tr.dtype).itemsize
        return backward_state_bytes(tr.max_steps, self.checkpoint_every, self.adjoint, itemsize)

    def set_params(self, params: np.ndarray) -> None:
        self.field.set_data(params)
        self.tracer.upload_field()

    def _chunks(self, n: int, order=None) -> list[np.ndarray]:
        order = np.arange(n) if order is None else order
        return [c for c in np.array_split(order, len(self.queues)) if len(c)]

    def _skip_order(self, origins, dirs):
        """With skipping, rays whose straight line meets the live cells' bounds first: the
        rays of a work-item (LANES of them) then mostly all fly or all step, instead of
        each vector waiting for its slowest lane. The loss and the gradient's sum do not
        depend on the order (beyond rounding)."""
        occ = self.tracer.occupancy == 0
        if not occ.any() or occ.all():
            return None
        box = self.tracer.box
        cell = (np.asarray(box.hi) - np.asarray(box.lo)) / occ.shape[0]
        idx = np.argwhere(occ)
        lo = np.asarray(box.lo) + idx.min(0) * cell
        hi = np.asarray(box.lo) + (idx.max(0) + 1) * cell
        d = dirs / np.linalg.norm(dirs, axis=1, keepdims=True)
        with np.errstate(divide="ignore", invalid="ignore"):
            t1, t2 = (lo - origins) / d, (hi - origins) / d
        near = np.nan_to_num(np.minimum(t1, t2), nan=-np.inf).max(1)
        far = np.nan_to_num(np.maximum(t1, t2), nan=np.inf).min(1)
        return np.argsort(far < np.maximum(near, 0), kind="stable")

    def forward(self, origins, dirs):
        """Trace on every queue; returns the per-chunk results in order."""
        tr = self.tracer
        order = self._skip_order(origins, dirs) if tr.skip_empty else None
        chunks = self._chunks(len(origins), order)
        pending, launches = [], []
        for q, idx in zip(self.queues, chunks):
            o, m = tr.padded_columns(origins[idx], "ray origins")
            d, _ = tr.padded_columns(dirs[idx], "ray directions")
            size = len(o[0])
            outs = [np.empty(size, tr.dtype) for _ in range(6)]
            status, steps = np.empty(size, np.int32), np.empty(size, np.int32)
            last = [np.empty(size, tr.dtype) for _ in range(3)]
            ckpt = self._checkpoint_buffer(q, size)
            args = [tr.dtype(tr.step), np.int32(tr.max_steps), *o, *d]
            args += [Out(a) for a in outs + [status, steps] + last]
            args += [np.int32(self.checkpoint_every), ckpt]
            # with skipping, the lattice index (steps plus steps flown over) starts the
            # backward pass; steps counts the work done
            lattice = np.empty(size, np.int32) if tr.skip_empty else steps
            if tr.skip_empty:
                args += [*tr.skip_args, Out(lattice)]
            launches.append(tr.enqueue(tr.trace_kernel, size // tr.lanes, args, q))
            pending.append((idx, outs, status, steps, last, ckpt, o, d, lattice))
        for launch in launches:
            launch.finish()
        return pending

    def loss_and_grad(
        self,
        origins: np.ndarray,
        dirs: np.ndarray,
        targets: np.ndarray,
        env: EnvMap,
        weights: np.ndarray | None = None,
        group: int = 1,
        terminal=None,
    ) -> GradientResult:
        """weights: (n,) loss weight of each ray's pixel (0: a clipped photograph pixel);
        group: rays compared by the mean of each consecutive run of this many;
        terminal: another loss of the exit state, (status, velocity) -> (loss, dJ/dv,
        radiance), in place of the photometric one (targets, env, weights, group unused)."""
        tr = self.tracer
        pending = self.forward(origins, dirs)
        n = len(origins)
        vel = np.empty((n, 3))
        status = np.empty(n, np.int32)
        steps = 0
        for idx, outs, st, sp, *_ in pending:
            m = len(idx)
            vel[idx] = np.stack(outs[3:6], axis=1)[:m]
            status[idx] = st[:m]
            steps += int(sp[:m].sum())
        exited = status == Status.EXITED
        if terminal is None:
            loss, mu, rad = traced_loss(env, status, vel, targets, weights, self.loss_space, group)
        else:
            loss, mu, rad = terminal(status, vel)

        n_par = len(self.field.data())
        jobs = []
        for q, (idx, outs, st, _sp, last, ckpt, o, d, lat) in zip(self.queues, pending):
            size, m = len(st), len(idx)
            mu_cols = []
            for k in range(3):
                col = np.zeros(size, tr.dtype)
                col[:m] = mu[idx, k]
                mu_cols.append(col)
            grad = np.zeros(n_par + 1, tr.dtype)
            items = size // tr.lanes
            partial = np.zeros(max(items * self.n_shared, 1), tr.dtype)
            # x, y, z, checkpoint gap, adjoint growth, dJ/dx at the entry
            back = [np.empty(size, tr.dtype) for _ in range(8)]
            # continuous: from the last state; discrete: replayed from the entry and checkpoints
            start = [*last, *outs[3:6]] if self.adjoint == "continuous" else [*o, *d]
            steps_back = steps_to_reverse(lat, st, mu[idx])
            args = [
                tr.dtype(tr.step),
                *start,
                steps_back,
                *mu_cols,
                InOut(grad),
                InOut(partial),  # the kernel accumulates in it
                *[Out(b) for b in back[:3]],
                np.int32(tr.max_steps),
                np.int32(self.checkpoint_every),
                ckpt,
            ]
            if self.adjoint == "discrete":
                args.append(self._scratch_buffer(q, size))
            args += [Out(back[3]), tr.dtype(self.growth_max), *[Out(b) for b in back[4:]]]
            args += tr.skip_args
            launch = tr.enqueue(self._k_adjoint, items, args, q)
            jobs.append((launch, idx, grad, partial, back, items))
        total = np.zeros(n_par)
        back_pos = np.empty((n, 3))
        gap = np.empty(n)
        growth = np.empty(n)
        origin_grad = np.zeros((n, 3))
        for launch, idx, grad, partial, back, items in jobs:
            launch.finish()
            total += grad[:n_par]
            if self.n_shared:
                off = self.field.shared_offset
                total[off : off + self.n_shared] += (
                    partial.reshape(items, self.n_shared).astype(np.float64).sum(0)
                )
            back_pos[idx] = np.stack(back[:3], axis=1)[: len(idx)]
            gap[idx] = back[3][: len(idx)]
            growth[idx] = back[4][: len(idx)]
            origin_grad[idx] = np.stack(back[5:], axis=1)[: len(idx)]
        entry = box_entry(self.box, origins, dirs)
        drift = np.maximum(np.linalg.norm(back_pos - entry, axis=1), gap)
        drift = np.where(exited, drift, 0.0)
        if not np.isfinite(loss) or not np.all(np.isfinite(total)):
            raise FloatingPointError("non-finite loss or gradient")
        growth = np.where(exited, growth, 1.0)
        origin_grad = origin_adjoint(self.box, origins, dirs, origin_grad)
        origin_grad[~exited] = 0.0
        return GradientResult(loss, total, rad, status, drift, steps, growth, origin_grad)
