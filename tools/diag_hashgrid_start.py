"""Does the adjoint gradient at a perturbed hash-grid start point back to the truth?

    python tools/diag_hashgrid_start.py [--d-eta -0.05] [--d-radius 0] [--data DIR]

On a 48 x 48 glass sphere (made in DIR if missing), the truth and a perturbed truth are each
fitted into the same hash grid. At the perturbed one it prints: the loss of the training rays
through the masks along the line to the fitted truth; the rays' adjoint growth; the
gradient's cosine with the direction to the truth; and, leaving out rays whose adjoint grew
past a limit, the gradient along that direction against secants of the same rays' loss.
"""

from __future__ import annotations

import argparse
import dataclasses
import io
import json
from pathlib import Path

import numpy as np

from clrefract.fit import Fit, fit_to_field, load_config
from clrefract.fit_linesearch import set_params
from clrefract.fit_start import START_BATCH
from clrefract.gradient import traced_loss
from clrefract.report import scene_truth
from clrefract.synth import MakeOptions, make_dataset


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--d-eta", type=float, default=-0.05)
    ap.add_argument("--d-radius", type=float, default=0.0)
    ap.add_argument("--data", default="bench_results/data/sphere48")
    ap.add_argument("--json", default="bench_results/diag_hashgrid_start.json")
    args = ap.parse_args()
    root = Path(args.data)
    if not (root / "scene.json").exists():
        make_dataset("sphere", root, MakeOptions(views=25, res=48, env_width=512, volume_res=16))
    cfg = load_config(
        None,
        dict(field="hashgrid", batch=16384, distil_iterations=600, levels=6, log2_table=14,
             hidden=16, val_views=4, adjoint_growth_max=1e6, width=1.0, optimizer="adam"),
    )  # fmt: skip
    fit = Fit(root, root / "diag_run", cfg, stream=io.StringIO())
    fit.box = fit._object_box()
    truth = scene_truth(fit.ds)
    field = fit._make_field(0)
    fit_to_field(field, truth, cfg.width, cfg.distil_iterations, 0)
    p_truth = np.array(field.data(), np.float64)
    start = dataclasses.replace(
        truth, eta=truth.eta + args.d_eta, radius=truth.radius + args.d_radius
    )
    fit_to_field(field, start, cfg.width, cfg.distil_iterations, 0)
    fit._bind(field)
    p0 = fit.params.copy()
    idx = fit._mask_batch(START_BATCH)
    o, d, c, w = fit.origins[idx], fit.dirs[idx], fit.rgb[idx], fit.weights[idx]
    env = fit._env_full

    def loss(p, keep):
        set_params(fit, p)
        r = fit.engine.tracer.trace(o, d)
        return traced_loss(env, r.status, r.direction, c, w * keep, cfg.loss)[0]

    out = {"rays": len(idx), "d_eta": args.d_eta, "d_radius": args.d_radius}
    to_truth = p_truth - p0
    out["line"] = {t: loss(p0 + t * to_truth, 1.0) for t in (0.0, 0.1, 0.3, 0.6, 1.0)}
    set_params(fit, p0)
    r = fit.engine.loss_and_grad(o, d, c, env, w)
    out["growth_p10_p25_p50_p75_p90"] = np.percentile(r.growth, [10, 25, 50, 75, 90]).tolist()
    rows = []
    for limit in (3.0, 10.0, 30.0):
        keep = (r.growth <= limit).astype(float)
        set_params(fit, p0)
        g = fit.engine.loss_and_grad(o, d, c, env, w * keep).grad
        secants = [(loss(p0 + t * to_truth, keep) - loss(p0, keep)) / t for t in (0.05, 0.1)]
        cos = -(g @ to_truth) / np.linalg.norm(g) / np.linalg.norm(to_truth)
        rows.append(dict(limit=limit, kept=float(keep.mean()), g_dot_d=float(g @ to_truth),
                         secant_005=secants[0], secant_01=secants[1], cos=float(cos)))  # fmt: skip
    out["dropped"] = rows
    print(f"{len(idx)} rays; loss along the line to the truth:")
    print("  " + "  ".join(f"t={t}: {v:.5f}" for t, v in out["line"].items()))
    print(
        "adjoint growth percentiles 10/25/50/75/90:",
        np.round(out["growth_p10_p25_p50_p75_p90"], 1),
    )
    print("| drop growth > | kept | g . d | secant 0.05 | secant 0.1 | cos(-g, d) |")
    print("|---|---|---|---|---|---|")
    for x in rows:
        print(f"| {x['limit']:g} | {x['kept']:.2f} | {x['g_dot_d']:.5f} | {x['secant_005']:.5f} "
              f"| {x['secant_01']:.5f} | {x['cos']:.4f} |")  # fmt: skip
    Path(args.json).parent.mkdir(parents=True, exist_ok=True)
    Path(args.json).write_text(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
