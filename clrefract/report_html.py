"""RUN/report.html: one self-contained page of a run, to open in a browser or send: its
scores, training and held-out loss curves, test views beside the truth and the error, eta
on the planes through the box centre, a picture of its surface and its settings, every
image inlined as a base64 PNG. `clrefract fit` writes it at its end, `clrefract report RUN`
at any time (what the run folder lacks is rendered from its field on the dataset)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from .calibrate import CENTRES_FILE, REGISTRATION_FILE
from .cameras import frame_stem
from .imageio import atomic_path
from .metrics import psnr_ssim
from .report import metrics_figure, pyplot, scene_truth

PANEL_MAX = 320  # pixels across one panel of a test view, at most (larger views are reduced)
SURFACE_NODES = 64  # nodes per axis of the grid the surface picture samples


def write_html_report(
    run: Path, dataset: Path | None = None, out: Path | None = None, device: str | None = None
) -> Path:
    """RUN/report.html (or `out`): the run's scores, its training and held-out loss curves,
    its test views beside the truth and the error, eta on the three central planes, a
    picture of its surface and its settings, images inlined, one file to open or send.
    What the run folder lacks is rendered from the field on the dataset (`dataset`, else
    the one run.json names); what cannot be had is named on the page. Returns its path."""
    import html

    from .errors import ClrefractError

    run = Path(run)
    if not run.is_dir():
        raise ClrefractError(f"{run}: run folder not found")
    notes: list[str] = []
    meta = _json_file(run / "run.json", notes) or {}
    results = _json_file(run / "results.json", notes) or {}
    if not (run / "results.json").is_file():
        notes.append("no results.json: the run has not finished; scores are missing")
    try:
        metrics = run / "metrics.jsonl"
        lines = metrics.read_text().splitlines() if metrics.is_file() else []
        rows = [json.loads(ln) for ln in lines if ln.strip()]
    except (OSError, ValueError) as exc:
        rows = []
        notes.append(f"metrics.jsonl: not readable ({exc})")
    settings = (run / "config.toml").read_text() if (run / "config.toml").is_file() else ""
    ds, model = _dataset_and_model(run, dataset, device, notes)

    parts = [_header_html(run, meta)]
    parts.append(_section("Scores", _scores_html(results)))
    parts.append(_section("Loss", _figure_section(lambda: _loss_figure(run, rows, results), notes)))
    try:
        views = _views_html(run, results, settings, ds, model, notes)
    except Exception as exc:  # noqa: BLE001 - one failing part must spare the page
        notes.append(f"test views failed: {str(exc).splitlines()[0] if str(exc) else exc!r}")
        views = "<p>(not available: see the notes)</p>"
    parts.append(_section("Test views", views))
    parts.append(
        _section(
            "eta through the box centre",
            _figure_section(lambda: _slices_png(run, ds, model), notes, "slices"),
        )
    )
    parts.append(
        _section("Surface", _figure_section(lambda: _surface_png(model, ds), notes, "surface"))
    )
    kept = run / REGISTRATION_FILE
    registered = _json_file(kept, notes) if kept.is_file() else None
    if registered and registered.get("found"):
        parts.append(_section("Registration", _registration_html(registered["found"], notes)))
    moved = run / CENTRES_FILE
    centres = _json_file(moved, notes) if moved.is_file() else None
    if centres and centres.get("views"):
        parts.append(_section("Camera centres", _centres_html(centres, notes)))
    parts.append(_section("Settings (config.toml)", f"<pre>{html.escape(settings)}</pre>"))
    if notes:
        items = "".join(f"<li>{html.escape(n)}</li>" for n in notes)
        parts.append(_section("Notes", f"<ul>{items}</ul>"))
    page = _PAGE.format(
        title=html.escape(f"clrefract run {run.resolve().name}"), body="\n".join(parts)
    )
    target = Path(out) if out is not None else run / "report.html"
    with atomic_path(target, suffix=".html") as tmp:
        tmp.write_text(page, encoding="utf-8")
    return target


_PAGE = """<!DOCTYPE html>
<html lang="en"><head><meta charset="utf-8"><title>{title}</title>
<style>
body {{ font-family: system-ui, sans-serif; margin: 1.5em auto; max-width: 1100px;
       padding: 0 1em; color: #222; }}
h1 {{ font-size: 1.4em; }} h2 {{ font-size: 1.15em; border-bottom: 1px solid #ccc; }}
table {{ border-collapse: collapse; margin: 0.5em 0; }}
td, th {{ border: 1px solid #ddd; padding: 2px 8px; text-align: left; }}
td.n {{ text-align: right; font-variant-numeric: tabular-nums; }}
figure {{ margin: 0.8em 0; }} figcaption {{ font-size: 0.9em; color: #444; }}
img {{ max-width: 100%; }} img.px {{ image-rendering: pixelated; }}
pre {{ background: #f6f6f6; padding: 0.6em; overflow-x: auto; font-size: 0.85em; }}
</style></head>
<body>
{body}
</body></html>
"""


def _section(title: str, body: str) -> str:
    import html

    return f"<section><h2>{html.escape(title)}</h2>\n{body}\n</section>"


def _json_file(path: Path, notes: list[str]) -> dict | None:
    if not path.is_file():
        return None
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        notes.append(f"{path.name}: not readable ({exc})")
        return None


def _dataset_and_model(run: Path, dataset: Path | None, device: str | None, notes: list[str]):
    """The run's dataset and its model (evaluate's: renders views, evaluates eta), or None
    for what cannot be had (named in `notes`)."""
    from .dataset import box_of
    from .errors import ClrefractError
    from .evaluate import EtaModel, load_model, run_dataset

    try:
        fitted = not (run / "straight.npz").is_file()
        cfg = _run_config(run, notes) if fitted else None
        box = box_of(cfg.box) if cfg is not None and cfg.box else None
        ds = run_dataset(run, dataset, box)
    except ClrefractError as exc:
        notes.append(f"no dataset ({exc}): views not rendered, no surface")
        return None, None
    try:
        from .runtime import Runtime

        runtime = Runtime((device or "").split(",")[0].strip() or None)
        if (run / "field.npz").is_file() or not fitted:
            return ds, load_model(run, ds, notes, runtime=runtime, cfg=cfg)
        if (run / "checkpoint.npz").is_file():  # a run in progress: its latest checkpoint
            from .fields.base import Box
            from .fit import field_from_run

            meta = _json_file(run / "run.json", notes) or {}
            fbox = Box.from_dict(meta["box"]) if "box" in meta else ds.box
            eta_hi = float(ds.scene.eta_range[1])
            notes.append("no field.npz: the field shown is the latest checkpoint's")
            return ds, EtaModel(field_from_run(run), fbox, cfg, eta_hi, runtime=runtime)
        notes.append("no field.npz or checkpoint.npz: no field to show")
    except Exception as exc:  # noqa: BLE001 - the page shows what the run folder holds
        notes.append(f"the run's field cannot be loaded ({str(exc).splitlines()[0]})")
    return ds, None


def _run_config(run: Path, notes: list[str]):
    """The run's configuration; the defaults (noted) where config.toml is missing or cannot
    be read: only the step and precision matter for rendering its views."""
    from .errors import ClrefractError
    from .fit import FitConfig, load_config

    try:
        return load_config(run / "config.toml", {})
    except (ClrefractError, OSError) as exc:
        notes.append(f"config.toml not usable ({exc}): views rendered with the default step")
        return FitConfig()


def _img(png: bytes, alt: str, width: int | None = None, pixelated: bool = False) -> str:
    import base64
    import html

    data = base64.b64encode(png).decode("ascii")
    size = f' width="{width}"' if width else ""
    cls = ' class="px"' if pixelated else ""
    return f'<img src="data:image/png;base64,{data}" alt="{html.escape(alt)}"{size}{cls}>'


def _png(img: np.ndarray) -> bytes:
    import imageio.v3 as iio

    img = np.asarray(img)
    if img.dtype != np.uint8:
        img = np.round(np.clip(np.nan_to_num(img, nan=0.0), 0, 1) * 255).astype(np.uint8)
    return iio.imwrite("<bytes>", img, extension=".png")


def _fig_png(fig, dpi: int = 100) -> bytes:
    import io

    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=dpi)
    pyplot().close(fig)
    return buf.getvalue()


def _figure_section(make, notes: list[str], what: str = "loss") -> str:
    """An inlined figure from make() (PNG bytes, or None: nothing to show), or why not."""
    try:
        png = make()
    except Exception as exc:  # noqa: BLE001 - one failing figure must spare the page
        notes.append(f"{what} figure failed: {str(exc).splitlines()[0] if str(exc) else exc!r}")
        return "<p>(not available: see the notes)</p>"
    return _img(png, what) if png else "<p>(not available: see the notes)</p>"


def _header_html(run: Path, meta: dict) -> str:
    import html

    keys = (
        ("dataset", "dataset"),
        ("version", "clrefract"),
        ("commit", "commit"),
        ("device", "device"),
        ("driver", "driver"),
        ("command", "command"),
        ("started", "started (UTC)"),
        ("ended", "ended (UTC)"),
    )
    rows = []
    for key, label in keys:
        if meta.get(key) is None:
            continue
        value = str(meta[key])
        if key == "commit" and meta.get("commit_dirty"):
            value += " (with changes)"
        rows.append(f"<tr><th>{label}</th><td><code>{html.escape(value)}</code></td></tr>")
    for r in meta.get("resumed", []):
        when = f"{r.get('started', '?')} to {r.get('ended', '?')}"
        rows.append(
            f"<tr><th>resumed</th><td><code>{html.escape(str(r.get('command', '')))}</code>"
            f" ({html.escape(when)})</td></tr>"
        )
    title = html.escape(str(run.resolve()))
    return f"<h1>clrefract run <code>{title}</code></h1>\n<table>{''.join(rows)}</table>"


_SCORES = (
    ("test_psnr", "test PSNR (dB)", 2),
    ("test_ssim", "test SSIM", 4),
    ("eta_rmse", "eta RMSE", 4),
    ("chamfer_mm", "chamfer distance (mm)", 3),
)


def _num(x, digits: int = 4) -> str:
    import html

    if x is None:
        return "-"
    if isinstance(x, bool) or not isinstance(x, int | float):
        return html.escape(str(x))
    if isinstance(x, int):
        return str(x)
    return f"{x:.{digits}f}" if abs(x) >= 1e-3 or x == 0 else f"{x:.4g}"


def _scores_html(results: dict) -> str:
    import html

    if not results:
        return "<p>(no results.json)</p>"
    start = results.get("start") or {}
    head = "<tr><th></th><th>fitted</th><th>start</th></tr>"
    body = "".join(
        f"<tr><th>{label}</th><td class=n>{_num(results.get(k), d)}</td>"
        f"<td class=n>{_num(start.get(k), d)}</td></tr>"
        for k, label, d in _SCORES
        if k in results or k in start
    )
    shown = {k for k, _, _ in _SCORES} | {"views", "start", "scoring_errors"}
    plain = [
        (k, v)
        for k, v in results.items()
        if k not in shown and (v is None or isinstance(v, int | float | str))
    ]
    nested = {k: v for k, v in results.items() if k not in shown and isinstance(v, dict | list)}
    more = "".join(
        f"<tr><th>{html.escape(k)}</th><td class=n>{_num(v)}</td></tr>" for k, v in plain
    )
    text = f"<table>{head}{body}</table>\n<table>{more}</table>"
    for line in results.get("scoring_errors", []):
        text += f"<p>scoring failed: {html.escape(str(line))}</p>"
    if nested:
        dump = html.escape(json.dumps(nested, indent=2))
        text += f"<details><summary>more (JSON)</summary><pre>{dump}</pre></details>"
    return text


def _loss_figure(run: Path, rows: list[dict], results: dict) -> bytes | None:
    """RUN/loss.png where the fit's finish drew it after the last metrics row, else drawn."""
    if not rows:
        return None
    png, metrics = run / "loss.png", run / "metrics.jsonl"
    if png.is_file() and png.stat().st_mtime >= metrics.stat().st_mtime:
        return png.read_bytes()
    return _fig_png(metrics_figure(rows, results.get("best_iteration")))


def _registration_html(found: dict, notes: list[str]) -> str:
    """What the fit's registration found (fit --register): the panorama's turn, the residual
    before and after, and per view its exposure and its camera's turn."""
    before, after = found["residual_log_rms_before"], found["residual_log_rms"]
    rows = (
        ("panorama rotation (degrees)", ", ".join(f"{a:g}" for a in found["envmap_rotation"])),
        ("turned by (degrees)", _num(found["turned_deg"])),
        ("RMS log residual", f"{_num(before)} before, {_num(after)} after"),
        ("background pixels", f"{found['background_pixels']} in {found['views']} views"),
    )
    table = "".join(f"<tr><th>{k}</th><td>{v}</td></tr>" for k, v in rows)
    return f"<table>{table}</table>" + _figure_section(
        lambda: _registration_figure(found), notes, "registration"
    )


def _registration_figure(found: dict) -> bytes | None:
    exposure = [f["exposure_scale"] for f in found.get("frames", [])]
    turns = [np.nan if t is None else t for t in found.get("view_turns_deg", [])]
    if not exposure and not turns:
        return None
    plt = pyplot()
    fig, axes = plt.subplots(1, 2, figsize=(10, 2.6), layout="constrained")
    axes[0].plot(exposure, ".")
    axes[0].set(xlabel="view", ylabel="exposure_scale", title="exposure found")
    axes[1].plot(turns, ".")
    axes[1].set(xlabel="view", ylabel="degrees", title="camera turned by")
    return _fig_png(fig)


def _centres_html(found: dict, notes: list[str]) -> str:
    """Where the fit moved the training cameras (fit --camera-centres fitted)."""
    shifts = [v["shift_px"] for v in found["views"]]
    rows = (
        ("views moved", str(len(shifts))),
        ("RMS move (mm)", _num(found["rms_offset_mm"])),
        ("largest move (pixels at the object)", _num(max(shifts), 3)),
        ("held-out views", found["held_out_views"]),
    )
    table = "".join(f"<tr><th>{k}</th><td>{v}</td></tr>" for k, v in rows)
    return f"<table>{table}</table>" + _figure_section(
        lambda: _centres_figure(found), notes, "camera centres"
    )


def _centres_figure(found: dict) -> bytes | None:
    uv = np.array([v["right_up_mm"] for v in found["views"]]) / found["footprint_mm"]
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(4, 4), layout="constrained")
    ax.axhline(0, color="#bbb", lw=0.8)
    ax.axvline(0, color="#bbb", lw=0.8)
    ax.plot(uv[:, 0], uv[:, 1], ".")
    r = max(float(np.abs(uv).max()) * 1.1, 1e-3)
    ax.set(xlim=(-r, r), ylim=(-r, r), aspect="equal", title="each camera's move")
    ax.set(xlabel="right (pixels at the object)", ylabel="up (pixels at the object)")
    return _fig_png(fig)


def _heat(err: np.ndarray, gain: float = 4.0) -> np.ndarray:
    from matplotlib import colormaps

    return colormaps["inferno"](np.clip(err * gain, 0, 1))[..., :3]


def _reduced(img: np.ndarray) -> np.ndarray:
    """A panel at most PANEL_MAX pixels across (block means: no aliasing)."""
    f = -(-img.shape[1] // PANEL_MAX)
    if f <= 1:
        return img
    h, w = img.shape[0] // f * f, img.shape[1] // f * f
    return img[:h, :w].reshape(h // f, f, w // f, f, -1).mean(axis=(1, 3))


def _view_panel(truth_srgb: np.ndarray, render_srgb: np.ndarray) -> np.ndarray:
    """truth | render | |error| x 4 (mean over channels, inferno), sRGB in [0, 1]."""
    err = np.abs(render_srgb - truth_srgb).mean(axis=-1)
    gap = np.ones((truth_srgb.shape[0], 2, 3))
    parts = [_reduced(truth_srgb), gap, _reduced(render_srgb), gap, _reduced(_heat(err))]
    return np.concatenate([p if p.shape[0] == parts[0].shape[0] else gap for p in parts], axis=1)


def _test_view_limit(settings: str) -> int:
    try:
        import tomllib
    except ImportError:  # Python 3.10
        import tomli as tomllib
    try:
        return int(tomllib.loads(settings).get("test_views", -1))
    except (ValueError, TypeError):
        return -1


def _views_html(run: Path, results: dict, settings: str, ds, model, notes: list[str]) -> str:
    """Each test view: the truth, the render and the error side by side, named, with its
    scores. From RUN/test/ (what the fit's finish wrote), else rendered from the field."""
    import html

    from .imageio import linear_to_srgb

    scores = {v["view"]: v for v in results.get("views", []) if "view" in v}
    names = list(scores) or sorted(p.stem for p in (run / "test").glob("*.png"))
    cams = {}
    if ds is not None:
        limit = _test_view_limit(settings)
        test = ds.test if limit < 0 else ds.test[:limit]
        cams = {frame_stem(cam, k): cam for k, cam in enumerate(test)}
        names = names or list(cams)
    if not names:
        return "<p>(no test views: no results, no test/ images, no dataset)</p>"
    figures, unshown, env = [], [], None
    for name in names:
        png = run / "test" / f"{name}.png"
        score = dict(scores.get(name, {}))
        if png.is_file():
            from .imageio import read_pillow

            raw = read_pillow(png, "test view", "image")
            pair = np.atleast_3d(raw)[..., :3].astype(np.float64)
            pair = np.broadcast_to(pair, (*pair.shape[:2], 3))
            if np.issubdtype(raw.dtype, np.integer):
                pair = pair / np.iinfo(raw.dtype).max
            w = pair.shape[1] // 2  # the fit writes render | truth
            panel = _view_panel(pair[:, w:], pair[:, :w])
        elif model is not None and name in cams:
            env = env if env is not None else ds.envmap()
            cam = cams[name]
            img, ref = model.render(cam, env), ds.image(cam)
            if "psnr" not in score:
                score["psnr"], score["ssim"] = psnr_ssim(img, ref)
            panel = _view_panel(linear_to_srgb(ref), linear_to_srgb(img))
        else:
            unshown.append(name)
            continue
        said = ", ".join(
            f"{k.upper()} {_num(score[k], 2 if k == 'psnr' else 4)}"
            for k in ("psnr", "ssim")
            if score.get(k) is not None
        )
        width = max(panel.shape[1], 3 * 160)  # small views drawn larger, pixel for pixel
        figures.append(
            f"<figure>{_img(_png(panel), name, width, pixelated=True)}<figcaption>"
            f"<b>{html.escape(name)}</b> {said}</figcaption></figure>"
        )
    if unshown:
        notes.append(
            f"test view(s) {', '.join(unshown)} not shown: no RUN/test/ image and no field "
            "and dataset to render them (pass --dataset)"
        )
        figures.append(f"<p>not shown: {html.escape(', '.join(unshown))}</p>")
    head = "<p>Each view: the truth, the render, and |render - truth| x 4 (sRGB values).</p>"
    return head + "\n".join(figures)


def _plane_points(box, axes: tuple[int, int], res: int) -> np.ndarray:
    """res x res points on the plane of `axes` through the box centre, row by row."""
    lo, hi = np.asarray(box.lo, dtype=float), np.asarray(box.hi, dtype=float)
    U, V = np.meshgrid(
        np.linspace(lo[axes[0]], hi[axes[0]], res), np.linspace(lo[axes[1]], hi[axes[1]], res)
    )
    pts = np.tile((lo + hi) / 2, (U.size, 1))
    pts[:, axes[0]], pts[:, axes[1]] = U.ravel(), V.ravel()
    return pts


def _slices_png(run: Path, ds, model) -> bytes | None:
    """eta on the planes through the box centre (xy, xz, yz), the truth's beneath where the
    dataset has an analytic object: RUN/slices.png (the fit's finish draws them), else
    sampled from the field."""
    png = run / "slices.png"
    if png.is_file():
        return png.read_bytes()
    if model is None:
        return None
    box = model.box if getattr(model, "box", None) is not None else ds.box
    truth = scene_truth(ds)
    res = 128
    planes = ((0, 1), (0, 2), (1, 2))
    names = "xyz"
    c = (np.asarray(box.lo) + np.asarray(box.hi)) / 2
    rows = [
        (
            getattr(model, "slice_label", "eta, fitted"),
            [model.slices_of(_plane_points(box, p, res)) for p in planes],
        )
    ]
    if truth is not None:
        rows.append(("eta, truth", [truth.eval(_plane_points(box, p, res))[0] for p in planes]))
    lo = min(float(np.min(s)) for _, sl in rows for s in sl)
    hi = max(float(np.max(s)) for _, sl in rows for s in sl)
    plt = pyplot()
    fig, ax = plt.subplots(
        len(rows), 3, figsize=(11, 3.4 * len(rows)), squeeze=False, layout="constrained"
    )
    for r, (label, sl) in enumerate(rows):
        for k, (s, (a, b)) in enumerate(zip(sl, planes)):
            third = 3 - a - b
            ext = [box.lo[a], box.hi[a], box.lo[b], box.hi[b]]
            im = ax[r, k].imshow(
                np.asarray(s).reshape(res, res), origin="lower", extent=ext,
                vmin=lo, vmax=max(hi, lo + 1e-6), cmap="viridis",
            )  # fmt: skip
            at = round(float(c[third]), 3) + 0.0  # no -3.55e-15 for 0
            ax[r, k].set_title(f"{label}, {names[third]} = {at:g} mm", fontsize=9)
            ax[r, k].set(xlabel=f"{names[a]} mm", ylabel=f"{names[b]} mm")
    fig.colorbar(im, ax=ax, shrink=0.8, label="eta")
    return _fig_png(fig, dpi=90)


def _height_shade(eta: np.ndarray, level: float, axis: int, step: np.ndarray) -> np.ndarray:
    """The surface eta = level seen from the + side of `axis`, lit from the upper left: RGB,
    white where the view passes no surface. eta: (nx, ny, nz) on a grid of `step` mm."""
    e = np.moveaxis(eta, axis, -1)[..., ::-1]  # from the viewer inwards
    inside = e >= level
    hit = inside.any(axis=-1)
    first = np.argmax(inside, axis=-1)
    # where between the last node outside and the first inside eta crosses the level
    before = np.take_along_axis(e, np.maximum(first - 1, 0)[..., None], -1)[..., 0]
    at = np.take_along_axis(e, first[..., None], -1)[..., 0]
    frac = np.clip((level - before) / np.where(at > before, at - before, 1.0), 0, 1)
    depth = np.where(first > 0, first - 1 + frac, 0.0)
    du, dv = (step[k] for k in range(3) if k != axis)
    h = -depth * step[axis]
    h[~hit] = h[hit].min() if hit.any() else 0.0
    gu, gv = np.gradient(h, du, dv)
    normal = np.stack([-gu, -gv, np.ones_like(h)], -1)
    normal /= np.linalg.norm(normal, axis=-1, keepdims=True)
    light = np.array([-0.45, 0.45, 0.77])
    shade = np.clip(normal @ (light / np.linalg.norm(light)), 0, 1) * 0.75 + 0.25
    rgb = shade[..., None] * np.array([0.55, 0.7, 0.95])
    rgb[~hit] = 1.0
    return rgb


def _surface_png(model, ds) -> bytes | None:
    """The surface eta = the midpoint of 1 and the scene's top index, seen from +z, +y and
    +x (shaded by its height), and the largest eta along each of those lines of sight."""
    if model is None or getattr(model, "kind", "eta") != "eta":
        return None
    box = model.box
    n = SURFACE_NODES
    axes = [np.linspace(box.lo[k], box.hi[k], n) for k in range(3)]
    pts = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    eta = np.concatenate([model.eta(p) for p in np.array_split(pts, 8)]).reshape(n, n, n)
    level = model.level if hasattr(model, "level") else 1 + (float(eta.max()) - 1) / 2
    step = np.array([(box.hi[k] - box.lo[k]) / (n - 1) for k in range(3)])
    plt = pyplot()
    fig, ax = plt.subplots(2, 3, figsize=(11, 7), layout="constrained")
    names = "xyz"
    for col, axis in enumerate((2, 1, 0)):
        a, b = (k for k in range(3) if k != axis)
        ext = [box.lo[a], box.hi[a], box.lo[b], box.hi[b]]
        shaded = _height_shade(eta, level, axis, step)
        ax[0, col].imshow(np.transpose(shaded, (1, 0, 2)), origin="lower", extent=ext)
        ax[0, col].set_title(f"eta = {level:.3f}, seen from +{names[axis]}", fontsize=9)
        im = ax[1, col].imshow(
            eta.max(axis=axis).T, origin="lower", extent=ext, cmap="magma", vmin=1.0
        )
        ax[1, col].set_title(f"largest eta along {names[axis]}", fontsize=9)
        for r in (0, 1):
            ax[r, col].set(xlabel=f"{names[a]} mm", ylabel=f"{names[b]} mm")
    if not (eta >= level).any():
        fig.suptitle(f"eta never reaches {level:.3f}: no surface", fontsize=10)
    fig.colorbar(im, ax=ax[1, :], shrink=0.8, label="eta")
    return _fig_png(fig, dpi=90)
