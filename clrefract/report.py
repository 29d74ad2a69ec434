"""What a finished fit leaves for people to look at: curves, eta slices, test renders, scores."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from .cameras import frame_stem
from .imageio import atomic_path, write_exr_rgb, write_png_srgb
from .metrics import psnr_ssim


def pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def plot_metrics(metrics_path: Path, out_png: Path, best_iteration: int | None = None) -> None:
    rows = [json.loads(ln) for ln in Path(metrics_path).read_text().splitlines() if ln.strip()]
    if not rows:
        return
    fig = metrics_figure(rows, best_iteration)  # the held-out loss picks the field kept
    with atomic_path(out_png, suffix=".png") as tmp:
        fig.savefig(tmp, dpi=110)
    pyplot().close(fig)


def eta_slices(field, box, res: int = 128):
    """eta on the three central planes (xy at z=0, xz at y=0, yz at x=0) of the box."""
    lo, hi = np.asarray(box.lo), np.asarray(box.hi)
    c = (lo + hi) / 2
    out = []
    for a, b in ((0, 1), (0, 2), (1, 2)):
        u = np.linspace(lo[a], hi[a], res)
        v = np.linspace(lo[b], hi[b], res)
        U, V = np.meshgrid(u, v, indexing="xy")
        pts = np.tile(c, (U.size, 1))  # the third coordinate stays at the centre
        pts[:, a], pts[:, b] = U.ravel(), V.ravel()
        out.append(field.eval(pts)[0].reshape(res, res))
    return out


def plot_slices(field, box, out_png: Path, truth=None, vmax: float | None = None) -> None:
    plt = pyplot()
    rows = [("fitted", eta_slices(field, box))]
    if truth is not None:
        rows.append(("ground truth", eta_slices(truth, box)))
    vmax = vmax or max(float(np.max(s)) for _, sl in rows for s in sl)
    fig, ax = plt.subplots(len(rows), 3, figsize=(10, 3.4 * len(rows)), squeeze=False)
    ext = [box.lo[0], box.hi[0], box.lo[1], box.hi[1]]
    for r, (name, sl) in enumerate(rows):
        for k, (s, title) in enumerate(zip(sl, ("xy (z=0)", "xz (y=0)", "yz (x=0)"))):
            im = ax[r, k].imshow(s, origin="lower", extent=ext, vmin=1.0, vmax=vmax, cmap="viridis")
            ax[r, k].set_title(f"eta, {title}", fontsize=9)
        ax[r, 0].set_ylabel(f"{name}\nmm")
    fig.colorbar(im, ax=ax, shrink=0.8, label="eta")
    with atomic_path(out_png, suffix=".png") as tmp:
        fig.savefig(tmp, dpi=100)
    plt.close(fig)


def render_test_views(fit, out_dir: Path | None, limit: int = -1, tracer=None) -> list[dict]:
    """Render the dataset's test views with the fitted field (or `tracer`'s); PSNR and SSIM
    per view. Images go to out_dir (rendering beside the photograph) unless it is None."""
    from .render import render_camera

    if out_dir is not None:
        out_dir.mkdir(parents=True, exist_ok=True)
    tracer = tracer or fit.forward_tracer(fit.field)
    env = fit.ds.envmap()
    cams = fit.ds.test if limit < 0 else fit.ds.test[:limit]
    rows = []
    for k, cam in enumerate(cams):
        img = render_camera(tracer, cam, env).image
        ref = fit.ds.image(cam)
        psnr, ssim = psnr_ssim(img, ref)
        stem = frame_stem(cam, k)
        if out_dir is not None:
            write_exr_rgb(out_dir / f"{stem}.exr", img)
            write_png_srgb(out_dir / f"{stem}.png", np.concatenate([img, ref], axis=1))
        rows.append({"view": stem, "psnr": psnr, "ssim": ssim})
    return rows


def scene_truth(ds):
    """The analytic object of a synthetic dataset, or None."""
    from .fields import field_from_dict

    if not ds.scene.object:
        return None
    try:
        return field_from_dict(ds.scene.object)
    except Exception:  # noqa: BLE001 - a user's scene may describe objects we cannot draw
        return None


def eta_rmse(field, truth, box, res: int = 48, eval_fn=None) -> float:
    axes = [np.linspace(box.lo[k], box.hi[k], res) for k in range(3)]
    g = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    eta = (eval_fn or field.eval)(g)[0]
    return float(np.sqrt(np.mean((eta - truth.eval(g)[0]) ** 2)))


def _guarded(result: dict, what: str, fn):
    """fn() or None: a score that fails is named in result["scoring_errors"] rather than
    raised, so that a finished fit always leaves its results (SPEC: scoring never loses a
    run). Interrupts still stop."""
    try:
        return fn()
    except Exception as exc:  # noqa: BLE001 - any failure of one score must spare the others
        msg = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        result.setdefault("scoring_errors", []).append(f"{what}: {msg}")
        return None


def score_field(fit, field=None, out_dir: Path | None = None, surface: Path | None = None) -> dict:
    """Test-view PSNR and SSIM, eta RMSE and chamfer distance of a field (default: the
    fit's) on the fit's dataset; with `surface`, the extracted surface is written there as a
    mesh. Each score that cannot be had is None, and its failure is listed in
    "scoring_errors"."""
    field = field or fit.field
    result: dict = {"test_psnr": None, "test_ssim": None, "views": []}
    # evaluates eta on the device too: hash grids are slow in NumPy
    tracer = _guarded(result, "tracer", lambda: fit.forward_tracer(field))
    if tracer is None:
        return result
    views = _guarded(
        result,
        "test views",
        lambda: render_test_views(fit, out_dir, fit.cfg.test_views, tracer=tracer),
    )
    if views:
        result["test_psnr"] = float(np.mean([v["psnr"] for v in views]))
        result["test_ssim"] = float(np.mean([v["ssim"] for v in views]))
        result["views"] = views
    truth = scene_truth(fit.ds)
    if truth is not None:
        result["eta_rmse"] = _guarded(
            result,
            "eta RMSE",
            lambda: eta_rmse(field, truth, fit.ds.box, eval_fn=tracer.eval_field),
        )
    # first: a bad ground-truth file is reported even when there is no surface
    truth_mesh = _guarded(result, "chamfer", lambda: ground_truth_mesh(fit.ds))
    if truth_mesh is None and surface is None:
        return result
    from .metrics import chamfer_distance, eta_surface

    level = surface_level(fit.ds)
    extracted = _guarded(
        result,
        "surface",
        lambda: (eta_surface(field, fit.ds.box, level, eval_fn=tracer.eval_field),),
    )
    mesh = extracted[0] if extracted else None
    if extracted and mesh is None:  # not a failure: eta never reaches the level
        result["surface_note"] = f"eta never crosses {level:.4g}: no surface"
        if truth_mesh is not None:
            result["chamfer_mm"] = None
    if mesh is not None and truth_mesh is not None:
        result["chamfer_mm"] = _guarded(
            result, "chamfer", lambda: chamfer_distance(mesh, truth_mesh)
        )
    if mesh is not None and surface is not None:
        from .mesh import write_mesh

        if _guarded(result, surface.name, lambda: write_mesh(surface, *mesh) or True):
            result["surface"] = surface.name
    return result


def _warn(fit, scores: dict) -> None:
    for line in scores.get("scoring_errors", []):
        fit.stream.write(f"warning: scoring failed, {line}\n")


def surface_level(ds) -> float:
    """The eta of the extracted surface: halfway between 1 and the scene's upper index."""
    return 1 + (ds.scene.eta_range[1] - 1) / 2


def ground_truth_mesh(ds):
    """The dataset's ground-truth surface (verts, faces), or None without one."""
    from .mesh import read_mesh

    gt = ds.root / ds.scene.ground_truth.get("surface", "gt_surface.ply")
    return read_mesh(gt) if gt.is_file() else None


def surface_chamfer(field, ds, eval_fn=None) -> float | None:
    """Chamfer distance (mm) from the surface of eta at surface_level to the dataset's
    ground-truth surface; None without one (or without a crossing: then the surface is
    missing, and inf is returned)."""
    from .metrics import chamfer_distance, eta_surface

    truth = ground_truth_mesh(ds)
    if truth is None:
        return None
    mesh = eta_surface(field, ds.box, surface_level(ds), eval_fn=eval_fn)
    if mesh is None:
        return float("inf")
    return chamfer_distance(mesh, truth)


def write_start_report(fit, seconds: float) -> dict:
    """Scores of the start (before any gradient step) in start.json, so that every run shows
    what the optimiser added (write_fit_report puts them beside the final ones)."""
    scores = {k: v for k, v in score_field(fit).items() if k != "views"}
    _warn(fit, scores)
    scores["seconds"] = seconds
    with atomic_path(fit.out / "start.json", suffix=".json") as tmp:
        tmp.write_text(json.dumps(scores, indent=2))
    fit.out.record_start(fit.runtime.info)  # run.json: version, commit, command, device
    return scores


def _metric_rows(path: Path) -> list[dict]:
    return [json.loads(ln) for ln in path.read_text().splitlines() if ln.strip()]


def write_fit_report(fit) -> dict:
    """results.json of a finished run, with whatever could be scored: plots and scores that
    fail are listed in "scoring_errors" and warned about, never raised."""
    out = fit.out
    result: dict = {
        "iterations": fit.it,
        "best_iteration": fit.best.iteration,
        "best_val_loss": float(fit.best.loss) if fit.best.found else None,
    }
    for key in (
        "stopped",
        "stopped_without_progress",
        "size_search",
        "quasi_newton",
        "final_refit",
        "face_search",
        "narrowing",
    ):
        if fit.record.get(key):
            result[key] = fit.record[key]
    # a resumed run (and the one a model choice goes on with) reads it from start.json
    start_val = fit.record.get("start_val_loss") or fit.out.start_loss()
    if start_val and fit.best.found:
        result["start_val_loss"] = float(start_val)
        result["best_val_over_start"] = float(fit.best.loss) / float(start_val)
    rows = _guarded(result, "metrics.jsonl", lambda: _metric_rows(out / "metrics.jsonl")) or []
    result["train_seconds"] = float(sum(r.get("seconds", 0.0) for r in rows))
    result["final_loss"] = rows[-1].get("loss") if rows else None
    kept = fit.best.iteration if fit.best.found else None
    _guarded(
        result, "loss.png", lambda: plot_metrics(out / "metrics.jsonl", out / "loss.png", kept)
    )
    _guarded(
        result,
        "slices.png",
        lambda: plot_slices(fit.field, fit.ds.box, out / "slices.png", truth=scene_truth(fit.ds)),
    )
    scores = score_field(fit, out_dir=out / "test", surface=out / "surface.ply")
    errors = result.pop("scoring_errors", []) + scores.pop("scoring_errors", [])
    result.update(scores)
    start = out / "start.json"
    if start.is_file():  # runs made before start.json existed have none
        result["start"] = _guarded(result, "start.json", lambda: json.loads(start.read_text()))
        errors += result.pop("scoring_errors", [])
        begun = (result["start"] or {}).get("test_psnr")
        if begun is not None and result["test_psnr"] is not None:
            result["psnr_gain_over_start"] = result["test_psnr"] - begun
    if errors:
        result["scoring_errors"] = errors
        _warn(fit, result)
    with atomic_path(out / "results.json", suffix=".json") as tmp:
        tmp.write_text(json.dumps(result, indent=2))
    fit.out.record_end(fit.runtime.info)  # run.json: the end time
    return result


def metrics_figure(rows: list[dict], best_iteration: int | None = None):
    """Training loss (per batch) and held-out loss against the iteration, and the batch
    PSNR; a matplotlib figure."""
    plt = pyplot()
    it = [r["iteration"] for r in rows]
    fig, ax = plt.subplots(1, 2, figsize=(10, 3.6))
    dots = "." if len(rows) < 50 else ""  # a short run's few points show
    ax[0].semilogy(it, [r["loss"] for r in rows], dots + "-", lw=0.8, label="training (batch)")
    held = [(r["iteration"], r["val_loss"]) for r in rows if r.get("val_loss") is not None]
    if held:
        ax[0].semilogy(*zip(*held), "o-", ms=3, lw=1.0, label="held-out")
    if best_iteration:
        ax[0].axvline(best_iteration, color="0.5", ls=":", lw=1, label="kept")
    ax[0].legend(fontsize=8)
    ax[0].set(xlabel="iteration", ylabel="photometric loss", title="loss")
    ax[1].plot(it, [r.get("psnr", np.nan) for r in rows], dots + "-", lw=0.8)
    ax[1].set(xlabel="iteration", ylabel="PSNR (dB, batch)", title="training PSNR")
    for a in ax:
        a.grid(alpha=0.3)
    fig.tight_layout()
    return fig
