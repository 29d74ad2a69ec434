"""The quasi-Newton finish of a graded medium's descent: L-BFGS (SciPy's L-BFGS-B) on one
fixed set of training rays, from the descent's best grid, preconditioned over octaves of
scale, kept where the held-out views prefer it.

Near its fit a graded medium's loss is close to a quadratic in the nodes' index, and a badly
conditioned one: a ray sees the index's gradient, so the broad part of the error moves the
images least. At the quick plume's last descent step half of the error left lay wider than
4 mm, a quarter wider than 16 mm. L-BFGS works in coordinates z where the grid moves by
S z, S a sum of Gaussian smoothings over octaves from the descent's finest scale to a third
of the box, each weighted so that it moves the first step's grid as far as the others. On
the quick plume's last descent grid, with 16 batches of rays, the held-out loss fell 32% in
7 evaluations; in the descent's 2 mm coordinates 24% in 27. See docs/design/plume-stall.md.
"""

from __future__ import annotations

import time

import numpy as np

from ..log import Progress
from ..smoothing import gaussian_nodes

# the widest smoothing: this share of the box's longest side
WIDEST_OF_BOX = 1 / 3


def octaves(finest_mm: float, box_mm: float) -> list[float]:
    """The preconditioner's scales, mm: finest_mm doubling while within WIDEST_OF_BOX of
    the box."""
    scales = [finest_mm]
    while scales[-1] * 2 <= box_mm * WIDEST_OF_BOX:
        scales.append(scales[-1] * 2)
    return scales


class Preconditioner:
    """S = sum_k w_k G_k over octaves of scale (G_k a Gaussian of sigma_k / sqrt(2), so that
    S S holds each octave at its own sigma), w_k set from a first gradient g so that each
    octave of S S g has the same largest magnitude."""

    def __init__(self, shape: tuple, spacing, scales: list[float], g: np.ndarray):
        self.shape = shape
        self.sigmas = [s / np.sqrt(2) / np.asarray(spacing, np.float64) for s in scales]
        tops = [float(np.abs(self._blur(self._blur(g, s, True), s)).max()) for s in self.sigmas]
        w = np.array([1 / t if t > 0 else 0.0 for t in tops])
        self.weights = np.sqrt(w / w.max()) if w.max() > 0 else np.ones(len(tops))

    def _blur(self, v: np.ndarray, sigma, transpose: bool = False) -> np.ndarray:
        return gaussian_nodes(v.reshape(self.shape), sigma, transpose).ravel()

    def __call__(self, v: np.ndarray) -> np.ndarray:
        return sum(w * self._blur(v, s) for w, s in zip(self.weights, self.sigmas))

    def transposed(self, g: np.ndarray) -> np.ndarray:
        """S^T g: a gradient in the grid's nodes carried to z."""
        return sum(w * self._blur(g, s, True) for w, s in zip(self.weights, self.sigmas))


def quasi_newton_finish(fit, bound, kind, eta_max: float, params, finest_mm: float) -> dict:
    """Polish the grid `params` of `bound` (a descent's nodes) by at most cfg.quasi_newton
    evaluations of the loss and gradient on cfg.quasi_newton_batches training batches drawn
    once, preconditioned from finest_mm up (Preconditioner). Leaves `bound` at the polished
    grid where its held-out loss is lower than `params`' (else at `params`); what it did."""
    from scipy.optimize import minimize

    cfg = fit.cfg
    t0 = time.perf_counter()
    field = bound.field
    shape = kind.descent_grid(field)
    n = int(np.prod(shape))
    base = np.array(params, np.float64)
    rays = fit.rays.drawn_batches(cfg.quasi_newton_batches)
    box_mm = float(np.max(np.asarray(fit.box.hi) - np.asarray(fit.box.lo)))
    scales = octaves(finest_mm, box_mm)

    def grid_at(z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The projected grid at z, and where the projection left it free to move."""
        x = base.copy()
        x[:n] += precondition(z * scale["z"])
        moved = x.copy()
        kind.project(cfg, x, eta_max, bound.free)
        return x, x[:n] == moved[:n]

    def raw(x: np.ndarray) -> tuple[float, np.ndarray]:
        bound.set_params(x, fit.it)
        r = fit.objective.loss_and_grad(bound.engine, rays)
        reg, greg = field.regularizer(x)
        loss, grad = r.loss + cfg.reg * reg, r.grad + cfg.reg * greg
        if not np.isfinite(loss) or not np.all(np.isfinite(grad)):
            raise FloatingPointError("non-finite loss or gradient")
        return loss, grad[:n]

    loss0, g0 = raw(base)  # leaves the nodes at base
    before = fit.objective.held_out_loss(bound.tracer)
    if bound.free is not None:
        g0 = np.where(bound.free[:n], g0, 0.0)
    precondition = Preconditioner(shape, field.spacing, scales, g0)
    # the first step moves the grid as far as the descent's last did
    sg = precondition.transposed(g0)
    top = float(np.abs(precondition(sg)).max())
    rate = cfg.lr * cfg.lr_final
    scale = {"z": rate * float(np.linalg.norm(sg)) / top if top > 0 else 1.0}
    scale["loss"] = 1.0 / loss0 if loss0 > 0 else 1.0
    bar = Progress(cfg.quasi_newton, "quasi-Newton", unit="eval", stream=fit.stream)

    def loss_and_grad(z: np.ndarray) -> tuple[float, np.ndarray]:
        x, free = grid_at(z)
        loss, g = raw(x)
        g = np.where(free, g, 0.0)
        bar.update(1, loss=loss)
        return loss * scale["loss"], precondition.transposed(g) * scale["z"] * scale["loss"]

    # the held-out views judge each iterate: on fixed rays L-BFGS goes on lowering their
    # loss past the grid the held-out views prefer, and on the quick plume their loss rose
    # up to 18% over 20 iterations before it fell 7% below its start (so no early stop)
    best = {"loss": before, "x": base, "iteration": 0}

    def judge(z: np.ndarray) -> None:
        x, _ = grid_at(z)
        bound.set_params(x, fit.it)
        held = fit.objective.held_out_loss(bound.tracer)
        best["iteration"] += 1
        if held < best["loss"]:
            best.update(loss=held, x=x, at=best["iteration"])

    try:
        res = minimize(
            loss_and_grad,
            np.zeros(n),
            jac=True,
            method="L-BFGS-B",
            callback=judge,
            # only the budget ends it: a finer grid spreads the gradient over more nodes, and
            # on the quick Luneburg lens at 128^3 SciPy's default gradient tolerance stopped
            # it after one iteration
            options=dict(
                maxfun=cfg.quasi_newton, maxiter=cfg.quasi_newton, maxcor=10, ftol=0.0, gtol=0.0
            ),
        )
    finally:
        bar.close()
    bound.set_params(best["x"], fit.it)
    kept = best["loss"] < before
    fit.stream.write(
        f"quasi-Newton finish: held-out loss {before:.4g} -> {best['loss']:.4g} "
        f"({'iteration ' + str(best['at']) if kept else 'not kept'} of {best['iteration']}, "
        f"{res.nfev + 1} evaluations)\n"
    )
    return {
        "quasi_newton": {
            "evaluations": int(res.nfev) + 1,
            "iterations": best["iteration"],
            "kept_iteration": best.get("at", 0),
            "rays": int(len(rays)),
            "scales_mm": scales,
            "held_out_loss": {"before": before, "after": best["loss"]},
            "kept": bool(kept),
            "stopped": str(res.message),  # SciPy's reason: the budget, or a failed line search
            "seconds": time.perf_counter() - t0,
        }
    }
