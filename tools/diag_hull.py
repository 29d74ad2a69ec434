"""How close is the visual hull to the object, under each rule for masks with holes?

    python tools/diag_hull.py [--scenes sphere,prism,...] [--data bench_results/data]
        [--tolerances 0 0.015] [--json bench_results/diag_hull.json]

For each scene's quick-protocol dataset (128 x 128, 100 views; made in DATA if missing),
the visual hull on the 64^3 node grid of the fit's object box, against the truth on the
same nodes, under two rules:
- "a fifth": a point is in the hull if it lies inside the silhouette cones of all views but
  a fifth of them (the rule before views were left out);
- "left out" (the fit's default): views whose masks carve the others' hull are left out
  (`carving_views`), and a point may lie outside 3% of the rest (to the nearest count);
  with --tolerances, the same with other shares in place of 3% ("tol 0": every view).
It also checks the refraction masks of every 8th training view against the truth's own
silhouette (pixels whose ray passes through the true object, sampled every 0.2 mm): pixels
the masks miss, with how deep their rays pass inside (mm, median), and pixels they add.
It prints the IoU, the nodes deeper than 1 mm inside the truth that the hull misses, the
hull's surface distance outside the truth's at the 10th / 50th / 90th percentile (mm, from
nodes within 0.6 mm of the true surface), and the views left out.
"""

from __future__ import annotations

import argparse
import io
import json
from pathlib import Path

import numpy as np

RULES = {"a fifth": dict(tolerance=0.2, carve=0.0), "left out": {}}
MASK_EVERY = 8  # training views whose masks are checked against the true silhouette


def silhouette_check(fit, truth, masks) -> dict:
    """The masks of every MASK_EVERY-th training view against the truth's silhouette."""
    true_px = missed = extra = 0
    depths = []
    for v in range(0, len(fit.ds.train), MASK_EVERY):
        cam = fit.ds.train[v]
        o, d = cam.rays()
        near, far = fit.box.ray_span(o, d)
        deepest = np.full(len(o), np.inf)
        for t in np.arange(0.0, float(np.max(far - near)), 0.2):
            deepest = np.minimum(deepest, truth.sdf(o + d * np.minimum(near + t, far)[:, None])[0])
        deepest = deepest.reshape(cam.height, cam.width)
        sil = deepest < 0
        lost = sil & ~masks[v]
        true_px += int(sil.sum())
        missed += int(lost.sum())
        extra += int((masks[v] & ~sil).sum())
        depths.extend(-deepest[lost])
    depth = float(np.median(depths)) if depths else 0.0
    return {
        "silhouette_px": true_px,
        "missed_px": missed,
        "missed_depth_mm": depth,
        "extra_px": extra,
    }


def main() -> None:
    from diag_shape_gradient import quick_dataset

    from clrefract.family import FAMILY
    from clrefract.fit import Fit, load_config
    from clrefract.hull import visual_hull
    from clrefract.report import scene_truth

    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--scenes", default=",".join(("sphere", "prism", "drop") + FAMILY))
    ap.add_argument("--data", default="bench_results/data")
    ap.add_argument("--tolerances", type=float, nargs="*", default=[])
    ap.add_argument("--json", default="bench_results/diag_hull.json")
    args = ap.parse_args()
    rules = dict(RULES, **{f"tol {t:g}": dict(tolerance=t) for t in args.tolerances})
    rows = []
    head = f"{'scene':13s} {'rule':9s} {'IoU':>6s} {'missed':>6s}"
    print(f"{head} {'outside p10/50/90 mm':>22s} left out")
    for scene in args.scenes.split(","):
        root = quick_dataset(scene, args.data)
        cfg = load_config(None, dict(field="levelset", res=64, iterations=1, validate_every=0))
        fit = Fit(root, root / "diag_run", cfg, stream=io.StringIO())
        fit.box = fit._object_box()
        truth = scene_truth(fit.ds)
        axes = [np.linspace(fit.box.lo[a], fit.box.hi[a], 64) for a in range(3)]
        pts = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
        sdf = truth.sdf(pts)[0]
        inside, near = sdf < 0, np.abs(sdf) < 0.6
        check = silhouette_check(fit, truth, fit._refraction_masks())
        print(
            f"{scene:13s} masks: {check['missed_px']} of {check['silhouette_px']} silhouette "
            f"pixels missed (rays {check['missed_depth_mm']:.2f} mm inside, median), "
            f"{check['extra_px']} added",
            flush=True,
        )
        rows.append({"scene": scene, "masks": check})
        for rule, kw in rules.items():
            hull = visual_hull(fit.box, fit.ds.train, fit._refraction_masks(), 64, **kw)
            d = hull.distance.ravel()
            held = d > 0
            outside = d[near] + sdf[near]  # > 0 where the hull's surface lies outside
            row = {
                "scene": scene,
                "rule": rule,
                "iou": float((held & inside).sum() / (held | inside).sum()),
                "missed_deep": int(((sdf < -1.0) & ~held).sum()),
                "outside_mm_p10_50_90": np.percentile(outside, [10, 50, 90]).round(2).tolist(),
                "left_out": [fit.ds.train[v].name for v in hull.rejected],
            }
            rows.append(row)
            p = "/".join(f"{x:+.2f}" for x in row["outside_mm_p10_50_90"])
            print(
                f"{scene:13s} {rule:9s} {row['iou']:6.3f} {row['missed_deep']:6d} {p:>22s} "
                f"{len(row['left_out'])}",
                flush=True,
            )
    Path(args.json).parent.mkdir(parents=True, exist_ok=True)
    Path(args.json).write_text(json.dumps(rows, indent=2))
    print(f"wrote {args.json}")


if __name__ == "__main__":
    main()
