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
again; its phi part is smoothed by `grad_sigma` cells (the index is held: the start searched
it); phi moves by the move in `line_steps` (the largest node move, mm) that lowers the kept
rays' loss most, or stays.
"""

from __future__ import annotations

import time

import numpy as np

from .errors import ClrefractError
from .metrics import psnr_linear_batch
from .tracer import Status


def check_line_search(cfg) -> None:
    """What the line search needs of a fit's config (FitConfig.validate)."""
    if cfg.field != "levelset":
        raise ClrefractError(
            f"optimizer 'line-search' moves a level set's surface; field {cfg.field!r} "
            "uses optimizer 'adam'"
        )
    if not (cfg.keep_growth > 1 and np.isfinite(cfg.keep_growth)):
        raise ClrefractError(f"keep_growth must be above 1, got {cfg.keep_growth}")
    if not (cfg.grad_sigma >= 0 and np.isfinite(cfg.grad_sigma)):
        raise ClrefractError(f"grad_sigma must be >= 0 (0: no smoothing), got {cfg.grad_sigma}")
    try:
        steps = tuple(float(s) for s in cfg.line_steps)
    except (TypeError, ValueError):
        steps = ()
    if not steps or not all(s > 0 and np.isfinite(s) for s in steps):
        raise ClrefractError(f"line_steps must be positive moves in mm, got {cfg.line_steps}")
    cfg.line_steps = steps
    if cfg.env_blur > 0 or cfg.block > 1:
        raise ClrefractError(
            "optimizer 'line-search' compares sharp pixels: set env_blur = 0 and block = 0"
        )


def smoothed(grad_phi: np.ndarray, shape: tuple, sigma: float) -> np.ndarray:
    """The phi gradient smoothed by a Gaussian of sigma grid cells (edge values extended)."""
    if sigma <= 0:
        return grad_phi
    from scipy.ndimage import gaussian_filter

    return gaussian_filter(grad_phi.reshape(shape), sigma, mode="nearest").ravel()


def line_search_step(fit) -> dict:
    """One step of the level set in `fit` (a Fit) on a fresh batch; its metrics row."""
    t0 = time.perf_counter()
    idx = fit._mask_batch(1000 + fit.it)
    first, ok = tame_rays(fit, idx)
    exited = first.status == Status.EXITED
    row = {
        "iteration": fit.it + 1,
        "loss": first.loss,
        "kept": float(ok.mean()),
        "step_mm": 0.0,
        "psnr": psnr_linear_batch(first.radiance[exited], fit.rgb[idx][exited]),
    }
    if ok.any():
        row.update(search_along(fit, idx[ok]))
    fit.it += 1
    dt = time.perf_counter() - t0
    row.update(seconds=dt, rays_per_s=len(idx) / dt)
    return row


def tame_rays(fit, rays: np.ndarray):
    """The loss and gradient of training rays, and which of them exit with an adjoint
    growth of at most keep_growth."""
    first = _loss_and_grad(fit, rays)
    return first, (first.status == Status.EXITED) & (first.growth <= fit.cfg.keep_growth)


def search_along(fit, kept: np.ndarray) -> dict:
    """Move phi along the kept rays' smoothed gradient by the best of line_steps (or not at
    all); their loss before and after, and the move taken."""
    cfg = fit.cfg
    r = _loss_and_grad(fit, kept)
    if not np.all(np.isfinite(r.grad)):
        raise FloatingPointError("non-finite gradient")
    move = np.zeros_like(r.grad)  # the index (last) is held
    move[:-1] = -smoothed(r.grad[:-1], fit.field.phi.shape, cfg.grad_sigma)
    peak = np.abs(move).max()
    best = (r.loss, 0.0)
    if peak > 0:
        move /= peak
        start = fit.params.copy()
        for s in cfg.line_steps:
            set_params(fit, start + s * move)
            loss = fit._forward_loss(kept)
            if loss < best[0]:
                best = (loss, float(s))
        set_params(fit, start + best[1] * move)
    return {"loss_kept": r.loss, "loss_kept_after": best[0], "step_mm": best[1]}


def set_params(fit, params: np.ndarray) -> None:
    """New parameters for the fit's field, on the device."""
    fit.params[:] = params
    fit.field.set_data(fit.params)
    fit._upload(stepped=True)


def _loss_and_grad(fit, rays: np.ndarray):
    return fit.engine.loss_and_grad(
        fit.origins[rays], fit.dirs[rays], fit.rgb[rays], fit._env_full, fit.weights[rays]
    )
