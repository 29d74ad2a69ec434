"""The training loop: steps, validation, patience, divergence, Ctrl-C and checkpoints, then
the finish. Batches, the blur and the grid are functions of (seed, iteration), so a resumed
run repeats exactly what an uninterrupted one would have done."""

from __future__ import annotations

import json
import math
import signal
import threading

from ..errors import ClrefractError
from ..log import Progress
from .finishes import judge_narrowing


class FitDiverged(ClrefractError):
    """A fit stopped because its numbers blew up; its run folder holds the last good state
    (field.npz, checkpoint.npz, results.json with "stopped")."""

    def __init__(self, message: str, result: dict):
        super().__init__(message)
        self.result = result


def train(fit, until: int | None = None) -> dict:
    """Run `fit` (a trainer.Fit, started or resumed) to its end, its results; or only to
    iteration `until`, checkpointed there ({}: a probe, which a resumed run continues)."""
    cfg = fit.cfg
    end = cfg.iterations if until is None else min(until, cfg.iterations)
    bar = Progress(end, "fit", unit="it", stream=fit.stream, initial=min(fit.it, end))
    last_ckpt = fit.it
    try:
        with fit.out.open_metrics() as metrics, StopOnInterrupt() as stop:
            while fit.it < end and not out_of_patience(fit):
                if stop.requested:
                    fit.save_checkpoint()
                    raise ClrefractError(
                        f"interrupted at iteration {fit.it}; checkpoint saved in "
                        f"{fit.out}: continue with --resume"
                    )
                if fit.it == 0 and not fit.best.found:
                    start_val = fit.track_best()  # the start is a candidate too
                    if start_val is not None:
                        fit.record["start_val_loss"] = start_val
                        fit.out.record_start_loss(start_val)
                        fit.optimizer.validated(fit, start_val)
                row = fit.step()
                fit.solve_centres()
                val = fit.track_best()
                if val is not None:
                    row["val_loss"] = val
                    fit.optimizer.validated(fit, val)
                metrics.write(json.dumps(row) + "\n")
                metrics.flush()
                blown = blown_up(fit, val)
                if blown:
                    return stop_diverged(fit, blown, fit.it)
                bar.update(
                    1, loss=row["loss"], psnr=round(row["psnr"], 2), rays_s=int(row["rays_per_s"])
                )
                if fit.it % cfg.checkpoint_every == 0:
                    fit.save_checkpoint()
                    last_ckpt = fit.it
    except KeyboardInterrupt:
        # a second Ctrl-C may have cut an update short: keep the last whole checkpoint
        raise ClrefractError(
            f"interrupted; the checkpoint of iteration {last_ckpt} in {fit.out} is "
            "intact: continue with --resume"
        ) from None
    except FloatingPointError as exc:
        return stop_diverged(fit, str(exc), fit.it + 1)
    finally:
        bar.close()  # a run stopped early (patience) leaves its bar short of the total
    fit.save_checkpoint()
    if fit.it < cfg.iterations and not fit.record.get("stopped_without_progress"):
        return {}  # a probe's end, not the run's
    fit.record.update(fit.optimizer.finish(fit))
    fit.record["narrowing"] = judge_narrowing(fit)  # may keep the earlier width's field.npz
    fit.out.save_field(fit.field)
    fit.write_centres()
    return report(fit)


def report(fit) -> dict:
    """results.json and the figures of a finished run (none on an MPI follower)."""
    if not fit.out.writes:
        return {}
    from ..report import write_fit_report

    return write_fit_report(fit)


def out_of_patience(fit) -> bool:
    """Whether the last `patience` validated steps found no better held-out loss; says so
    once, and results.json records it."""
    cfg = fit.cfg
    waited = fit.it - fit.best.iteration
    if not cfg.patience or not fit.best.found:
        return False  # no validated step yet (or none asked for)
    if waited < cfg.patience * cfg.validate_every:
        return False
    fit.record["stopped_without_progress"] = {
        "at_iteration": fit.it,
        "best_iteration": fit.best.iteration,
    }
    fit.stream.write(
        f"fit: no better held-out loss in the {waited} steps since step {fit.best.iteration}: "
        f"stopped (patience = {cfg.patience}; 0 runs every step)\n"
    )
    return True


def blown_up(fit, val: float | None) -> str:
    """Why the held-out loss says the fit diverged ("" if it does not)."""
    if val is None:
        return ""
    if not math.isfinite(val):
        return "non-finite held-out loss"
    best, factor = fit.best.loss, fit.cfg.diverge_factor
    if factor and math.isfinite(best) and val > factor * best:
        return f"held-out loss {val:.4g} is {val / best:.1f}x its best {best:.4g}"
    return ""


def stop_diverged(fit, reason: str, at: int):
    """End a diverged run with what it had before: the best validated parameters (else the
    last finite ones) as field.npz, the checkpoint rolled back to their iteration with
    fresh Adam moments (the old ones carry the blow-up), and results.json; then raise
    FitDiverged with one line saying why and what was kept."""
    best = fit.best
    top = fit.eta_max
    if best.params is not None and fit.optimizer.judged(fit) is not fit.bound:
        fit.record.update(fit.optimizer.finish(fit))  # the grid fitted to its guide's best
        fit.it, kept = best.iteration, "the best on held-out views"
        top = fit.eta_max
    elif best.params is not None and len(best.params) == len(fit.params):
        fit.params[:] = best.params
        fit.it, kept = best.iteration, "the best on held-out views"
        top = best.eta_max or top
    else:
        kept = "the last finite parameters"
    fit.field.set_data(fit.params)
    fit.set_eta_max(top)
    fit.optimizer.reset(fit)
    fit.record["stopped"] = {"reason": reason, "at_iteration": at, "field_iteration": fit.it}
    fit.save_checkpoint()
    fit.out.save_field(fit.field)
    result = report(fit)
    raise FitDiverged(
        f"fit diverged at iteration {at} ({reason}); {fit.out} holds the field of "
        f"iteration {fit.it} ({kept}) and its checkpoint: lower the learning rate in "
        f"{fit.out / 'config.toml'} and --resume",
        result,
    )


class StopOnInterrupt:
    """Ctrl-C ends the run after the iteration in flight, so the checkpoint is consistent;
    a second Ctrl-C interrupts at once."""

    def __init__(self):
        self.requested = False
        self._old = None

    def _handler(self, signum, frame):
        if self.requested:
            raise KeyboardInterrupt
        self.requested = True

    def __enter__(self):
        if threading.current_thread() is threading.main_thread():
            self._old = signal.signal(signal.SIGINT, self._handler)
        return self

    def __exit__(self, *exc):
        if self._old is not None:
            signal.signal(signal.SIGINT, self._old)
        return False
