"""A level set's line-search step (`optimizer = "line-search"`): the rays that behave, a
smoothed shape gradient, and the best of a few moves along it.

On glass, a ray that grazes or reflects inside changes its exit by degrees when the surface
moves by 10 nm: a few such rays make the loss of a batch rough at every step a search can
try, and their gradients (truncated at `adjoint_growth_max`) are noise. Without the rays
whose adjoint grows past 10 the loss follows its gradient (on the quick sphere's start, the
change along it within 0.1% of the prediction at 10 nm, 80% at 1 um; README, Fitting). The
raw gradient's steepest directions then fit the batch's pixels with ripples a node wide,
which the test views punish; a Gaussian of a few grid cells keeps the moves that are shapes.

Each step: the loss and adjoint gradient of a batch of rays through the masks; the rays
that exit with an adjoint growth of at most `keep_growth` are kept and their gradient taken
again; its phi part is smoothed over the scales of `grad_sigma` (cells); phi moves by the move
in `line_steps` (the largest node move, mm) that lowers the kept rays' loss most, or stays.

The smoothing is a sum of Gaussians of sigma = 3, 6 and 12 cells weighted by sigma^2: the
larger a shape's error, the more of it one step corrects. A gradient smoothed at one scale
moves a surface's broad errors (a sphere a few tenths of a millimetre too large, a face
tilted) as slowly as its ripples, the way plain gradient descent crawls along the low
frequencies of a Laplacian; weights that grow as sigma^2 approximate the inverse of it (a
Sobolev gradient, as in "large steps" remeshing). On the quick sphere's start, 32 steps
took the held-out loss to 0.0018-0.0019 with the three scales and to 0.0020-0.0023 with
3 cells alone, and the test views to 34.91 dB (+3.22) against 34.59 (+2.90). With
`index_steps`, the index then moves down its gradient by the best of them, or stays (the
start searched it with the hull's shape, which a wrong normal makes look like another index).

A hash grid from the hull takes these steps on the level set it was distilled from (its
`Guide`): the grid's own parameters have no cells to smooth a gradient over. The held-out
views then judge that level set, and the grid is fitted once to the best of its steps
(`refit = "best"`), or again after each move that was taken and judged itself (`"step"`).
"""

from __future__ import annotations

import numpy as np

from ..metrics import psnr_linear_batch
from ..smoothing import gaussian_nodes
from ..tracer import Status
from .rays import Tag


def smoothed(grad_phi: np.ndarray, shape: tuple, sigma) -> np.ndarray:
    """The phi gradient smoothed by a Gaussian of sigma grid cells (edge values extended);
    with several scales, the sum of their smoothings weighted by sigma^2 (a scale of 0 adds
    the gradient itself, weighted 1)."""
    scales = sigma if isinstance(sigma, (list, tuple)) else (sigma,)
    grid = grad_phi.reshape(shape)
    if len(scales) == 1:
        return gaussian_nodes(grid, scales[0]).ravel()
    return sum(gaussian_nodes(grid, s).ravel() * (s * s if s > 0 else 1.0) for s in scales)


def level_set_step(fit, bound) -> dict:
    """One step of a level set (the fit's, or a hash grid's guide) on a fresh batch of mask
    rays; its metrics row, with the rays it traced."""
    cfg = fit.cfg
    idx = fit.rays.mask_batch(Tag.line_step(fit.it), cfg.line_batch)
    first, ok = tame_rays(fit, bound, idx)
    exited = first.status == Status.EXITED
    row = {
        "iteration": fit.it + 1,
        "loss": first.loss,
        "kept": float(ok.mean()),
        "step_mm": 0.0,
        "index_move": 0.0,
        "psnr": psnr_linear_batch(first.radiance[exited], fit.rays.rgb[idx][exited]),
    }
    if ok.any():
        row.update(search_along(fit, bound, idx[ok]))
    row["rays"] = len(idx)
    return row


def tame_rays(fit, bound, rays: np.ndarray):
    """The loss and gradient of training rays (fitted camera centres moved by it), and which
    of them exit with an adjoint growth of at most keep_growth."""
    first = fit.objective.loss_and_grad(bound.engine, rays, step=fit.it)
    return first, (first.status == Status.EXITED) & (first.growth <= fit.cfg.keep_growth)


def search_along(fit, bound, kept: np.ndarray) -> dict:
    """Move phi along the kept rays' smoothed gradient by the best of line_steps (or not at
    all), then the index down its gradient by the best of index_steps (or not at all); their
    loss before and after, and the moves taken."""
    cfg = fit.cfg
    r = fit.objective.loss_and_grad(bound.engine, kept)
    if not np.all(np.isfinite(r.grad)):
        raise FloatingPointError("non-finite gradient")
    move = np.zeros_like(r.grad)  # the index (last) is held
    move[:-1] = -smoothed(r.grad[:-1], bound.field.phi.shape, cfg.grad_sigma)
    peak = np.abs(move).max()
    best = (r.loss, 0.0)
    if peak > 0:
        best = best_move(fit, bound, kept, move / peak, cfg.line_steps, r.loss)
    row = {"loss_kept": r.loss, "step_mm": best[1], "index_move": 0.0}
    if cfg.index_steps and r.grad[-1] != 0:
        before = bound.params[-1]
        along = np.zeros_like(r.grad)
        along[-1] = -np.sign(r.grad[-1])
        best = best_move(fit, bound, kept, along, cfg.index_steps, best[0])
        row["index_move"] = float(bound.params[-1] - before)  # as projected onto its bounds
    row["loss_kept_after"] = best[0]
    row["index"] = float(bound.params[-1])
    return row


def best_move(fit, bound, kept: np.ndarray, direction: np.ndarray, steps, loss: float):
    """Move the parameters along `direction` by the best of `steps` (or not at all) for the
    kept rays, whose loss is `loss` now; (their loss, the step taken)."""
    start = bound.params.copy()
    best = (loss, 0.0)
    for s in steps:
        bound.set_params(start + s * direction, fit.it)
        if np.array_equal(bound.params, start):  # held at its bounds: nothing to trace
            continue
        trial = fit.objective.loss(bound.tracer, kept)
        if trial < best[0]:
            best = (trial, float(s))
    bound.set_params(start + best[1] * direction, fit.it)
    return best
