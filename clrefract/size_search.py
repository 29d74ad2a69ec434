"""The last move of a line search: its best level set grown or shrunk uniformly and its index
moved, together.

A glass object a little too small with an index a little too low renders much like the
truth: the quick drop's best step lay 0.17 mm inside the true surface everywhere (p10 /
p90 -0.19 / -0.14 mm) at index 1.316 for 1.33. The line search's smoothed steps move the
surface and leave the index (`index_steps` off), so they do not go along that valley, and
neither a growth alone nor an index alone leaves it: at a 0.25 mm interface the drop's
test views scored 34.86 dB, 32.87 grown by 0.17 mm, 33.70 at index 1.33, and 36.09 grown
by 0.1 mm at 1.325. A pattern search over both, on the loss of a fixed batch of training
mask rays, finds the valley's floor in a few dozen traces; the held-out views keep it only
if their loss falls too.
"""

from __future__ import annotations

import time
from contextlib import nullcontext

import numpy as np

from .fit_linesearch import on_guide, set_params

# the growth steps (mm): the first, and the last before the search stops
GROW_STEPS = (0.05, 0.0125)
# the first index step, as a share of the index contrast n - 1 (0.01 at index 1.5)
INDEX_STEP = 0.02
SEARCH_TAG = 3000  # the fixed batch's tag (Fit._mask_batch)


def size_index_search(fit) -> dict | None:
    """Search the growth and index of the fit's best level set (a hash grid's guide's) on
    training mask rays; with the held-out loss lower there, make it the fit's best. Returns
    what it did, or None where the fit has no level set to search."""
    guide = fit.guide is not None
    if not (fit.validates_guide() if guide else fit.cfg.field == "levelset"):
        return None  # a grid refitted after every step: its best holds the grid's own
    t0 = time.perf_counter()
    _, it, best = fit.best
    with on_guide(fit) if guide else nullcontext():
        last = fit.params.copy()
        base = (last if best is None else best).copy()
        top = fit.field.eta_bound or np.inf
        rays = fit._mask_batch(SEARCH_TAG, fit.cfg.line_batch)
        losses: dict = {}

        def params_at(grow: float, index: float) -> np.ndarray:
            p = base.copy()
            p[:-1] -= grow
            p[-1] = index
            return p

        def loss(grow: float, index: float) -> float:
            key = (round(grow, 6), round(index, 7))
            if key not in losses:
                set_params(fit, params_at(grow, index))
                losses[key] = fit._forward_loss(rays)
            return losses[key]

        grow, index = 0.0, float(base[-1])
        dg, de = GROW_STEPS[0], INDEX_STEP * (index - 1.0)
        low = first = loss(grow, index)
        while dg >= GROW_STEPS[1] and de > 0:
            moves = [(grow + a * dg, index + b * de) for a in (-1, 0, 1) for b in (-1, 0, 1)]
            moves = [(g, e) for g, e in moves if 1.0 < e <= top and (g, e) != (grow, index)]
            scored = [(loss(g, e), g, e) for g, e in moves]
            found = min(scored) if scored else (np.inf, grow, index)
            if found[0] < low:
                low, grow, index = found
            else:
                dg, de = dg / 2, de / 2
        # the base's held-out loss is traced again, not taken from fit.best: after
        # --resume --width it was measured at another width
        set_params(fit, base)
        held = [fit.held_out_loss()] * 2
        if (grow, index) != (0.0, float(base[-1])):
            set_params(fit, params_at(grow, index))
            held[1] = fit.held_out_loss()
        kept = held[1] < held[0]
        set_params(fit, last)
    row = {
        "grow_mm": grow,
        "index": [float(base[-1]), index],
        "train_loss": [first, low],
        "held_out_loss": held,
        "kept": bool(kept),
        "traces": len(losses),
        "seconds": time.perf_counter() - t0,
    }
    if kept:
        fit.best = (held[1], it, params_at(grow, index))
        if guide:
            fit.best_eta_max = fit.cfg.hashgrid_eta_max(index)
    verdict = "kept" if kept else "not kept: the held-out views disagree"
    fit.stream.write(
        f"size and index: grown {grow:+.4f} mm, index {base[-1]:.4f} -> {index:.4f}, "
        f"held-out loss {held[0]:.5g} -> {held[1]:.5g} ({verdict}; {len(losses)} traces, "
        f"{row['seconds']:.0f} s)\n"
    )
    return row
