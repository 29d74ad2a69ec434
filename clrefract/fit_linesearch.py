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

import time
from contextlib import contextmanager
from dataclasses import dataclass

import numpy as np

from .errors import ClrefractError
from .metrics import psnr_linear_batch
from .tracer import Status

# a refit starts where the grid is: its Adam rates a tenth of a fresh distillation's
REFIT_RATE = 0.1
# refit = "best": the one refit to the best step, from the start's fit, as (iterations in
# refit_iterations, rate) in turn. The quick sphere's level set after 30 steps renders
# 35.20 dB; the grid fitted to it 34.20 after 800 at 0.3 (eta RMS 0.00054, 22 s), 34.36
# after 1,600 more at 0.1 (0.00036, 42 s), 33.59 fitted afresh as a start is (2,000 at 1)
FINAL_REFIT = ((4, 0.3), (8, 0.1))


def check_line_search(cfg) -> None:
    """What the line search needs of a fit's config (FitConfig.validate)."""
    if cfg.field == "voxel":
        raise ClrefractError(
            "optimizer 'line-search' moves a surface (a level set's, or the one a hash grid "
            "is distilled from); field 'voxel' uses optimizer 'adam'"
        )
    if cfg.field == "hashgrid" and cfg.init != "hull":
        raise ClrefractError(
            "optimizer 'line-search' moves a hash grid's surface from the visual hull: "
            "set init = 'hull'"
        )
    if cfg.line_batch < 0:
        raise ClrefractError(f"line_batch must be >= 0 (0: batch), got {cfg.line_batch}")
    if cfg.refit_iterations < 1:
        raise ClrefractError(f"refit_iterations must be at least 1, got {cfg.refit_iterations}")
    if cfg.refit not in ("best", "step"):
        raise ClrefractError(f"refit must be 'best' or 'step', got {cfg.refit!r}")
    if not (cfg.keep_growth > 1 and np.isfinite(cfg.keep_growth)):
        raise ClrefractError(f"keep_growth must be above 1, got {cfg.keep_growth}")
    cfg.grad_sigma = smoothing_scales(cfg.grad_sigma)
    try:
        steps = tuple(float(s) for s in cfg.line_steps)
    except (TypeError, ValueError):
        steps = ()
    if not steps or not all(s > 0 and np.isfinite(s) for s in steps):
        raise ClrefractError(f"line_steps must be positive moves in mm, got {cfg.line_steps}")
    cfg.line_steps = steps
    try:
        moves = tuple(float(s) for s in cfg.index_steps)
    except (TypeError, ValueError):
        moves = (-1.0,)
    if not all(s > 0 and np.isfinite(s) for s in moves):
        raise ClrefractError(
            f"index_steps must be positive index moves (or empty), got {cfg.index_steps}"
        )
    cfg.index_steps = moves
    if cfg.env_blur > 0 or cfg.block > 1:
        raise ClrefractError(
            "optimizer 'line-search' compares sharp pixels: set env_blur = 0 and block = 0"
        )


def smoothing_scales(value) -> tuple:
    """grad_sigma as a tuple of scales in cells: one number, or a list of them (0 alone: no
    smoothing)."""
    scales = value if isinstance(value, (list, tuple)) else (value,)
    try:
        scales = tuple(float(s) for s in scales)
    except (TypeError, ValueError):
        scales = ()
    if not scales or not all(s >= 0 and np.isfinite(s) for s in scales):
        raise ClrefractError(
            f"grad_sigma must be one or more scales >= 0 in cells (0: no smoothing), got {value}"
        )
    return scales


def smoothed(grad_phi: np.ndarray, shape: tuple, sigma) -> np.ndarray:
    """The phi gradient smoothed by a Gaussian of sigma grid cells (edge values extended);
    with several scales, the sum of their smoothings weighted by sigma^2 (a scale of 0 adds
    the gradient itself, weighted 1)."""
    scales = sigma if isinstance(sigma, (list, tuple)) else (sigma,)
    if len(scales) == 1:
        return _gaussian(grad_phi, shape, scales[0])
    return sum(_gaussian(grad_phi, shape, s) * (s * s if s > 0 else 1.0) for s in scales)


def _gaussian(grad_phi: np.ndarray, shape: tuple, sigma: float) -> np.ndarray:
    from scipy.ndimage import gaussian_filter

    if sigma <= 0:
        return grad_phi
    return gaussian_filter(grad_phi.reshape(shape), sigma, mode="nearest").ravel()


@dataclass
class Guide:
    """The level set a hash grid's line search moves (the start it was distilled from),
    with its own engine and parameters."""

    field: object
    engine: object
    params: np.ndarray
    eta_max: float

    def state(self) -> dict:
        """What a checkpoint keeps of it."""
        return {
            "guide_params": self.params,
            "guide_res": self.field.phi.shape[0],
            "guide_eta_max": self.eta_max,
        }

    @classmethod
    def restore(cls, fit, state: dict, path) -> Guide:
        """The guide of a resumed fit, from its checkpoint's `state()`."""
        from .fit import make_field

        if "guide_params" not in state:
            raise ClrefractError(
                f"{path}: the checkpoint holds no level set for the hash grid's line search "
                "(a run begun with optimizer 'adam'?)"
            )
        cfg = fit.guide_config()
        eta_max = float(state["guide_eta_max"])
        field = make_field(cfg, fit.box, eta_max, int(state["guide_res"]))
        params = np.array(state["guide_params"], np.float64)
        if len(params) != len(field.data()):
            raise ClrefractError(f"{path}: the line search's level set does not fit its grid")
        field.set_data(params)
        guide = cls(field, engine=fit._engine_for(field, cfg.step), params=params, eta_max=eta_max)
        with on_guide(fit, guide):
            fit._upload()  # and the cells it skips, as the run it continues did
        return guide


@contextmanager
def on_guide(fit, guide=None):
    """`fit` with its guide's (or `guide`'s) field, engine and parameters in place of its
    own."""
    guide = guide or fit.guide
    own = fit.field, fit.engine, fit.params
    fit.field, fit.engine, fit.params = guide.field, guide.engine, guide.params
    try:
        yield
    finally:
        fit.field, fit.engine, fit.params = own


def line_search_step(fit) -> dict:
    """One step of the level set in `fit` (a Fit), or of its guide, on a fresh batch; its
    metrics row."""
    t0 = time.perf_counter()
    if fit.guide is None:
        row = _level_set_step(fit)
    else:
        with on_guide(fit):
            row = _level_set_step(fit)
        if row["index_move"]:
            fit.set_eta_max(fit.cfg.hashgrid_eta_max(fit.guide.params[-1]))
        if row["step_mm"] > 0 and fit.cfg.refit == "step":
            row["distilled_rms"] = refit(fit, fit.cfg.refit_iterations)
    fit.it += 1
    dt = time.perf_counter() - t0
    row.update(seconds=dt, rays_per_s=row.pop("rays") / dt)
    return row


def refit(fit, iterations: int, rate: float = REFIT_RATE) -> float:
    """Fit the hash grid to its guide again, from where it is; the RMS error of eta."""
    from .fit import fit_to_field

    rms = fit_to_field(
        fit.field,
        fit.guide.field,
        fit.cfg.width,
        iterations,
        fit.cfg.seed + fit.it + 1,
        rate=rate,
        device=fit.distil_device(),
    )
    set_params(fit, fit.field.data())
    return rms


def refit_to_best(fit, moved: bool = False) -> dict | None:
    """With refit = "best": the hash grid fitted to its guide's best-validated step (the
    last without validation) from the start's fit (FINAL_REFIT's iterations), the
    guide left at its last step; what that took, or None where the best is the start, whose
    level set the grid holds already, and the size search did not `move` it."""
    _, it, params = fit.best
    if params is None:  # none validated: the last step
        it, params = fit.it, fit.guide.params.copy()
    if it == 0 and not moved:
        return None
    t0 = time.perf_counter()
    # the refit samples the level set on the host: nothing to upload, and the guide's own
    # parameters stay at its last step, where --resume goes on
    fit.guide.field.set_data(params)
    fit.set_eta_max(fit.best_eta_max or fit.eta_max)
    for times, rate in FINAL_REFIT:
        rms = refit(fit, times * fit.cfg.refit_iterations, rate)
    fit.guide.field.set_data(fit.guide.params)
    return {"iteration": it, "distilled_rms": rms, "seconds": time.perf_counter() - t0}


def _level_set_step(fit) -> dict:
    idx = fit._mask_batch(1000 + fit.it, fit.cfg.line_batch)
    first, ok = tame_rays(fit, idx)
    exited = first.status == Status.EXITED
    row = {
        "iteration": fit.it + 1,
        "loss": first.loss,
        "kept": float(ok.mean()),
        "step_mm": 0.0,
        "index_move": 0.0,
        "psnr": psnr_linear_batch(first.radiance[exited], fit.rgb[idx][exited]),
    }
    if ok.any():
        row.update(search_along(fit, idx[ok]))
    row["rays"] = len(idx)
    return row


def tame_rays(fit, rays: np.ndarray):
    """The loss and gradient of training rays, and which of them exit with an adjoint
    growth of at most keep_growth."""
    first = _loss_and_grad(fit, rays)
    return first, (first.status == Status.EXITED) & (first.growth <= fit.cfg.keep_growth)


def search_along(fit, kept: np.ndarray) -> dict:
    """Move phi along the kept rays' smoothed gradient by the best of line_steps (or not at
    all), then the index down its gradient by the best of index_steps (or not at all); their
    loss before and after, and the moves taken."""
    cfg = fit.cfg
    r = _loss_and_grad(fit, kept)
    if not np.all(np.isfinite(r.grad)):
        raise FloatingPointError("non-finite gradient")
    move = np.zeros_like(r.grad)  # the index (last) is held
    move[:-1] = -smoothed(r.grad[:-1], fit.field.phi.shape, cfg.grad_sigma)
    peak = np.abs(move).max()
    best = (r.loss, 0.0)
    if peak > 0:
        best = best_move(fit, kept, move / peak, cfg.line_steps, r.loss)
    row = {"loss_kept": r.loss, "step_mm": best[1], "index_move": 0.0}
    if cfg.index_steps and r.grad[-1] != 0:
        before = fit.params[-1]
        along = np.zeros_like(r.grad)
        along[-1] = -np.sign(r.grad[-1])
        best = best_move(fit, kept, along, cfg.index_steps, best[0])
        row["index_move"] = float(fit.params[-1] - before)  # as projected onto its bounds
    row["loss_kept_after"] = best[0]
    row["index"] = float(fit.params[-1])
    return row


def best_move(fit, kept: np.ndarray, direction: np.ndarray, steps, loss: float):
    """Move the parameters along `direction` by the best of `steps` (or not at all) for the
    kept rays, whose loss is `loss` now; (their loss, the step taken)."""
    start = fit.params.copy()
    best = (loss, 0.0)
    for s in steps:
        set_params(fit, start + s * direction)
        if np.array_equal(fit.params, start):  # held at its bounds: nothing to trace
            continue
        trial = fit._forward_loss(kept)
        if trial < best[0]:
            best = (trial, float(s))
    set_params(fit, start + best[1] * direction)
    return best


def set_params(fit, params: np.ndarray) -> None:
    """New parameters for the fit's field, on the device, with the occupancy rebuilt from
    them: a resumed run then skips the same cells (in float32 a flight rounds otherwise
    than the steps it replaces), and a step's moves are few."""
    fit.params[:] = params
    fit.field.set_data(fit.params)
    fit._upload()


def _loss_and_grad(fit, rays: np.ndarray):
    return fit.engine.loss_and_grad(
        fit.origins[rays], fit.dirs[rays], fit.rgb[rays], fit._env_full, fit.weights[rays]
    )
