"""How close is the visual hull to the object, under each rule for masks with holes?

    python tools/diag_hull.py [--scenes sphere,prism,...] [--data bench_results/data]
        [--json bench_results/diag_hull.json]

For each scene's quick-protocol dataset (128 x 128, 100 views; made in DATA if missing),
the visual hull on the 64^3 node grid of the fit's object box, against the truth on the
same nodes, under two rules:
- "a fifth": a point is in the hull if it lies inside the silhouette cones of all views but
  a fifth of them (the rule before views were left out);
- "left out" (the fit's default): views whose masks carve the others' hull are left out
  (`carving_views`), and a point may lie outside 3% of the rest (to the nearest count).
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


def main() -> None:
    from diag_shape_gradient import quick_dataset

    from clrefract.family import FAMILY
    from clrefract.fit import Fit, load_config
    from clrefract.hull import visual_hull
    from clrefract.report import scene_truth

    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--scenes", default=",".join(("sphere", "prism", "drop") + FAMILY))
    ap.add_argument("--data", default="bench_results/data")
    ap.add_argument("--json", default="bench_results/diag_hull.json")
    args = ap.parse_args()
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
        for rule, kw in RULES.items():
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
