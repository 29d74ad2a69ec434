"""How a fit finishes.

The size and index search, the last move of a line search: its best level set grown or
shrunk uniformly and its index moved, together.

A glass object a little too small with an index a little too low renders much like the
truth: the quick drop's best step lay 0.17 mm inside the true surface everywhere (p10 /
p90 -0.19 / -0.14 mm) at index 1.316 for 1.33. The line search's smoothed steps move the
surface and leave the index (`index_steps` off), so they do not go along that valley, and
neither a growth alone nor an index alone leaves it: at a 0.25 mm interface the drop's
test views scored 34.86 dB, 32.87 grown by 0.17 mm, 33.70 at index 1.33, and 36.09 grown
by 0.1 mm at 1.325. A pattern search over both, on the loss of a fixed batch of training
mask rays, finds the valley's floor in a few dozen traces; the held-out views keep it only
if their loss falls too.

`--resume --width W` (narrow_run) gives a finished line search another interface width;
its finish is judged against the field it had before (judge_narrowing). A fit at 0.5 mm
finds the shape that is best for 0.5 mm images; sharper images then ask for its size and
index together. Whether the new field renders the held-out views better is not known in
advance: on the quick sphere the level set gained at 0.25 mm where the hash grid fitted to
it lost 1.8 dB. So the run remembers its earlier width in run.json until its next finish,
and that finish keeps whichever field scores the lower held-out loss.
"""

from __future__ import annotations

import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from ..errors import ClrefractError
from .rays import Tag
from .runfolder import Best, RunFolder

# the growth steps (mm): the first, and the last before the search stops
GROW_STEPS = (0.05, 0.0125)
# the first index step, as a share of the index contrast n - 1 (0.01 at index 1.5)
INDEX_STEP = 0.02
MARK = "narrowed_from"  # run.json: the width of the field.npz a narrowed run is judged against


def size_index_search(fit, bound, guided: bool = False) -> dict:
    """Search the growth and index of the best parameters of `bound` (a level set: the
    fit's, or a hash grid's guide) on training mask rays; with the held-out loss lower
    there, make them the fit's best. What it did."""
    t0 = time.perf_counter()
    best = fit.best
    last = bound.params.copy()
    base = (last if best.params is None else best.params).copy()
    top = bound.field.eta_bound or np.inf
    rays = fit.rays.mask_batch(Tag.SIZE_SEARCH, fit.cfg.line_batch)
    losses: dict = {}

    def params_at(grow: float, index: float) -> np.ndarray:
        p = base.copy()
        p[:-1] -= grow
        p[-1] = index
        return p

    def loss(grow: float, index: float) -> float:
        key = (round(grow, 6), round(index, 7))
        if key not in losses:
            bound.set_params(params_at(grow, index), fit.it)
            losses[key] = fit.objective.loss(bound.tracer, rays)
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
    bound.set_params(base, fit.it)
    held = [fit.objective.held_out_loss(bound.tracer)] * 2
    if (grow, index) != (0.0, float(base[-1])):
        bound.set_params(params_at(grow, index), fit.it)
        held[1] = fit.objective.held_out_loss(bound.tracer)
    kept = held[1] < held[0]
    bound.set_params(last, fit.it)
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
        top_there = fit.kind.eta_top(fit.cfg, index) if guided else best.eta_max
        fit.best = Best(held[1], best.iteration, params_at(grow, index), top_there)
    verdict = "kept" if kept else "not kept: the held-out views disagree"
    fit.stream.write(
        f"size and index: grown {grow:+.4f} mm, index {base[-1]:.4f} -> {index:.4f}, "
        f"held-out loss {held[0]:.5g} -> {held[1]:.5g} ({verdict}; {len(losses)} traces, "
        f"{row['seconds']:.0f} s)\n"
    )
    return row


def narrow_run(out: Path, width: float) -> None:
    """Give a line-search run another interface width before it is resumed: its best level
    set is searched again at that width and the grid fitted to it there. The tracers' steps
    follow the width: a hash grid's unless the run set `step`, its level set's always."""
    folder = RunFolder(out)
    cfg = folder.config()
    if width == cfg.width:
        return
    if cfg.optimizer != "line-search":
        raise ClrefractError(
            f"{out}: --resume --width {width}: only a line search's level set (a hash grid's "
            "guide) can take another interface width; start a new run"
        )
    new = replace(cfg, width=width)
    new.validate()
    if (folder / "field.npz").is_file():
        meta = folder.meta()
        if meta is not None:
            # a second narrowing before the finish is judged against the same field.npz
            before = meta.setdefault(MARK, cfg.width)
            if before == width:
                del meta[MARK]
            folder.write_meta(meta)
    folder.write_config(new)


def judge_narrowing(fit) -> dict | None:
    """At the finish of a narrowed run, before its field.npz is overwritten: the earlier
    width's field against the new one on the held-out views, each traced as its run traces
    it. The earlier one stays (the fit adopts it, with config.toml's width back) where its
    loss is lower. What was compared, or None where the run was not narrowed."""
    from ..fields import load_field_file

    meta = fit.out.meta()
    if meta is None or MARK not in meta:
        return None
    before = float(meta.pop(MARK))
    path = fit.out / "field.npz"
    result, earlier = None, None
    if path.is_file():
        try:
            earlier = load_field_file(path, fit.box)
        except ClrefractError as exc:  # the new field is saved over it: say so, go on
            fit.stream.write(f"fit: the earlier width's field is not judged: {exc}\n")
    if earlier is not None:
        earlier_cfg = replace(fit.cfg, width=before)
        held = fit.objective.held_out_loss
        new_loss = held(fit.forward_tracer(fit.field, interface_steps=False))
        old_loss = held(fit.forward_tracer(earlier, earlier_cfg, interface_steps=False))
        kept = "earlier" if old_loss <= new_loss else "new"
        result = {
            "earlier_width": before,
            "width": fit.cfg.width,
            "earlier_val_loss": old_loss,
            "val_loss": new_loss,
            "kept": kept,
        }
        if kept == "earlier":
            fit.adopt(earlier, earlier_cfg)
            fit.out.write_config(earlier_cfg)
            fit.stream.write(
                f"fit: the field at width {before:g} mm scores a lower held-out loss than at "
                f"{result['width']:g} mm ({old_loss:.5g} against {new_loss:.5g}): it stays, "
                f"and {fit.out / 'config.toml'} has width {before:g} again\n"
            )
        else:
            fit.stream.write(
                f"fit: at width {result['width']:g} mm the held-out loss is {new_loss:.5g}, "
                f"against {old_loss:.5g} at {before:g} mm\n"
            )
    fit.out.write_meta(meta)
    return result


# each face's offset, by these steps (mm) in turn, after the polytope's Adam: a face's
# offset moves no ray's direction, only which face a ray meets near an edge, so its gradient
# is that of a few rays and Adam left the quick prism's faces up to 0.18 mm off
FACE_STEPS = (0.2, 0.1, 0.05, 0.02)
FACE_SWEEPS = 3  # sweeps over the faces per step, while one moves
FACE_TRIES = (-2.0, -1.0, 1.0, 2.0)
FACE_RAYS = 4  # times the batch: an edge is a few pixels of a view
# losses the search traces at most: the prism's and the cut stones' (5 to 11 faces) take 240
# to 530; a cylinder held by 27 rounded (marched) faces took 8.8 minutes to fit without the
# cap, 7.2 with it, to the same faces
FACE_BUDGET = 600


def face_offsets(fit) -> dict:
    """Move each face of the fit's polytope (its best parameters) by the offset of lowest
    loss on a fixed batch of mask rays; the held-out views keep the move only if their loss
    falls too. What the finish did."""
    t0 = time.perf_counter()
    bound = fit.bound
    idx = fit.rays.mask_batch(Tag.SIZE_SEARCH, FACE_RAYS * fit.cfg.batch)
    before = bound.params.copy()
    held_before = fit.held_out_loss()

    def loss_of(p):
        bound.set_params(p, fit.it)
        return fit.loss(idx)

    params, loss = before.copy(), loss_of(before)
    faces = bound.field.n_planes
    traced = 0
    for step in FACE_STEPS:
        for _ in range(FACE_SWEEPS):
            start = loss
            for j in range(faces):
                for delta in step * np.array(FACE_TRIES):
                    if traced >= FACE_BUDGET:
                        break
                    trial = params.copy()
                    trial[4 * j + 3] += delta
                    t = loss_of(trial)
                    traced += 1
                    if t < loss:
                        params, loss = trial, t
            if loss == start:
                break
    bound.set_params(params, fit.it)
    held = fit.held_out_loss()
    kept = held < held_before
    if not kept:
        bound.set_params(before, fit.it)
    moved = np.abs(params[3 : 4 * faces : 4] - before[3 : 4 * faces : 4])
    fit.stream.write(
        f"finish: faces moved up to {moved.max():.2f} mm, held-out loss {held_before:.4g} -> "
        f"{held:.4g} ({'kept' if kept else 'not kept'})\n"
    )
    return {
        "face_search": {
            "kept": bool(kept),
            "moved_mm": float(moved.max()),
            "losses": traced,
            "held_out_before": float(held_before),
            "held_out_after": float(held),
            "seconds": time.perf_counter() - t0,
        }
    }
