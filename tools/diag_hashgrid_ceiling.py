"""How well can the hash grid + MLP hold a glass object at all? The truth fitted into it.

    python tools/diag_hashgrid_ceiling.py [--scene sphere] [--data bench_results/data]
        [--settings default "trilinear:interp=trilinear" "mlp64:hidden=64" ...]
        [--levelset-res 64 128]
        [--json bench_results/diag_hashgrid_ceiling.json]

On a quick-protocol scene (128 x 128, 100 views; made in DATA if missing) the true object is
fitted into the hash grid the way a fit's start is (`fit_to_field`, the fit's interface
width, 1 mm unless a setting says `width=`), once per setting (`name:key=value,...` over the
fit's defaults; `headroom` is eta_max
above the index in units of index - 1; `distil=values` fits eta and its gradient instead of
the surface), and into level sets on the same box for comparison (64^3, or
`--levelset-res`). For each it prints the test views' PSNR and SSIM and the angle between
grad eta and the true surface normal at points within 0.3 mm of the surface (0.3 width
below 1 mm; percentiles 50 / 90 / 99): refraction follows the normals, and the images of
glass need them to about a degree.
"""

from __future__ import annotations

import argparse
import dataclasses
import io
import json
import sys
import time
from pathlib import Path

import numpy as np

DEFAULT_SETTINGS = (
    "default",
    "values:distil=values,headroom=0.04",
    "trilinear:interp=trilinear",
    "mlp64:hidden=64",
    "features4:features=4",
    "table2^19:log2_table=19",
    "headroom1%:headroom=0.01",
)


def normal_errors(field, truth, box, band: float = 0.3, n: int = 20000, seed: int = 5):
    """Angles (degrees) between -grad eta and the outward normal within `band` mm of the
    true surface, where eta has a gradient (a level set's is flat beyond its ramp)."""
    rng = np.random.default_rng(seed)
    lo, size = np.asarray(box.lo), box.size
    pts = np.empty((0, 3))
    while len(pts) < n:
        cand = lo + rng.uniform(size=(400_000, 3)) * size
        pts = np.concatenate([pts, cand[np.abs(truth.distance(cand)) < band]])
    pts = pts[:n]
    normal = truth.sdf(pts)[1]
    grad = field.eval(pts)[1]
    slope = np.linalg.norm(grad, axis=1)
    bends = slope > 0  # a ramp output is flat beyond its interface: no normal to judge
    cos = -(grad[bends] * normal[bends]).sum(1) / slope[bends]
    return np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))


def parse_setting(spec: str) -> tuple[str, dict]:
    name, _, body = spec.partition(":")
    kv = {}
    for item in filter(None, body.split(",")):
        key, _, value = item.partition("=")
        try:
            kv[key] = int(value)
        except ValueError:
            try:
                kv[key] = float(value)
            except ValueError:
                kv[key] = value
    return name, kv


def main() -> None:
    from clrefract.fields.hashgrid import HashGridField
    from clrefract.fields.levelset import LevelSetField
    from clrefract.fit import Fit, fit_to_field, hashgrid_config, load_config
    from clrefract.report import scene_truth, score_field

    sys.path.insert(0, str(Path(__file__).parent))
    from diag_shape_gradient import quick_dataset

    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--scene", default="sphere")
    ap.add_argument("--data", default="bench_results/data")
    ap.add_argument("--settings", nargs="+", default=list(DEFAULT_SETTINGS))
    ap.add_argument("--levelset-res", type=int, nargs="+", default=[64],
                    help="level sets of the truth to compare with, cells per axis")  # fmt: skip
    ap.add_argument("--json", default="bench_results/diag_hashgrid_ceiling.json")
    args = ap.parse_args()
    root = quick_dataset(args.scene, args.data)
    rows = []

    def report(name: str, fit, field, rms: float, seconds: float) -> None:
        ang = normal_errors(field, truth, fit.box, 0.3 * min(1.0, fit.cfg.width))
        fit._bind(field)
        s = score_field(fit, field)
        row = dict(setting=name, psnr=s["test_psnr"], ssim=s["test_ssim"], eta_rms=rms,
                   normal_deg_p50_p90_p99=np.percentile(ang, [50, 90, 99]).tolist(),
                   seconds=seconds)  # fmt: skip
        rows.append(row)
        p = row["normal_deg_p50_p90_p99"]
        angles = f"{p[0]:.2f} / {p[1]:.2f} / {p[2]:.2f}"
        print(f"| {name} | {row['psnr']:.2f} | {row['ssim']:.3f} | {rms:.4f} | {angles} "
              f"| {seconds:.0f} s |", flush=True)  # fmt: skip

    print("| setting | test PSNR | SSIM | eta RMS | normal error p50 / p90 / p99 deg | fit time |")
    print("|---|---|---|---|---|---|")
    for spec in args.settings:
        name, kv = parse_setting(spec)
        headroom = kv.pop("headroom", None)
        interp = kv.pop("interp", None)
        surface = kv.pop("distil", "surface") == "surface"
        batch = kv.pop("distil_batch", 8192)
        kv.setdefault("width", 1.0)  # the interface its table was measured at
        cfg = load_config(None, dict(field="hashgrid", **kv))
        fit = Fit(root, root / "diag_ceiling_run", cfg, stream=io.StringIO())
        fit.box = fit._object_box()
        truth = scene_truth(fit.ds)
        for res in args.levelset_res if not rows else ():  # the truth on the same box
            level = LevelSetField.from_sdf(
                lambda p, t=truth: t.sdf(p)[0], fit.box, res, truth.eta, cfg.width
            )
            report(f"level set {res}^3", fit, level, 0.0, 0.0)
        top = cfg.hashgrid_eta_max(truth.eta)
        if headroom is not None:
            top = 1 + (truth.eta - 1) * (1 + headroom)
        hc = hashgrid_config(cfg, top)
        if interp:
            hc = dataclasses.replace(hc, interp=interp)
        field = HashGridField(hc, fit.box, seed=cfg.seed)
        t0 = time.perf_counter()
        rms = fit_to_field(
            field, truth, cfg.width, cfg.distil_iterations, cfg.seed, surface,
            device=fit.distil_device(), batch=batch,
        )  # fmt: skip
        report(name, fit, field, rms, time.perf_counter() - t0)
    Path(args.json).parent.mkdir(parents=True, exist_ok=True)
    Path(args.json).write_text(json.dumps({"scene": args.scene, "rows": rows}, indent=2))


if __name__ == "__main__":
    main()
