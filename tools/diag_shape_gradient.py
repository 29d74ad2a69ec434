"""Does the photometric gradient carry a glass level set from its visual hull to the object?

    python tools/diag_shape_gradient.py [--scene rounded-cube] [--data bench_results/data]
        [--rays 16384] [--self-targets] [--json bench_results/diag_shape_gradient.json]
        [--descend 40 --lr-phi 0.002 --precision float64 --adjoint discrete]
        [--direction-targets] [--line-search 12 --start bench_results/runs_hgls/prism]

On a family solid (quick protocol: 128 x 128, 100 views; made in DATA if missing), a 64^3
level set with the true index, rays through the masks, rays whose adjoint grew past 30 left
out. It prints:
- the visual hull against the truth (cells inside each; how far the hull's extra cells lie
  from the true surface) and the refraction masks against the true silhouettes;
- the loss, per pixel and by 8 x 8 blocks, along the straight line in the level set's values
  from the hull (t = 0) to the truth sampled on the same grid (t = 1);
- at t = 0, 0.5, 0.9 and 0.99: the gradient's cosine with the way to the truth, and the
  cosine between the gradients of two disjoint halves of the rays (near 1: the rays agree on
  where the surface should go; near 0: each half fits its own pixels), raw and smoothed by
  a Gaussian of grad_sigma cells (as the line search takes it);
--direction-targets adds the same for a loss no photograph gives: the squared distance of
each ray's exit direction from the truth's (traced on the same grid), the most any
per-ray loss of the exit state could say about where the surface lies.
--self-targets compares with the truth on the grid as the eikonal tracer renders it, not
with the photographs: no model error, the loss is 0 at t = 1.
--descend N then runs N Adam steps of the fit (index fixed, 90% of each batch through the
masks) from t = 0.9 and prints the loss and the level set's mean error near the surface.
--line-search N runs N steps of the line-search optimiser's rule (tame rays, gradient
smoothed by grad_sigma cells, the best of 0.001 to 1 mm) on the --rays pool, driven by the
photometric loss and, with --direction-targets, by the exit directions' distance from the
truth's; from the hull (t = 0), or with --start RUN from the level set of a line-search run
on this scene (its level set's, or a hash grid's guide), at the true index. It prints the
pool's photometric loss and the level set's mean error near the surface at each step.
"""

from __future__ import annotations

import argparse
import io
import json
from pathlib import Path

import numpy as np

from clrefract.fit_linesearch import smoothed
from clrefract.loss import direction_loss
from clrefract.tracer import Status


def main() -> None:
    from clrefract.fit import Fit, load_config, make_field
    from clrefract.report import scene_truth

    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--scene", default="rounded-cube")
    ap.add_argument("--data", default="bench_results/data")
    ap.add_argument("--rays", type=int, default=16384)
    ap.add_argument("--self-targets", action="store_true")
    ap.add_argument("--json", default="bench_results/diag_shape_gradient.json")
    ap.add_argument("--descend", type=int, default=0)
    ap.add_argument("--lr-phi", type=float, default=0.002)
    ap.add_argument("--precision", default="float32")
    ap.add_argument("--adjoint", default="continuous")
    ap.add_argument("--direction-targets", action="store_true")
    ap.add_argument("--line-search", type=int, default=0)
    ap.add_argument("--start", help="a line-search run folder on this scene")
    args = ap.parse_args()
    root = quick_dataset(args.scene, args.data)
    cfg = load_config(
        None,
        dict(
            field="levelset",
            res=64,
            res_schedule=(),
            batch=8192,
            precision=args.precision,
            adjoint=args.adjoint,
            lr_phi=args.lr_phi,
            lr_index=0.0,
            mask_share=0.9,
            iterations=max(args.descend, 1),
            validate_every=0,
        ),
    )
    fit = Fit(root, root / "diag_run", cfg, stream=io.StringIO())
    fit.box = fit._object_box()
    fit._bind(make_field(cfg, fit.box, fit.eta_max, 64), step=cfg.width / 4)
    truth = scene_truth(fit.ds)
    hull = fit._hull(64)
    out: dict = {"scene": args.scene, "rays": args.rays}

    axes = [np.linspace(fit.box.lo[a], fit.box.hi[a], 64) for a in range(3)]
    pts = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    sdf = truth.sdf(pts)[0]
    inside, in_hull = sdf < 0, hull.distance.ravel() > 0
    extra = in_hull & ~inside
    out["hull"] = {
        "truth_cells": int(inside.sum()),
        "hull_cells": int(in_hull.sum()),
        "truth_outside_hull": int((inside & ~in_hull).sum()),
        "extra_mm_p10_50_90_99": np.percentile(sdf[extra], [10, 50, 90, 99]).round(2).tolist(),
        **mask_errors(fit, truth),
    }
    print("hull:", out["hull"])

    phi_true = true_levelset(fit, truth)
    fit._set_start(hull, truth.eta, 0.0)
    phi_hull = fit.params[:-1].copy()
    way = phi_true - phi_hull
    rng = np.random.default_rng(3)
    marked = fit._marked_pool()
    pixels = rng.choice(marked, size=min(args.rays, len(marked)), replace=False)
    blocks = fit._blocks(pixels[: args.rays // 64], 8)
    if args.self_targets:
        # the descent draws its batches from the whole masks
        rendered = marked if args.descend else np.union1d(pixels, blocks)
        render_targets(fit, rendered, phi_true, truth.eta)

    def at(t: float) -> None:
        set_params(fit, phi_hull + t * way)

    out["line"] = []
    for t in (0.0, 0.25, 0.5, 0.75, 0.9, 0.99, 1.0):
        at(t)
        row = {"t": t, "pixels": loss(fit, pixels, 1), "blocks8": loss(fit, blocks, 64)}
        args_ = (fit.origins[pixels], fit.dirs[pixels], fit.rgb[pixels], fit._env_full)
        calm = fit.engine.loss_and_grad(*args_, fit.weights[pixels]).growth <= 5
        row["calm_share"] = float(calm.mean())  # rays whose adjoint grew by 5 at most
        row["calm_loss"] = float(fit.engine.loss_and_grad(*args_, fit.weights[pixels] * calm).loss)
        out["line"].append(row)
        print(
            f"t {t:5.3f}: loss {row['pixels']:.5f}  8x8 blocks {row['blocks8']:.5f}  "
            f"rays with adjoint growth <= 5: {100 * row['calm_share']:.0f}%, "
            f"their share of the loss {row['calm_loss'] / max(row['pixels'], 1e-30):.2f}"
        )

    near = np.abs(phi_true) < 3 * cfg.width
    aims = None
    if args.direction_targets:
        at(1.0)
        aims = exit_directions(fit, pixels)
    out["gradient"] = []
    half = len(pixels) // 2
    losses = {"photometric": None}
    if aims is not None:
        losses["directions"] = aims
    for t in (0.0, 0.5, 0.9, 0.99):
        at(t)
        for name, aim in losses.items():
            g1, g2 = (gradient(fit, part, aims=aim) for part in (pixels[:half], pixels[half:]))
            s1, s2 = (smoothed(g, fit.field.phi.shape, cfg.grad_sigma) for g in (g1, g2))
            row = {
                "t": t,
                "loss": name,
                "cos_with_way": -cosine(g1 + g2, way, near),
                "cos_between_halves": cosine(g1, g2, near),
                "smoothed_cos_with_way": -cosine(s1 + s2, way, near),
                "smoothed_cos_between_halves": cosine(s1, s2, near),
            }
            out["gradient"].append(row)
            print(
                f"t {t:5.3f} {name:>11}: cos(-g, way to truth) {row['cos_with_way']:+.4f}  "
                f"cos(g half 1, g half 2) {row['cos_between_halves']:+.4f}; smoothed "
                f"{row['smoothed_cos_with_way']:+.4f}, {row['smoothed_cos_between_halves']:+.4f}"
            )
    if args.descend:
        out["descent"] = descend(fit, args.descend, lambda: at(0.9), phi_true, near)
    if args.line_search:
        start = run_level_set(Path(args.start), phi_hull.shape) if args.start else phi_hull
        out["line_search"] = {
            name: line_search(fit, start, args.line_search, pixels, phi_true, near, aim, name)
            for name, aim in losses.items()
        }
    Path(args.json).parent.mkdir(parents=True, exist_ok=True)
    Path(args.json).write_text(json.dumps(out, indent=2))


def descend(fit, steps: int, reset, phi_true, near) -> list:
    """Adam steps of the fit from the field reset() sets; loss and level-set error per 10."""
    from clrefract.adam import Adam

    reset()
    fit.adam = Adam(len(fit.params), fit._groups())
    rows = []
    for it in range(1, steps + 1):
        m = fit.step()
        if it % 10 == 0 or it == steps:
            err = float(np.abs(fit.params[:-1] - phi_true)[near].mean())
            rows.append({"iteration": it, "loss": m["loss"], "phi_error_mm": err})
            print(f"descent {it:4d}: batch loss {m['loss']:.5f}, mean |phi - truth| {err:.4f} mm")
    return rows


def run_level_set(run: Path, shape) -> np.ndarray:
    """The level set (phi) a line-search run's checkpoint holds: its own, or its guide's."""
    ckpt = np.load(run / "checkpoint.npz")
    phi = (ckpt["guide_params"] if "guide_params" in ckpt.files else ckpt["params"])[:-1]
    if phi.shape != shape:
        raise SystemExit(f"{run}: its level set has {phi.size} values, not 64^3")
    return phi.astype(np.float64)


def line_search(fit, start, steps: int, pool, phi_true, near, aims, name: str) -> list:
    """The line-search rule on the pool's rays from phi = start, driven by the photometric
    loss (aims None) or by the distance of exit directions from aims; a row per step."""
    set_params(fit, start)
    args = (fit.origins[pool], fit.dirs[pool], fit.rgb[pool], fit._env_full)
    if aims is not None:
        aim = aimed(aims, pool)
        has = np.isfinite(aim[:, 0])
    rows = []
    for it in range(steps + 1):
        err = float(np.abs(fit.params[:-1] - phi_true)[near].mean())
        row = {"step": it, "photometric": loss(fit, pool, 1), "phi_error_mm": err}
        rows.append(row)
        print(
            f"line search ({name}) {it:3d}: photometric {row['photometric']:.5f}, "
            f"mean |phi - truth| {err:.4f} mm"
        )
        if it == steps:
            break
        if aims is None:
            first = fit.engine.loss_and_grad(*args, fit.weights[pool])
            tame = (first.status == Status.EXITED) & (first.growth <= fit.cfg.keep_growth)
            weight = fit.weights[pool] * tame
            r = fit.engine.loss_and_grad(*args, weight)

            def driven(weight=weight):
                return loss(fit, pool, 1, weight)
        else:
            first = fit.engine.loss_and_grad(*args, terminal=toward(aim, has))
            term = toward(aim, has & (first.growth <= fit.cfg.keep_growth))
            r = fit.engine.loss_and_grad(*args, terminal=term)

            def driven(term=term):
                tr = fit.engine.tracer.trace(fit.origins[pool], fit.dirs[pool])
                return term(tr.status, tr.direction)[0]

        move = -smoothed(r.grad[:-1], fit.field.phi.shape, fit.cfg.grad_sigma)
        move /= max(np.abs(move).max(), 1e-30)
        base, best = fit.params[:-1].copy(), (r.loss, 0.0)
        for s in (0.001, 0.003, 0.01, 0.03, 0.1, 0.3, 1.0):
            set_params(fit, base + s * move)
            trial = driven()
            if trial < best[0]:
                best = (trial, s)
        set_params(fit, base + best[1] * move)
        row.update(driving_loss=r.loss, after=best[0], step_mm=best[1])
    return rows


def quick_dataset(scene: str, data: str) -> Path:
    """The family solid's quick-protocol dataset (128 x 128, 100 views), made if missing."""
    from clrefract.synth import MakeOptions, make_dataset

    root = Path(data) / f"{scene}_128"
    if not (root / "scene.json").is_file():
        make_dataset(scene, root, MakeOptions(views=100, res=128))
    return root


def levelset_fit(scene: str, data: str, run: str):
    """An unstarted `Fit` of a 64^3 level set on the scene's quick-protocol dataset, its run
    folder `run` inside the dataset (the start diagnostics' setting)."""
    import io

    from clrefract.fit import Fit, load_config

    root = quick_dataset(scene, data)
    cfg = load_config(None, dict(field="levelset", res=64, res_schedule=(), batch=8192))
    (root / run).mkdir(exist_ok=True)
    return Fit(root, root / run, cfg, stream=io.StringIO())


def true_levelset(fit, truth) -> np.ndarray:
    """The truth's level-set values on the fit's grid and interface width."""
    from clrefract.fields.levelset import LevelSetField

    res, width = fit.field.values.shape[0], fit.cfg.width
    sdf = lambda p: truth.sdf(p)[0]  # noqa: E731
    return LevelSetField.from_sdf(sdf, fit.box, res, truth.eta, width).data()[:-1]


def set_params(fit, phi: np.ndarray, eta: float | None = None) -> None:
    """Set the level set's values (and index) and send them to the device."""
    fit.params[:-1] = phi
    if eta is not None:
        fit.params[-1] = eta
    fit.field.set_data(fit.params)
    fit.engine.tracer.upload_field()


def render_targets(fit, idx, phi, eta: float) -> None:
    """Replace the photographs of rays idx by renders of the level set (phi, eta)."""
    from clrefract.gradient import traced_loss

    set_params(fit, phi, eta)
    for s in range(0, len(idx), 8192):
        j = idx[s : s + 8192]
        r = fit.engine.tracer.trace(fit.origins[j], fit.dirs[j])
        rgb = fit.rgb[j]
        fit.rgb[j] = traced_loss(fit._env_full, r.status, r.direction, rgb, space="linear")[2]


def mask_errors(fit, truth, views: int = 20) -> dict:
    """Refraction-mask pixels off the true silhouette (sphere-traced straight rays)."""
    wrong_in = wrong_out = total = 0
    for cam, mask in list(zip(fit.ds.train, fit._refraction_masks()))[:views]:
        o, d = cam.rays()
        t, hit = np.zeros(len(o)), np.zeros(len(o), bool)
        for _ in range(300):
            s = truth.sdf(o + t[:, None] * d)[0]
            hit |= s < 1e-3
            t += np.maximum(s, 0.05)
        sil = hit.reshape(mask.shape)
        wrong_in += int((mask & ~sil).sum())
        wrong_out += int((~mask & sil).sum())
        total += int(sil.sum())
    return {
        "silhouette_px": total,
        "mask_not_silhouette": wrong_in,
        "silhouette_not_mask": wrong_out,
    }


def loss(fit, idx, group: int, weights=None) -> float:
    from clrefract.gradient import traced_loss

    r = fit.engine.tracer.trace(fit.origins[idx], fit.dirs[idx])
    weights = fit.weights[idx] if weights is None else weights
    return float(
        traced_loss(fit._env_full, r.status, r.direction, fit.rgb[idx], weights, group=group)[0]
    )


def gradient(fit, idx, growth_max: float = 30.0, aims: dict | None = None) -> np.ndarray:
    """Mean gradient over idx of the level set's values, rays whose adjoint grew past
    growth_max left out (their paths are chaotic); of the photometric loss, or with aims
    (ray -> unit direction) of the exit directions' distance from them."""
    total = np.zeros(len(fit.params))
    for s in range(0, len(idx), 8192):
        j = idx[s : s + 8192]
        args = (fit.origins[j], fit.dirs[j], fit.rgb[j], fit._env_full)
        if aims is None:
            kept = fit.engine.loss_and_grad(*args, fit.weights[j]).growth <= growth_max
            r = fit.engine.loss_and_grad(*args, fit.weights[j] * kept)
        else:
            aim = aimed(aims, j)
            has = np.isfinite(aim[:, 0])
            first = fit.engine.loss_and_grad(*args, terminal=toward(aim, has))
            r = fit.engine.loss_and_grad(
                *args, terminal=toward(aim, has & (first.growth <= growth_max))
            )
        total += r.grad * len(j)
    return total[:-1] / len(idx)


def toward(aim: np.ndarray, counted: np.ndarray):
    """The terminal loss of exit directions against aim, over counted rays that exit."""

    def terminal(status, velocity):
        return direction_loss(velocity, aim, (status == Status.EXITED) & counted)

    return terminal


def aimed(aims: dict, idx) -> np.ndarray:
    """(len(idx), 3) target directions of rays idx; NaN where the truth's ray did not exit."""
    return np.array([aims.get(int(k), (np.nan,) * 3) for k in idx])


def exit_directions(fit, idx) -> dict:
    """Ray -> unit exit direction of the rays idx that exit the current field."""
    r = fit.engine.tracer.trace(fit.origins[idx], fit.dirs[idx])
    ok = r.status == Status.EXITED
    d = r.direction / np.linalg.norm(r.direction, axis=1, keepdims=True)
    return {int(k): d[i] for i, k in enumerate(idx) if ok[i]}


def cosine(a: np.ndarray, b: np.ndarray, where: np.ndarray) -> float:
    a, b = a[where], b[where]
    return float(a @ b / (np.linalg.norm(a) * np.linalg.norm(b) + 1e-300))


if __name__ == "__main__":
    main()
