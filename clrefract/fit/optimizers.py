"""How a fit moves its field: Adam on every parameter, the line search on a level set, and
the line search a hash grid follows through its level set (its guide). Each optimiser owns
its state and says which field the held-out views judge."""

from __future__ import annotations

import time

import numpy as np

from ..adam import Adam
from ..errors import ClrefractError
from ..metrics import psnr_linear_batch
from ..smoothing import gaussian_nodes
from .distil import fit_to_field
from .finishes import face_offsets, size_index_search
from .kinds import KINDS, guide_config, guide_kind, make_field
from .linesearch import level_set_step
from .quasi_newton import quasi_newton_finish
from .rays import blur_at

# a refit starts where the grid is: its Adam rates a tenth of a fresh distillation's
REFIT_RATE = 0.1
# refit = "best": the one refit to the best step, from the start's fit, as (iterations in
# refit_iterations, rate) in turn. The quick sphere's level set after 30 steps renders
# 35.20 dB; the grid fitted to it 34.20 after 800 at 0.3 (eta RMS 0.00054, 22 s), 34.36
# after 1,600 more at 0.1 (0.00036, 42 s), 33.59 fitted afresh as a start is (2,000 at 1)
FINAL_REFIT = ((4, 0.3), (8, 0.1))


class AdamSteps:
    """Adam on the field's parameters, on a fresh batch each iteration (voxel grids refined
    coarse to fine on the way)."""

    def __init__(self, fit):
        self.reset(fit)

    def reset(self, fit) -> None:
        """Fresh moments (a start, a blow-up)."""
        self.adam = Adam(len(fit.params), fit.groups())

    def state(self) -> dict:
        return self.adam.state()

    def restore(self, fit, ckpt) -> None:
        self.adam.load_state(ckpt.adam)

    def judged(self, fit):
        """The bound field whose held-out loss picks what the run keeps."""
        return fit.bound

    def validation_loss(self, fit) -> float:
        return fit.objective.held_out_loss(fit.bound.tracer)

    def step(self, fit) -> dict:
        self._regrid(fit)
        cfg, bound = fit.cfg, fit.bound
        idx, side = fit.rays.batch(fit.it)
        t0 = time.perf_counter()
        r = fit.objective.loss_and_grad(bound.engine, idx, fit.it, side * side, step=fit.it)
        reg, greg = bound.field.regularizer(bound.params)
        grad = r.grad + cfg.reg * greg + fit.kind.extra_gradient(cfg, bound.params)
        if bound.free is not None:
            grad[~bound.free] = 0.0
        if not np.all(np.isfinite(grad)):
            raise FloatingPointError("non-finite gradient")
        decay = cfg.lr_final ** (fit.it / cfg.iterations)
        before = bound.params.copy()
        self.adam.step(bound.params, grad, lr_scale=decay)
        if not np.all(np.isfinite(bound.params)):
            bound.params[:] = before  # the field stays as the iteration found it
            raise FloatingPointError("non-finite parameters")
        fit.kind.project(cfg, bound.params, fit.eta_max, bound.free)
        bound.field.set_data(bound.params)
        bound.upload(fit.it, stepped=True)
        dt = time.perf_counter() - t0
        fit.it += 1
        exited = r.status == 0
        cap = cfg.adjoint_growth_max
        targets = fit.rays.blurred(fit.it - 1)[1]
        return {
            "truncated": float(np.mean(r.growth[exited] > cap)) if cap > 0 else 0.0,
            "iteration": fit.it,
            "loss": r.loss,
            "reg": float(reg),
            "psnr": psnr_linear_batch(r.radiance[exited], targets[r.rays][exited]),
            "rays_per_s": len(idx) / dt,
            "seconds": dt,
            "drift_mm": float(r.drift.max()),
            "blur": blur_at(cfg, fit.it - 1),
            "block": side,
            "res": fit.kind.resolution(bound.field),
            "steps_per_ray": r.steps / len(idx),
            **({"live": bound.occupancy.live_fraction} if bound.occupancy is not None else {}),
        }

    def _regrid(self, fit) -> None:
        """Coarse to fine: the field and Adam's moments upsampled (Teh et al.); step counts
        carry over."""
        res = fit.kind.resolution_at(fit.cfg, fit.it)
        old = fit.field
        if not fit.kind.grid or res == fit.kind.resolution(old):
            return
        m = old.resampled_values(self.adam.m.reshape(old.values.shape), res)
        v = np.maximum(old.resampled_values(self.adam.v.reshape(old.values.shape), res), 0)
        t = int(self.adam.t.max())
        fit.bind(old.resampled(res))
        self.reset(fit)
        self.adam.m, self.adam.v = m.ravel(), v.ravel()
        self.adam.t[:] = t

    def validated(self, fit, loss: float) -> None:
        """Told each held-out loss as it is measured."""

    def finish(self, fit) -> dict:
        """Leave the field at its best-validated parameters, then the kind's own finish;
        what the finish did."""
        fit.use_best()
        finish = ADAM_FINISHES.get(fit.kind.adam_finish)
        return finish(fit) if finish else {}


ADAM_FINISHES = {"face-offsets": face_offsets}


# the first descent step of a voxel grid tries its rate over 4^6 = 4,096 times down: a
# plume's index (7.5e-4) is a seventh of the 5e-3 that suits a blob cluster
CALIBRATION_STEPS = 6


# A held-out loss more than this above the run's best halves a calibrated rate. The graded
# set's held-out losses rise by up to 2.3% from one validation to the next while they fall
# overall: halving on any rise took the Luneburg lens's rate from 5e-3 to 5e-6 and the GRIN
# rod's and lens's below 1e-6 within 600 steps, and they kept their starts; halving only on
# rises of 5% between validations let the lens drift 10% above its best at 5e-3.
OVERSHOOT = 0.05
# More validations than this without a better held-out loss halve the rate too, once a run
# has beaten its start; any halving goes back to a best older than the last validation.
# Quick GRIN rod, test PSNR: 29.21 with neither (its rate stayed at 5e-3 over the last 300
# steps within 3% of its best), 30.25 going back alone, 30.84 and 29.95 with both (ceiling
# 31.61; docs/design/descent-rate.md)
PLATEAU = 3


# A validation that finds a better held-out loss grows a calibrated rate by this (up to
# lr_max). Quick graded set, test PSNR without / with: plume 71.84 / 73.70 (ceiling 77.73),
# GRIN rod 26.91 / 27.93 (its rate calibrated to 3.1e-4; ceiling 31.61); the Luneburg lens,
# the GRIN lens and the blob clusters within run-to-run noise or above their ceilings
# (docs/design/descent-rate.md); growth by 2 not measured
GROWTH = 1.5


class IterateMean:
    """The mean of the iterates a descent passed through since it was last taken: where the
    steps are as long as the noise in their directions, the mean lies nearer the minimum
    than any one of them (Polyak-Ruppert averaging)."""

    def __init__(self):
        self.total, self.count = None, 0

    def add(self, params: np.ndarray) -> None:
        if self.total is None or self.total.shape != params.shape:  # a new grid starts anew
            self.total, self.count = np.zeros_like(params, np.float64), 0
        self.total += params
        self.count += 1

    def take(self) -> np.ndarray | None:
        """The mean (None for fewer than two iterates), and a fresh start."""
        mean = self.total / self.count if self.count >= 2 else None
        self.total, self.count = None, 0
        return mean


# the descent's narrowing smoothing stops at this many cells: at 16^3 over 100 mm, narrowing
# alone to 2 mm took a blob cluster from empty space to 0.92 of its held-out loss in 100
# steps, 8 mm throughout to 0.70 (a node's gradient there is its rays' alone)
FINEST_CELLS = 1.25


def sigma_at(cfg, it: int, spacing: float) -> float:
    """The descent's narrowing smoothing at an iteration, mm: descent_sigma narrowing
    geometrically to descent_sigma_final (where it is set; at least FINEST_CELLS of
    `spacing` mm) over the first half of the iterations."""
    final = max(cfg.descent_sigma_final, FINEST_CELLS * spacing)
    if cfg.descent_sigma_final <= 0 or final >= cfg.descent_sigma:
        return cfg.descent_sigma
    frac = min(1.0, it / max(cfg.iterations / 2, 1))
    return cfg.descent_sigma * (final / cfg.descent_sigma) ** frac


def smoothed_unit(grad: np.ndarray, shape: tuple, sigma_cells, free) -> np.ndarray:
    """A grid's gradient smoothed over sigma_cells (per axis), zero off the free nodes, and
    scaled to a largest magnitude of 1 (all zero where it is zero)."""
    g = gaussian_nodes(grad.reshape(shape), sigma_cells).ravel()
    if free is not None:
        g[~free[: len(g)]] = 0.0
    top = float(np.abs(g).max())
    return g / top if top > 0 else g


class SmoothedDescent(AdamSteps):
    """Gradient descent on a grid of nodes (a surface's distances, a medium's eta). A ray's
    gradient reaches only the 64 nodes about it and is noisy from node to node: smoothed over
    descent_sigma mm (and, with descent_sigma_final, over a narrowing scale too, each
    moving a node at most the kind's grid rate: the narrow one alone stalled a smooth lens,
    whose largest moves became its noisiest nodes', and the two scaled together halved the
    wide one's step where they agreed), it moves the field as a whole
    (Adam's per-node scaling moves the noisiest nodes as far as the rest, and took the test
    views down). Scalars after the grid (an interface's index) move their rate along their
    gradient's sign. Both decay by a cosine to lr_final."""

    def reset(self, fit) -> None:
        super().reset(fit)
        self.mean = IterateMean()

    def nodes(self, fit) -> tuple:
        """The bound field whose nodes descend, its kind and its top index: the fit's own."""
        return fit.bound, fit.kind, fit.eta_max

    def judged(self, fit):
        return self.nodes(fit)[0]

    def validation_loss(self, fit) -> float:
        """The held-out loss of the grid, or of the mean of its steps since the last
        validation where that is lower (a calibrated descent's): the descent goes on from the
        one kept. Quick graded set: the blob clusters 0.6 to 1.5 dB higher in two runs, the
        lenses and the plume within run-to-run spread (docs/design/descent-rate.md)."""
        bound, kind, _ = self.nodes(fit)
        loss = fit.objective.held_out_loss(bound.tracer)
        mean = self.mean.take()
        if mean is None or not kind.calibrates_descent:
            return loss
        here = bound.params.copy()
        bound.set_params(mean, fit.it)
        averaged = fit.objective.held_out_loss(bound.tracer)
        if averaged < loss:
            return averaged
        bound.set_params(here, fit.it)
        return loss

    def step(self, fit) -> dict:
        self._regrid(fit)
        bound, kind, eta_max = self.nodes(fit)
        cfg = fit.cfg
        field = bound.field
        idx, side = fit.rays.batch(fit.it)
        t0 = time.perf_counter()
        r = fit.objective.loss_and_grad(bound.engine, idx, fit.it, side * side, step=fit.it)
        reg, greg = field.regularizer(bound.params)
        grad = r.grad + cfg.reg * greg
        if bound.free is not None:
            grad[~bound.free] = 0.0
        if not np.all(np.isfinite(grad)):
            raise FloatingPointError("non-finite gradient")
        shape = kind.descent_grid(field)
        n = int(np.prod(shape))
        grid_rate, scalar_rate = kind.descent_rates(cfg)
        g = smoothed_unit(grad[:n], shape, cfg.descent_sigma / field.spacing, bound.free)
        fine = sigma_at(cfg, fit.it, float(np.max(field.spacing)))
        if fine < cfg.descent_sigma:  # each scale moves a node up to the rate
            g += smoothed_unit(grad[:n], shape, fine / field.spacing, bound.free)
        rate = cfg.lr_final + (1 - cfg.lr_final) * 0.5 * (
            1 + np.cos(np.pi * fit.it / cfg.iterations)
        )
        if fit.it == 0 and kind.calibrates_descent and np.any(g):
            grid_rate = self._calibrate(fit, bound, kind, eta_max, g, n, grid_rate)
        bound.params[:n] -= grid_rate * rate * g
        bound.params[n:] -= scalar_rate * rate * np.sign(grad[n:])
        kind.project(cfg, bound.params, eta_max, bound.free)
        field.set_data(bound.params)
        bound.upload(fit.it, stepped=True)
        if kind.calibrates_descent:  # interfaces keep no mean: no work on their steps
            self.mean.add(bound.params)
        dt = time.perf_counter() - t0
        fit.it += 1
        exited = r.status == 0
        targets = fit.rays.blurred(fit.it - 1)[1]
        return {
            "iteration": fit.it,
            "loss": r.loss,
            "reg": float(reg),
            "psnr": psnr_linear_batch(r.radiance[exited], targets[r.rays][exited]),
            "rays_per_s": len(idx) / dt,
            "seconds": dt,
            "rate": float(rate),
            "lr": float(grid_rate),  # as calibrated, halved and grown
            "steps_per_ray": r.steps / len(idx),
            **kind.descent_row(field),
        }

    def validated(self, fit, loss: float) -> None:
        """A calibrated rate halves (in config.toml) at each validation whose held-out loss is
        more than OVERSHOOT above the run's best (tracked before this is called), or that
        follows more than PLATEAU without a better one once the run has beaten its start.
        Where that best is the start, or older than the last validation, the grid goes back
        to it: a first step's best length, repeated, overshot a faint blob's whole index
        (1.003: the test views lost 2.2 dB in 60 steps), and from a graded start near the
        truth 50 steps of 5e-3 took the Luneburg lens too far to come back at any rate. A
        validation that is the run's new best grows it by GROWTH, up to lr_max: one batch's
        calibration is no measure of the whole run."""
        cfg = fit.cfg
        if not self.nodes(fit)[1].calibrates_descent:
            return
        stale = fit.it - fit.best.iteration
        # a plateau at the start is a descent still finding its way: halving there froze it
        plateau = fit.best.iteration > 0 and stale > PLATEAU * cfg.validate_every
        if loss > fit.best.loss * (1 + OVERSHOOT) or plateau:
            cfg.lr /= 2
            # steps too long for a start near the truth, or for the basin the run reached
            # (a hash grid's guide keeps its own best apart)
            back = fit.best.iteration == 0 or stale > cfg.validate_every
            if back and self.nodes(fit)[0] is fit.bound:
                fit.use_best()
                fit.bound.upload(fit.it)
        elif fit.it > 0 and fit.best.iteration == fit.it and cfg.lr < cfg.lr_max:
            cfg.lr = min(cfg.lr * GROWTH, cfg.lr_max)
        else:
            return
        fit.out.write_config(cfg)

    def finish(self, fit) -> dict:
        """As AdamSteps.finish, a graded medium's grid polished first (quasi_newton.py)."""
        did = self.polish(fit)
        if did.get("quasi_newton", {}).get("kept"):
            fit.best.params = fit.bound.params.copy()
            fit.best.loss = did["quasi_newton"]["held_out_loss"]["after"]
        return {**did, **super().finish(fit)}

    def polish(self, fit, params=None) -> dict:
        """The quasi-Newton finish of the nodes' best grid (or `params`), where the kind
        calibrates its descent and cfg.quasi_newton asks for one; the nodes are left at the
        grid it keeps."""
        bound, kind, eta_max = self.nodes(fit)
        if not (kind.calibrates_descent and fit.cfg.quasi_newton):
            return {}
        if params is None:
            params = fit.best.params if fit.best.params is not None else bound.params
        sigma = sigma_at(fit.cfg, fit.cfg.iterations, float(np.max(bound.field.spacing)))
        return quasi_newton_finish(fit, bound, kind, eta_max, params.copy(), sigma)

    def _calibrate(self, fit, bound, kind, eta_max, direction, n: int, grid_rate: float) -> float:
        """The run's rate, of grid_rate / 4^k (k = 0 to CALIBRATION_STEPS), kept in
        config.toml with grid_rate as its lr_max: grid_rate itself unless its first step
        raises a fixed batch's loss, else a quarter of the one that lowers it most (none
        lowering it, the first direction measures no length: a Luneburg lens's took 4^-6 and
        kept its start); `validated` halves it where later steps overshoot and grows it back
        where they find better. A medium's contrast spans 1e-3 (a gas) to 0.4
        (a graded-index lens), and a step that suits a lens overshoots a plume's whole index;
        the step of the largest fall,
        always, took the blob cluster to 27.43 dB where 5e-3 took it to 33.29. The largest
        fall's step reaches the line's minimum, and repeated it circles it: on a faint gas
        (1.003) it left 0.24-0.82 of the start's held-out loss over 120 steps, its quarter
        0.16 every time."""
        from ..parallel import world
        from .rays import Tag

        if world().size != 1:
            return grid_rate
        idx = fit.rays.mask_batch(Tag.CALIBRATION)
        start = bound.params.copy()
        base = fit.objective.loss(bound.tracer, idx)  # unmoved
        fall = []
        for k in range(CALIBRATION_STEPS + 1):
            bound.params[:n] = start[:n] - grid_rate / 4**k * direction
            kind.project(fit.cfg, bound.params, eta_max, bound.free)
            bound.field.set_data(bound.params)
            bound.upload(fit.it)
            fall.append(base - fit.objective.loss(bound.tracer, idx))
        bound.set_params(start, fit.it)
        k = min(int(np.argmax(fall)) + 1, CALIBRATION_STEPS) if fall[0] < 0 < max(fall) else 0
        fit.cfg.lr, fit.cfg.lr_max = grid_rate / 4**k, grid_rate
        fit.out.write_config(fit.cfg)
        fit.stream.write(
            f"descent: a voxel's step {fit.cfg.lr:.3g} ({grid_rate:g} / 4^{k}), kept in "
            "config.toml\n"
        )
        return fit.cfg.lr


class LineSearch(AdamSteps):
    """A level set's line search (linesearch.py); its best level set's size and index are
    searched together at the end (finishes.py). Adam's moments stay in the checkpoint, unused."""

    def step(self, fit) -> dict:
        t0 = time.perf_counter()
        row = level_set_step(fit, fit.bound)
        fit.it += 1
        return _timed(row, t0)

    def finish(self, fit) -> dict:
        done = {}
        if fit.cfg.size_search:
            done["size_search"] = size_index_search(fit, fit.bound)
        fit.use_best()
        return done


class FollowsGuide:
    """An optimiser that moves another field (its guide) which the fitted one follows: the
    guide and its top index, kept in the checkpoint."""

    def __init__(self, fit, guide, guide_eta_max: float):
        super().__init__(fit)
        self.guide, self.guide_eta_max = guide, guide_eta_max

    @classmethod
    def resumed(cls, fit, ckpt):
        """The optimiser of a resumed fit, its guide from the checkpoint."""
        return cls(fit, *resumed_guide(fit, ckpt))

    def state(self) -> dict:
        return {
            **self.adam.state(),
            "guide_params": self.guide.params,
            "guide_res": self.guide.field.shape[0],
            "guide_eta_max": self.guide_eta_max,
        }


class GuidedLineSearch(FollowsGuide, LineSearch):
    """A hash grid from the hull: the line search moves the level set it was distilled from
    (its guide), and the grid is fitted to it, once to the best step (refit = "best", where
    the held-out views judge the level set) or after every move (refit = "step")."""

    def __init__(self, fit, guide, guide_eta_max: float):
        super().__init__(fit, guide, guide_eta_max)
        self.grid_tracer = None

    def judged(self, fit):
        return self.guide if fit.cfg.refit == "best" else fit.bound

    def validation_loss(self, fit) -> float:
        if fit.cfg.refit == "best":
            return fit.objective.held_out_loss(self.guide.tracer)
        return fit.objective.held_out_loss(self.validation_tracer(fit) or fit.bound.tracer)

    def validation_tracer(self, fit):
        """With skip_empty, the grid is validated through rays that skip the cells where its
        eta is constant, sampled from the grid as it is now (it changes between validations
        only by a refit), and steps as its engine does. Forward only, so no gradient is
        lost; its engine's own rays never skip. On the quick sphere: 4.2 s instead of 9.2,
        and 1.7 s to sample the grid."""
        if not fit.cfg.skip_empty:
            return None
        tracer = self.grid_tracer
        if tracer is None or tracer.field is not fit.field:
            self.grid_tracer = fit.forward_tracer(fit.field, interface_steps=False)
            return self.grid_tracer
        tracer.upload_field()
        tracer.set_occupancy(tracer.field_occupancy())
        return tracer

    def step(self, fit) -> dict:
        t0 = time.perf_counter()
        row = level_set_step(fit, self.guide)
        if row["index_move"]:
            fit.set_eta_max(fit.kind.eta_top(fit.cfg, self.guide.params[-1]))
        if row["step_mm"] > 0 and fit.cfg.refit == "step":
            row["distilled_rms"] = self.refit(fit, fit.cfg.refit_iterations)
        fit.it += 1
        return _timed(row, t0)

    def refit(self, fit, iterations: int, rate: float = REFIT_RATE) -> float:
        """Fit the hash grid to its guide again, from where it is; the RMS error of eta."""
        rms = fit_to_field(
            fit.field,
            self.guide.field,
            fit.cfg.width,
            iterations,
            fit.cfg.seed + fit.it + 1,
            rate=rate,
            device=fit.distil_device(),
        )
        fit.bound.set_params(fit.field.data(), fit.it)
        return rms

    def finish(self, fit) -> dict:
        if fit.cfg.refit != "best":
            fit.use_best()  # the grid's own best
            return {}
        done = {}
        searched = None
        if fit.cfg.size_search:
            searched = done["size_search"] = size_index_search(fit, self.guide, guided=True)
        done["final_refit"] = self.refit_to_best(fit, moved=bool(searched and searched["kept"]))
        return done

    def refit_to_best(self, fit, moved: bool = False) -> dict | None:
        """The hash grid fitted to its guide's best-validated step (the last without
        validation) from the start's fit (FINAL_REFIT's iterations), the guide left at its
        last step; what that took, or None where the best is the start, whose level set the
        grid holds already, and the size search did not `move` it."""
        best = fit.best
        it, params = best.iteration, best.params
        if params is None:  # none validated: the last step
            it, params = fit.it, self.guide.params.copy()
        if it == 0 and not moved:
            return None
        t0 = time.perf_counter()
        # the refit samples the level set on the host: nothing to upload, and the guide's own
        # parameters stay at its last step, where --resume goes on
        self.guide.field.set_data(params)
        fit.set_eta_max(best.eta_max or fit.eta_max)
        for times, rate in FINAL_REFIT:
            rms = self.refit(fit, times * fit.cfg.refit_iterations, rate)
        self.guide.field.set_data(self.guide.params)
        return {"iteration": it, "distilled_rms": rms, "seconds": time.perf_counter() - t0}


class GuidedDescent(FollowsGuide, SmoothedDescent):
    """A hash grid for a graded medium: the smoothed descent moves a voxel grid (its guide),
    the held-out views judge it, and the grid is fitted to its best at the end. The descent
    lowers a graded medium's held-out loss in a tenth of the time Adam on the grid's own
    parameters takes to move it at all."""

    def __init__(self, fit, guide, guide_eta_max: float):
        super().__init__(fit, guide, guide_eta_max)
        self.kind = KINDS[guide_kind(fit.cfg)]

    def nodes(self, fit) -> tuple:
        return self.guide, self.kind, self.guide_eta_max

    def finish(self, fit) -> dict:
        """The hash grid fitted afresh to the guide's best-validated step (the last without
        validation; none where that is the start, which it holds), kept where the held-out
        views prefer it to the start's grid: a fit holds what the guide gained only where
        the grid can (the README's Luneburg lens on n_max 32 lost 0.15 dB in the refit); the
        guide left at its last step, where --resume goes on."""
        best = fit.best
        it, params = best.iteration, best.params
        if params is None:
            it, params = fit.it, self.guide.params.copy()
        last = self.guide.params.copy()
        polished = self.polish(fit, params)
        if polished.get("quasi_newton", {}).get("kept"):
            params = fit.best.params = self.guide.params.copy()
            fit.best.loss = polished["quasi_newton"]["held_out_loss"]["after"]
        elif it == 0:
            if polished:  # the guide back at its last step, where --resume goes on
                self.guide.set_params(last, fit.it)
            return polished  # the grid holds the start's fit already
        t0 = time.perf_counter()
        start = fit.bound.params.copy()
        before = fit.objective.held_out_loss(fit.bound.tracer)
        self.guide.field.set_data(params)
        rms = fit_to_field(
            fit.field,
            self.guide.field,
            fit.cfg.width,
            fit.cfg.distil_iterations,
            fit.cfg.seed + fit.it + 1,
            device=fit.distil_device(),
        )
        fit.bound.set_params(fit.field.data(), fit.it)
        if polished:
            self.guide.set_params(last, fit.it)
        else:
            self.guide.field.set_data(self.guide.params)
        after = fit.objective.held_out_loss(fit.bound.tracer)
        kept = after <= before
        if not kept:
            fit.bound.set_params(start, fit.it)
            fit.stream.write(
                f"fit: the grid fitted to step {it} scores worse on the held-out views than "
                f"the start's ({after:.4g} against {before:.4g}): keeping the start's\n"
            )
        return {
            **polished,
            "final_refit": {
                "iteration": it,
                "distilled_rms": rms,
                "held_out_loss": {"start": before, "refit": after},
                "kept": kept,
                "seconds": time.perf_counter() - t0,
            },
        }


def resumed_guide(fit, ckpt) -> tuple:
    """A guided fit's guide (bound) and its eta_max, from the checkpoint."""
    state, path = ckpt.guide, fit.out.checkpoint_path
    if "guide_params" not in state:
        raise ClrefractError(
            f"{path}: the checkpoint holds no field for the hash grid to follow (a run begun "
            "with optimizer 'adam'?)"
        )
    cfg = guide_config(fit.cfg, fit.ds.scene.eta_range[1])
    eta_max = float(state["guide_eta_max"])
    field = make_field(cfg, fit.box, eta_max, int(state["guide_res"]))
    params = np.array(state["guide_params"], np.float64)
    if len(params) != len(field.data()):
        raise ClrefractError(f"{path}: the guide in the checkpoint does not fit its grid")
    field.set_data(params)
    guide = fit.guide_bound(field, cfg)
    guide.set_params(params, fit.it)  # and the cells it skips, as the run it continues did
    return guide, eta_max


def _timed(row: dict, t0: float) -> dict:
    dt = time.perf_counter() - t0
    row.update(seconds=dt, rays_per_s=row.pop("rays") / dt)
    return row


def optimizer_for(fit, guide=None):
    """The fit's optimiser: its guide (bound, eta_max) from a start, else from `fit`'s
    checkpoint where it follows one (`guide` = the checkpoint)."""
    if fit.cfg.optimizer not in ("descent", "line-search"):
        return AdamSteps(fit)
    if not fit.kind.guided(fit.cfg):
        return SmoothedDescent(fit) if fit.cfg.optimizer == "descent" else LineSearch(fit)
    guided = GuidedDescent if fit.cfg.optimizer == "descent" else GuidedLineSearch
    return guided(fit, *guide) if isinstance(guide, tuple) else guided.resumed(fit, guide)
