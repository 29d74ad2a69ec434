"""How far is the visual-hull start from the object in ray space, and can a signal smoother
than the photometric gradient carry it closer?

    python tools/diag_start_shape.py [--scene rounded-cube] [--data bench_results/data]
        [--regions 6] [--eta 1.5] [--freeze-index] [--sweeps 4]
        [--json bench_results/diag_start_shape.json]

On a family solid (quick protocol: 128 x 128, 100 views; made in DATA if missing), a 64^3
level set. It prints:
- exit directions: the angle between each mask ray's exit direction at the hull (filled with
  the true index) and at the truth sampled on the same grid;
- colour correspondences: each ray matched to the environment texel nearest in direction and
  colour, |d - w|^2 + alpha^2 |t - c|^2 (t the photographed pixel, sRGB): how often the match
  lies nearer the true exit direction than the hull's exit does, and the cosine between the
  pull towards it and the way to the true exit direction;
- a regional shape search: the start's level set plus a displacement on a coarse lattice of
  REGIONS^3 trilinear hats (those touching the surface's band), each searched in turn by the
  loss of a fixed batch of mask rays (the start's own search, offsets of 2, 1, 1, 0.5, ...
  cells), the index by a line search after each sweep unless --freeze-index; per sweep the
  search loss, the held-out views' loss, and the voxel IoU with the truth.
--eta starts from the hull at offset 0 filled with that index instead of the fit's start.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from clrefract.fit_start import START_BATCH


def texel_directions(height: int, width: int) -> np.ndarray:
    """Unit directions of a lat-long map's texel centres, as the environment lookup maps them."""
    theta = (np.arange(height) + 0.5) / height * np.pi
    phi = ((np.arange(width) + 0.5) / width - 0.5) * 2 * np.pi
    th, ph = np.meshgrid(theta, phi, indexing="ij")
    dirs = [np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph), np.cos(th)]
    return np.stack(dirs, -1).reshape(-1, 3)


def colour_matches(env, directions, targets, alpha: float, width: int) -> np.ndarray:
    """The texel direction nearest each (direction, target colour) in the joint metric, over
    the environment box-filtered to `width` texels across."""
    from scipy.spatial import cKDTree

    from clrefract.loss import srgb

    img = env.image.astype(np.float64)
    f = max(1, img.shape[1] // width)
    h, w = img.shape[0] // f, img.shape[1] // f
    img = img[: h * f, : w * f].reshape(h, f, w, f, 3).mean(axis=(1, 3))
    texels = texel_directions(h, w)
    tree = cKDTree(np.hstack([texels, alpha * srgb(img.reshape(-1, 3))[0]]))
    _, k = tree.query(np.hstack([directions, alpha * srgb(np.asarray(targets, float))[0]]))
    return texels[k]


def angle_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.degrees(np.arccos(np.clip((a * b).sum(1), -1.0, 1.0)))


def main() -> None:
    from diag_shape_gradient import levelset_fit, set_params, true_levelset

    from clrefract.report import scene_truth

    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--scene", default="rounded-cube")
    ap.add_argument("--data", default="bench_results/data")
    ap.add_argument("--regions", type=int, default=6)
    ap.add_argument("--eta", type=float, default=0.0)
    ap.add_argument("--freeze-index", action="store_true")
    ap.add_argument("--sweeps", type=int, default=4)
    ap.add_argument("--json", default="bench_results/diag_start_shape.json")
    args = ap.parse_args()
    t0 = time.perf_counter()
    fit = levelset_fit(args.scene, args.data, "diag_start_run")
    cfg = fit.cfg
    fit.start()
    truth = scene_truth(fit.ds)
    hull = fit._hull(64)
    phi_true = true_levelset(fit, truth)
    out: dict = {"scene": args.scene, "start": fit.init_info}
    print(
        f"start: eta {fit.init_info['eta']:.3f}, offset {fit.init_info['offset_mm']:+.2f} mm, "
        f"smoothed {fit.init_info['smoothing_mm']:.1f} mm (truth eta {truth.eta:.2f})"
    )
    start_params = fit.params.copy()

    # exit directions and colour correspondences at the hull, true index
    pix = np.random.default_rng(3).choice(fit._marked_pool(), size=8192, replace=False)

    def exits(params):
        set_params(fit, params[:-1], params[-1])
        r = fit.engine.tracer.trace(fit.origins[pix], fit.dirs[pix])
        return r.status, r.direction / np.linalg.norm(r.direction, axis=1, keepdims=True)

    st_t, d_t = exits(np.append(phi_true, truth.eta))
    fit._set_start(hull, truth.eta, 0.0)
    st_h, d_h = exits(fit.params.copy())
    ok = (st_t == 0) & (st_h == 0)
    off = angle_deg(d_h, d_t)[ok]
    out["exit_error_deg_p25_50_75_90"] = np.percentile(off, [25, 50, 75, 90]).round(1).tolist()
    pct = out["exit_error_deg_p25_50_75_90"]
    print(f"exit direction, hull against truth (deg, 25/50/75/90%): {pct}")
    want = (d_t - d_h)[ok]
    moved = off > 0.5
    out["matches"] = []
    for alpha, width in [(1.0, 2048), (4.0, 2048), (4.0, 64), (16.0, 32)]:
        w = colour_matches(fit._env_full, d_h, fit.rgb[pix], alpha, width)[ok]
        pull = w - d_h[ok]
        cos = (pull * want).sum(1) / (
            np.linalg.norm(pull, axis=1) * np.linalg.norm(want, axis=1) + 1e-12
        )
        row = {
            "alpha": alpha,
            "env_width": width,
            "nearer_truth": float((angle_deg(w, d_t[ok]) < off)[moved].mean()),
            "cos_pull_way_mean": float(cos[moved].mean()),
        }
        out["matches"].append(row)
        print(
            f"colour match alpha {alpha:g}, env {width} wide: nearer the true exit for "
            f"{100 * row['nearer_truth']:.0f}% of rays, "
            f"cos(pull, way) {row['cos_pull_way_mean']:+.2f}"
        )

    # regional shape search
    if args.eta:
        fit._set_start(hull, args.eta, 0.0)
    else:
        fit.params[:] = start_params
    phi0, eta = fit.params[:-1].copy(), float(fit.params[-1])
    shape = fit.field.values.shape
    lattice = [np.linspace(0, args.regions - 1, shape[a]) for a in range(3)]
    band = np.abs(phi0) < 2 * cfg.width
    modes = []
    for c in np.ndindex(*(args.regions,) * 3):
        hats = [np.maximum(0, 1 - np.abs(lattice[a] - c[a])) for a in range(3)]
        mode = np.einsum("i,j,k->ijk", *hats).ravel()
        if (mode[band] > 0.5).any():
            modes.append(mode)
    idx = fit._mask_batch(START_BATCH)

    def loss_at(a, e) -> float:
        set_params(fit, phi0 - np.tensordot(a, modes, axes=1) if len(modes) else phi0, e)
        return fit._forward_loss(idx)

    inside = phi_true < 0

    def record(tag, a, e, loss) -> None:
        loss_at(a, e)
        mine = fit.params[:-1] < 0
        row = {
            "sweep": tag,
            "eta": e,
            "search_loss": loss,
            "held_out_loss": float(fit.validation_loss()),
            "iou": float((mine & inside).sum() / (mine | inside).sum()),
        }
        out["regional"].append(row)
        print(
            f"regional search {tag}: eta {e:.3f}, loss {loss:.5f}, held-out "
            f"{row['held_out_loss']:.5f}, IoU with truth {row['iou']:.3f}"
        )

    set_params(fit, phi0, 1.0)
    out["empty_loss"] = fit._forward_loss(idx)
    out["held_out_empty"] = float(fit.validation_loss())
    out["modes"] = len(modes)
    print(
        f"{len(modes)} regions; empty box: loss {out['empty_loss']:.5f}, "
        f"held-out {out['held_out_empty']:.5f}"
    )
    out["regional"] = []
    a = np.zeros(len(modes))
    best = loss_at(a, eta)
    record("start", a, eta, best)
    scales = [2.0, 1.0, 1.0, 0.5, 0.5, 0.25][: args.sweeps]
    for sweep, scale in enumerate(scales):
        for m in range(len(modes)):
            for o in np.array([-2.0, -1.0, 1.0, 2.0]) * cfg.width * scale:
                trial = a.copy()
                trial[m] += o
                loss = loss_at(trial, eta)
                if loss < best:
                    best, a = loss, trial
        if not args.freeze_index:
            for e in eta + np.array([-0.06, -0.04, -0.02, 0.02, 0.04, 0.06]):
                loss = loss_at(a, float(e))
                if e > 1 and loss < best:
                    best, eta = loss, float(e)
        record(sweep + 1, a, eta, best)
    out["seconds"] = time.perf_counter() - t0
    Path(args.json).parent.mkdir(parents=True, exist_ok=True)
    Path(args.json).write_text(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
