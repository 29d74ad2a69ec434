"""`clrefract eval RUN`: the paper's metrics (SPEC section 5) on any finished run folder.

A run is scored through a small model interface, so that eta fields (every `clrefract fit`
run, old ones included) and the straight-ray baselines (clrefract.baselines) are measured by
the same code: render(camera, env) -> image, eta(points) -> eta or None, surface() -> mesh or
None with the rule that extracted it.

Writes RUN/eval/ (or --out): eval.json, eval.md (the table), views/<view>.png (ground truth |
render | error), slices.png (eta, or density, on the three central planes beside the truth)
surface.png (the extracted surface) and surface.ply (that surface as a mesh, mm).
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from .errors import ClrefractError
from .imageio import atomic_path, ensure_out_dir, linear_to_srgb, write_png
from .metrics import chamfer_distance, eta_surface, psnr_ssim

GT_NOTE = "dataset has no ground truth (no analytic object, no gt_surface.ply): image metrics only"


class EtaModel:
    """A fitted index field, rendered through curved rays by the fit's own tracer."""

    kind = "eta"
    slice_label = "eta, fitted"

    def __init__(self, field, box, cfg, eta_hi: float, runtime=None):
        from .fit import forward_settings
        from .render import run_tracer

        self.field, self.box, self.eta_hi = field, box, eta_hi
        self.tracer = run_tracer(field, box, forward_settings(cfg), runtime)
        self.surface_rule = f"marching cubes of eta at {self.level:.4g} (halfway to the index)"
        if getattr(field, "surface", None) is not None:
            self.surface_rule = getattr(
                field, "surface_rule", "marching cubes of phi at 0 (the sharp surface)"
            )

    @property
    def level(self) -> float:
        return 1 + (self.eta_hi - 1) / 2

    def render(self, cam, env) -> np.ndarray:
        from .render import render_camera

        return render_camera(self.tracer, cam, env).image

    def eta(self, pts: np.ndarray) -> np.ndarray:
        return self.tracer.eval_field(pts)[0]

    def slices_of(self, pts: np.ndarray) -> np.ndarray:
        return self.eta(pts)

    def surface(self, box):
        own = getattr(self.field, "surface", None)  # a sharp surface's own zero set
        if own is not None:
            return own(box)
        return eta_surface(self.field, box, self.level, eval_fn=self.tracer.eval_field)


def run_config(run: Path, notes: list[str]):
    """The run's configuration; the defaults (with a note) where an older or damaged
    config.toml cannot be read: only the step and precision matter for scoring."""
    from .fit import FitConfig, load_config

    if not (run / "config.toml").is_file():
        notes.append("run has no config.toml: rendered with the default step and precision")
        return FitConfig()
    try:
        return load_config(run / "config.toml", {})
    except ClrefractError as exc:
        notes.append(f"config.toml not usable ({exc}); rendered with the default step")
        return FitConfig()


def _run_json(run: Path) -> dict:
    path = run / "run.json"
    if not path.is_file():
        return {}
    try:
        return json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise ClrefractError(f"{path}: not readable JSON ({exc})") from None


def check_run(run: Path) -> None:
    """One-line refusal of a folder that holds no finished run, naming what is missing."""
    if not run.is_dir():
        raise ClrefractError(f"{run}: run folder not found")
    if (run / "straight.npz").is_file() or (run / "field.npz").is_file():
        return
    if (run / "checkpoint.npz").is_file():
        raise ClrefractError(
            f"{run}: unfinished run (checkpoint.npz but no field.npz): finish it with "
            "`clrefract fit --resume`, or render its checkpoint with `clrefract render --field`"
        )
    raise ClrefractError(f"{run}: not a finished run (no field.npz or straight.npz)")


def dataset_of(run: Path, dataset: Path | None) -> Path:
    if dataset is not None:
        return Path(dataset)
    named = _run_json(run).get("dataset")
    if not named:
        raise ClrefractError(f"{run}: run.json does not name the dataset; pass --dataset DIR")
    return Path(named)


def run_dataset(run: Path, dataset: Path | None, box=None):
    """The dataset a run is evaluated on (`dataset_of`), as the fit saw it: its own dataset
    with the registration the fit kept (fit --register), any other as it is."""
    from .calibrate import run_corrections
    from .dataset import Dataset

    ds = Dataset(dataset_of(run, dataset), box=box)
    corrections = run_corrections(run)
    if corrections is not None and _is_runs_own(run, ds.root):
        corrections.apply(ds)
    return ds


def _is_runs_own(run: Path, root: Path) -> bool:
    named = _run_json(run).get("dataset")
    return bool(named) and Path(named).resolve() == Path(root).resolve()


def load_model(run: Path, ds, notes: list[str], runtime=None, cfg=None):
    """The model a run folder holds, ready to render the dataset's views (`cfg`: the run's
    configuration, read from it when None)."""
    from .fields import load_field_file
    from .fields.base import Box

    if (run / "straight.npz").is_file():
        from .baselines.straight import load_straight

        return load_straight(run / "straight.npz", runtime=runtime)
    meta = _run_json(run)
    box = Box.from_dict(meta["box"]) if "box" in meta else ds.box
    field = load_field_file(run / "field.npz", box)
    eta_hi = float(ds.scene.eta_range[1])
    cfg = cfg or run_config(run, notes)
    return EtaModel(field, box, cfg, eta_hi, runtime=runtime)


def error_image(render: np.ndarray, truth: np.ndarray, gain: float = 4.0) -> np.ndarray:
    """Per-pixel |difference| of the sRGB images (mean over channels) times `gain`, as an
    sRGB heat map: black is exact."""
    from matplotlib import colormaps

    err = np.abs(linear_to_srgb(render) - linear_to_srgb(truth)).mean(axis=-1)
    return colormaps["inferno"](np.clip(err * gain, 0, 1))[..., :3]


def _view_figure(path: Path, render: np.ndarray, truth: np.ndarray) -> None:
    panel = np.concatenate(
        [linear_to_srgb(truth), linear_to_srgb(render), error_image(render, truth)], axis=1
    )
    write_png(path, panel)


def eta_rmse_of(model, truth, box, res: int = 48) -> float:
    """RMSE of a model's eta (anything with .eta(points)) against the analytic truth at res^3
    nodes over the box."""
    from .report import eta_rmse

    return eta_rmse(None, truth, box, res, eval_fn=lambda pts: (model.eta(pts),))


def _plane_points(box, axes: tuple[int, int], res: int) -> np.ndarray:
    lo, hi = np.asarray(box.lo), np.asarray(box.hi)
    u = np.linspace(lo[axes[0]], hi[axes[0]], res)
    v = np.linspace(lo[axes[1]], hi[axes[1]], res)
    U, V = np.meshgrid(u, v, indexing="xy")
    pts = np.tile((lo + hi) / 2, (U.size, 1))
    pts[:, axes[0]], pts[:, axes[1]] = U.ravel(), V.ravel()
    return pts


def _slices_figure(path: Path, model, truth, box, res: int = 96) -> None:
    from .report import pyplot

    planes = ((0, 1), (0, 2), (1, 2))
    rows = [(model.slice_label, [model.slices_of(_plane_points(box, p, res)) for p in planes])]
    if truth is not None:
        rows.append(("eta, truth", [truth.eval(_plane_points(box, p, res))[0] for p in planes]))
    plt = pyplot()
    fig, ax = plt.subplots(len(rows), 3, figsize=(10, 3.3 * len(rows)), squeeze=False)
    for r, (name, sl) in enumerate(rows):
        for k, (s, title) in enumerate(zip(sl, ("xy (z=0)", "xz (y=0)", "yz (x=0)"))):
            a = ax[r, k]
            im = a.imshow(s.reshape(res, res), origin="lower", cmap="viridis")
            a.set_title(f"{name}, {title}", fontsize=9)
            a.set_xticks([])
            a.set_yticks([])
            fig.colorbar(im, ax=a, shrink=0.8)
    with atomic_path(path, suffix=".png") as tmp:
        fig.savefig(tmp, dpi=90)
    plt.close(fig)


def _surface_figure(path: Path, mesh, truth_mesh) -> None:
    """Cross-sections: points spread over the extracted surface (blue) and the truth's
    (grey) within 2 mm of the three central planes through the truth's centre; flat and
    quick, where a 3-D plot of thousands of triangles is neither."""
    from .metrics import sample_surface
    from .report import pyplot

    plt = pyplot()
    fig, ax = plt.subplots(1, 3, figsize=(11, 3.8))
    centre = np.mean((truth_mesh or mesh)[0], axis=0)
    for m, colour, label in ((truth_mesh, "0.6", "truth"), (mesh, "tab:blue", "extracted")):
        if m is None:
            continue
        p = sample_surface(m[0], m[1], 60000, seed=3)
        for a, (i, j, k) in zip(ax, ((0, 1, 2), (0, 2, 1), (1, 2, 0))):
            near = np.abs(p[:, k] - centre[k]) < 2.0
            a.scatter(p[near, i], p[near, j], s=0.5, c=colour, label=label)
    for a, (x, y) in zip(ax, ("xy", "xz", "yz")):
        a.set(
            xlabel=f"{x} mm",
            ylabel=f"{y} mm",
            aspect="equal",
            title=f"surface near the {x}{y} plane",
        )
    ax[0].legend(markerscale=10, fontsize=8)
    fig.tight_layout()
    with atomic_path(path, suffix=".png") as tmp:
        fig.savefig(tmp, dpi=90)
    plt.close(fig)


def _guard(result: dict, what: str, fn):
    """fn() or None: one failing figure or score is listed, the others still come."""
    try:
        return fn()
    except ClrefractError:
        raise
    except Exception as exc:  # noqa: BLE001 - one failure must spare the other scores
        result.setdefault("errors", []).append(f"{what}: {str(exc).splitlines()[0]}")
        return None


def evaluate_run(
    run: Path,
    dataset: Path | None = None,
    out: Path | None = None,
    views: int = -1,
    figures: bool = True,
    runtime=None,
    samples: int = 100_000,
) -> dict:
    """Scores of a run on its dataset's test views (all, or the first `views`); `samples`
    surface points per side for the chamfer distance (the protocol's 100k unless told)."""
    from .dataset import box_of
    from .mesh import read_mesh
    from .report import scene_truth

    run = Path(run)
    check_run(run)
    notes: list[str] = []
    cfg = None if (run / "straight.npz").is_file() else run_config(run, notes)
    box = box_of(cfg.box) if cfg is not None and cfg.box else None  # the fit's --box
    ds = run_dataset(run, dataset, box)
    model = load_model(run, ds, notes, runtime=runtime, cfg=cfg)
    out = ensure_out_dir(out or run / "eval", "eval folder")
    env = ds.envmap()
    cams = ds.test if views < 0 else ds.test[:views]
    result: dict = {"run": str(run), "dataset": str(ds.root), "method": model.kind, "views": []}
    from .cameras import frame_stem

    for k, cam in enumerate(cams):
        img, ref = model.render(cam, env), ds.image(cam)
        psnr, ssim = psnr_ssim(img, ref)
        stem = frame_stem(cam, k)
        result["views"].append({"view": stem, "psnr": psnr, "ssim": ssim})
        if figures:
            (out / "views").mkdir(exist_ok=True)
            _guard(
                result,
                f"figure {stem}",
                lambda s=stem, a=img, b=ref: _view_figure(out / "views" / f"{s}.png", a, b),
            )
    psnrs = [v["psnr"] for v in result["views"]]
    result["psnr"] = float(np.mean(psnrs)) if psnrs else None
    result["ssim"] = float(np.mean([v["ssim"] for v in result["views"]])) if psnrs else None
    truth = scene_truth(ds)
    gt_path = ds.root / ds.scene.ground_truth.get("surface", "gt_surface.ply")
    truth_mesh = read_mesh(gt_path) if gt_path.is_file() else None
    result["chamfer_mm"] = result["eta_rmse"] = None
    if truth is None and truth_mesh is None:
        notes.append(GT_NOTE)
    mesh = _guard(result, "surface", lambda: model.surface(ds.box))
    result["surface_rule"] = model.surface_rule
    result["surface"] = None
    if mesh is not None:
        from .mesh import write_mesh

        if _guard(result, "surface.ply", lambda: write_mesh(out / "surface.ply", *mesh) or True):
            result["surface"] = "surface.ply"
    if truth_mesh is not None:
        if mesh is None:
            notes.append("no surface could be extracted (the level is never crossed)")
        else:
            result["chamfer_mm"] = _guard(
                result, "chamfer", lambda: chamfer_distance(mesh, truth_mesh, n=samples)
            )
    if truth is not None:
        if model.kind == "eta":
            result["eta_rmse"] = _guard(
                result, "eta RMSE", lambda: eta_rmse_of(model, truth, ds.box)
            )
        else:
            result["eta_rmse"] = "n/a"
            notes.append("eta RMSE not applicable: a straight-ray model has no index")
    if figures:
        _guard(
            result, "slices.png", lambda: _slices_figure(out / "slices.png", model, truth, ds.box)
        )
        if mesh is not None or truth_mesh is not None:
            _guard(
                result,
                "surface.png",
                lambda: _surface_figure(out / "surface.png", mesh, truth_mesh),
            )
    result["notes"] = notes
    with atomic_path(out / "eval.json", suffix=".json") as tmp:
        tmp.write_text(json.dumps(result, indent=2, default=_json_number))
    with atomic_path(out / "eval.md", suffix=".md") as tmp:
        tmp.write_text(format_table(result))
    return result


def _json_number(x):
    return float(x)


def _fmt(x, digits: int) -> str:
    if x is None:
        return "-"
    if isinstance(x, str):
        return x
    return "inf" if math.isinf(x) else f"{x:.{digits}f}"


def format_table(result: dict) -> str:
    """The scores as a markdown table: one row per test view, then the mean."""
    lines = [
        f"run: {result['run']}  dataset: {result['dataset']}  method: {result['method']}",
        "",
        "| view | PSNR (dB) | SSIM |",
        "|---|---:|---:|",
    ]
    for v in result["views"]:
        lines.append(f"| {v['view']} | {_fmt(v['psnr'], 2)} | {_fmt(v['ssim'], 3)} |")
    lines.append(f"| **mean** | **{_fmt(result['psnr'], 2)}** | **{_fmt(result['ssim'], 3)}** |")
    lines += [
        "",
        f"chamfer distance: {_fmt(result['chamfer_mm'], 3)} mm "
        f"(surface: {result.get('surface_rule', '-')})",
        f"eta RMSE over the box: {_fmt(result['eta_rmse'], 4)}",
    ]
    lines += [f"note: {n}" for n in result.get("notes", [])]
    lines += [f"error: {e}" for e in result.get("errors", [])]
    return "\n".join(lines) + "\n"
