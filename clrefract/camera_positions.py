"""`clrefract dataset refine-positions`: each training camera's centre, moved so that a fitted
field renders its photograph best (view_offsets.py's solve, once, against a run's field).

`register-env --poses` turns each camera onto the panorama, but the panorama is at infinity:
no background pixel moves when a camera moves, so it says nothing of where a camera stands.
Only the object does (its silhouette, and what it refracts), so the positions are fitted
against a fitted field.

The field's own position is the gauge: a shift common to every camera is a shift of the
object, so the offsets are relative to where the fit put it. Test views keep their recorded
poses, so that their scores stay an honest measure.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .calibrate import read_json, write_json
from .dataset import box_of
from .errors import ClrefractError
from .view_offsets import estimate_offsets, train_indices


def refine_positions(dataset, run, write: bool = False, runtime=None) -> dict:
    """Estimate each training camera's position against the field of a run folder (see
    estimate_offsets); with `write`, move the cameras in the training transforms file,
    keeping every other key. What it found, as a JSON-able dict."""
    from .evaluate import check_run, load_model, run_config, run_dataset

    run = Path(run)
    check_run(run)
    if (run / "straight.npz").is_file():
        raise ClrefractError(
            f"{run / 'straight.npz'}: a straight-ray baseline has no index field to refine "
            "camera positions against"
        )
    notes: list[str] = []
    cfg = run_config(run, notes)
    ds = run_dataset(run, Path(dataset), box_of(cfg.box) if cfg.box else None)
    source = ds.root / ds.scene.train
    doc = read_json(source) if write else None  # unreadable: refused before any work
    model = load_model(run, ds, notes, runtime=runtime, cfg=cfg)
    if cfg.loss == "srgb420":  # as the run was fitted: colour per block, as stored
        ds.train_chroma = "stored"
    offsets = estimate_offsets(ds, model.tracer, threshold=cfg.mask_threshold, space=cfg.loss)
    moved = np.array([v.offset_mm for v in offsets])
    info: dict = {
        "dataset": str(ds.root),
        "run": str(run),
        "views": [v.to_dict() for v in offsets],
        "rms_offset_mm": round(float(np.sqrt(np.mean(np.sum(moved**2, axis=1)))), 4),
        "mean_offset_mm": np.round(moved.mean(axis=0), 4).tolist(),
        "loss_before": float(np.mean([v.loss_before for v in offsets])),
        "loss_after": float(np.mean([v.loss_after for v in offsets])),
        "views_at_bound": [v.frame for v in offsets if v.at_bound],
        "test_views": "keep their recorded positions (their scores stay honest)",
        "notes": notes,
        "written": [],
    }
    if write:
        frames = doc.get("frames")
        for k, v in zip(train_indices(ds), offsets, strict=True):
            c2w = np.asarray(frames[k]["transform_matrix"], float)
            c2w[:3, 3] += v.offset_mm
            frames[k]["transform_matrix"] = c2w.tolist()
        write_json(source, doc)
        info["written"].append(str(source))
    return info
