"""`clrefract fit --field hashgrid` on a small glass sphere: it starts where a level set
does (the visual hull filled by line search, fitted into the hash grid), in the object's
box, and its run folder works like the other fields' (resume, field file, scores)."""

import dataclasses
import json
import re

import numpy as np
import pytest

from clrefract.fields import load_field_file
from clrefract.fields.hashgrid import HashGridField
from clrefract.fit import load_config, prepare_fit
from clrefract.fit.rays import batch_indices, held_out_views
from clrefract.fit.starts import search_losses


def _cfg(**kw):
    # the default optimiser (the line search), at the 1 mm interface the figures below were
    # measured with: 48 x 48 pixels see 2 mm each, and a 0.5 mm one doubles the steps
    base = dict(
        field="hashgrid",
        width=1.0,
        res=32,
        iterations=4,
        batch=2048,
        distil_iterations=300,
        levels=6,
        log2_table=14,
        hidden=16,
        validate_every=2,
        checkpoint_every=2,
        test_views=2,
    )
    base.update(kw)
    return load_config(None, base)


@pytest.mark.benchmark  # about 100 s; test_a_small_hash_grid_starts_from_the_hull
def test_hash_grid_starts_from_the_hull_in_the_objects_box(sphere_25x48, tmp_path):
    import io

    sphere = sphere_25x48

    log = io.StringIO()
    # a run of two steps and its resume; what steps gain is test_fit_linesearch's to show.
    # The sphere's start is its smoothed visual hull: the tightened and hollow shapes, and
    # the search's count with them, are test_levelset's and test_family_fit's
    cfg = _cfg(iterations=2, refit_iterations=100, tighten_hull=False, shell_starts=False)
    fit = prepare_fit(sphere, tmp_path / "run", cfg, stream=log)
    # the search's and the distillation's progress (minutes each on the quick protocol)
    lines = re.split(r"[\r\n]", log.getvalue())  # tqdm redraws after carriage returns
    total = 1 + search_losses(8, [6])  # the hull's six smoothings
    assert any(line.startswith("start:") and f" {total}/{total} " in line for line in lines)
    assert any(line.startswith("distil:") and " 300/300 " in line for line in lines)
    info = json.loads((tmp_path / "run" / "init.json").read_text())
    start = json.loads((tmp_path / "run" / "start.json").read_text())
    assert abs(info["eta"] - 1.5) < 0.06, info
    assert info["distilled_rms"] < 0.03, info
    assert np.all(fit.box.size < 70) and np.all(fit.box.size > 40)
    # against the empty box (the field's own initialisation, eta = 1), 48 x 48 pixels:
    # measured +2.5 dB. Before the index headroom and a step of a quarter of the interface
    # it was +0.2 to +1.0 dB, as noise in eta inside the glass bent every ray
    empty = _empty_scores(fit)
    assert start["test_psnr"] > empty["test_psnr"] + 1.5, (start, empty)
    assert fit.eta_max < 1 + (info["eta"] - 1) * 1.05
    assert start["eta_rmse"] < empty["eta_rmse"] / 2, (start, empty)
    assert start["chamfer_mm"] < 1.0, start
    result = fit.run()
    assert np.isfinite(result["test_psnr"])
    assert "start" in result and "psnr_gain_over_start" in result
    field = load_field_file(tmp_path / "run" / "field.npz")
    assert isinstance(field, HashGridField)
    # a resumed run rebuilds the same field: eta_max from the run's checkpoint, not the
    # scene's bound (the size search at the run's end may have moved the field's since: it
    # is the run's last move, which a resumed run makes again after its steps)
    again = prepare_fit(sphere, tmp_path / "run", cfg, resume=True)
    with np.load(tmp_path / "run" / "checkpoint.npz") as z:
        top = float(z["eta_max"])
    assert again.field.config == dataclasses.replace(fit.field.config, eta_max=top)
    assert top < 1 + (info["eta"] - 1) * 1.05
    assert field.box.to_dict() == fit.box.to_dict()


def test_a_small_hash_grid_starts_from_the_hull(sphere_12x24, tmp_path):
    """The benchmark above on the 24 x 24 sphere, a small grid (4 levels of 2^12) at a 2 mm
    interface on 16^3 nodes, one step: the same start, reports, run folder and resume. The
    coarse views set the bounds: the start's index 1.34 (the pixels blur the rim), an object
    box of 69 mm, half the empty box's eta RMSE, a surface 2.0 mm off; the grid holds its
    level set to an RMS error of eta of 0.024. Its test view's PSNR is not held to the empty
    box's: on one view of 24 x 24 pixels it moved by 1.5 dB between runs (the threads of the
    distillation add in any order), from 0.2 below to 1.3 above it."""
    import io

    log = io.StringIO()
    cfg = _cfg(
        width=2.0,
        res=16,
        levels=4,
        log2_table=12,
        hidden=16,
        distil_iterations=50,
        batch=512,
        iterations=1,
        refit_iterations=10,
        tighten_hull=False,
        shell_starts=False,
        validate_every=1,
        checkpoint_every=1,
        test_views=1,
    )
    fit = prepare_fit(sphere_12x24, tmp_path / "run", cfg, stream=log)
    lines = re.split(r"[\r\n]", log.getvalue())  # tqdm redraws after carriage returns
    total = 1 + search_losses(8, [6])
    assert any(line.startswith("start:") and f" {total}/{total} " in line for line in lines)
    assert any(line.startswith("distil:") and " 50/50 " in line for line in lines)
    info = json.loads((tmp_path / "run" / "init.json").read_text())
    start = json.loads((tmp_path / "run" / "start.json").read_text())
    assert abs(info["eta"] - 1.5) < 0.2, info
    assert info["loss"] < info["loss_empty"] / 2, info
    assert info["distilled_rms"] < 0.05, info
    assert np.all(fit.box.size < 80) and np.all(fit.box.size > 40)  # not the scene's 100 mm
    empty = _empty_scores(fit)
    assert np.isfinite(start["test_psnr"]) and np.isfinite(empty["test_psnr"])
    assert fit.eta_max < 1 + (info["eta"] - 1) * 1.05
    assert start["eta_rmse"] < 0.7 * empty["eta_rmse"], (start, empty)
    assert start["chamfer_mm"] < 3.0, start
    result = fit.run()
    assert np.isfinite(result["test_psnr"])
    assert "start" in result and "psnr_gain_over_start" in result
    field = load_field_file(tmp_path / "run" / "field.npz")
    assert isinstance(field, HashGridField)
    again = prepare_fit(sphere_12x24, tmp_path / "run", cfg, resume=True)
    with np.load(tmp_path / "run" / "checkpoint.npz") as z:
        top = float(z["eta_max"])
    assert again.field.config == dataclasses.replace(fit.field.config, eta_max=top)
    assert top < 1 + (info["eta"] - 1) * 1.05
    assert field.box.to_dict() == fit.box.to_dict()


def _empty_scores(fit) -> dict:
    from clrefract.fields.voxel import VoxelGrid
    from clrefract.report import score_field

    return score_field(fit, VoxelGrid(np.ones((8, 8, 8)), fit.box))


def test_held_out_views_are_spread_and_never_trained_on(sphere_25x48, tmp_path):
    sphere = sphere_25x48
    cfg = _cfg(val_views=4)
    assert held_out_views(cfg, 20) == [2, 7, 12, 17]
    assert held_out_views(cfg, 9) == [4]
    assert held_out_views(cfg, 4) == []
    # the split is the field's and the start's alike: an empty voxel grid needs no search
    fit = prepare_fit(sphere, tmp_path / "run", _cfg(field="voxel", init="empty", val_views=4))
    n = fit.ds.train[0].width * fit.ds.train[0].height
    held = {int(i) // n for i in fit.rays.held}
    assert held == set(held_out_views(cfg, len(fit.ds.train)))
    marked = fit.rays.marked_pool()  # the rays a start searches and the mask share draws
    assert len(marked) > 1000 and not set((marked // n).tolist()) & held
    for it in range(3):
        idx = batch_indices(fit.cfg, it, fit.rays.pool)
        assert not set((idx // n).tolist()) & held
