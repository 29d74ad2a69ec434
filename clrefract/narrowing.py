"""`clrefract fit --resume --width W`: a finished line search given another interface width,
and the judgement of its end against the field it had before.

A fit at 0.5 mm finds the shape that is best for 0.5 mm images; sharper images then ask for
its size and index together (size_search.py). Whether the new field renders the held-out
views better is not known in advance: on the quick sphere the level set gained at 0.25 mm
where the hash grid fitted to it lost 1.8 dB (README, Fitting). So the run remembers its
earlier width in run.json until its next finish, and that finish keeps whichever field
scores the lower held-out loss."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

from .errors import ClrefractError
from .imageio import atomic_path

MARK = "narrowed_from"  # run.json: the width of the field.npz a narrowed run is judged against


def narrow_run(out: Path, width: float) -> None:
    """Give a line-search run another interface width before it is resumed: its best level
    set is searched again at that width (size_search.py) and the grid fitted to it there.
    The tracers' steps follow the width: a hash grid's unless the run set `step`, its level
    set's always."""
    from .fit import _rewrite_config, load_config

    cfg = load_config(out / "config.toml", {})
    if width == cfg.width:
        return
    if cfg.optimizer != "line-search" or cfg.field not in ("levelset", "hashgrid"):
        raise ClrefractError(
            f"{out}: --resume --width {width}: only a line search's level set (a hash grid's "
            "guide) can take another interface width; start a new run"
        )
    new = replace(cfg, width=width)
    new.validate()
    if (out / "field.npz").is_file():
        meta = _read_meta(out)
        if meta is not None:
            # a second narrowing before the finish is judged against the same field.npz
            before = meta.setdefault(MARK, cfg.width)
            if before == width:
                del meta[MARK]
            _write_meta(out, meta)
    _rewrite_config(out, new)


def judge_narrowing(fit) -> dict | None:
    """At the finish of a narrowed run, before its field.npz is overwritten: the earlier
    width's field against the new one on the held-out views, each traced as its run traces
    it. The earlier one stays (as `fit.field`, with config.toml's width back) where its
    loss is lower. What was compared, or None where the run was not narrowed."""
    from .fields import load_field_file
    from .fit import _rewrite_config
    from .render import run_tracer

    meta = _read_meta(fit.out)
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
        new_loss = fit.held_out_loss(run_tracer(fit.field, fit.box, fit.cfg, fit.runtime, False))
        old_loss = fit.held_out_loss(run_tracer(earlier, fit.box, earlier_cfg, fit.runtime, False))
        kept = "earlier" if old_loss <= new_loss else "new"
        result = {
            "earlier_width": before,
            "width": fit.cfg.width,
            "earlier_val_loss": old_loss,
            "val_loss": new_loss,
            "kept": kept,
        }
        if kept == "earlier":
            fit.field, fit.cfg = earlier, earlier_cfg
            _rewrite_config(fit.out, earlier_cfg)
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
    _write_meta(fit.out, meta)
    return result


def _read_meta(out: Path) -> dict | None:
    try:
        return json.loads((Path(out) / "run.json").read_text())
    except (OSError, ValueError):
        return None  # a follower rank's scratch folder, or a run that predates run.json


def _write_meta(out: Path, meta: dict) -> None:
    with atomic_path(Path(out) / "run.json", suffix=".json") as tmp:
        tmp.write_text(json.dumps(meta, indent=2))
