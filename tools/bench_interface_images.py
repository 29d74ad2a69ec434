"""What the smooth interface costs in the benchmark's images: each scene's true object,
smoothed over an interface of width w and traced by the eikonal tracer at step w / ratio,
rendered at the test views and scored against the exact-Snell photographs.

    python tools/bench_interface_images.py [--scenes sphere,prism,drop] [--widths 1,0.5,0.25]
        [--ratios 4,8,16] [--data bench_results/data]
        [--json bench_results/interface_images.json]

A fitted field is a smooth interface too, so its test PSNR cannot be expected above its
width's row here (the truth itself, without representation error): the row is the ceiling
that the fit's width and step put on every start and every optimiser. Each row also gives
the render's cost (seconds, RK4 steps per ray), the speed side of the trade.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time
from pathlib import Path

import numpy as np


def floats(text: str) -> list[float]:
    return [float(v) for v in text.split(",") if v]


def quick_dataset(scene: str, data: str) -> Path:
    """The family solid's quick-protocol dataset (128 x 128, 100 views), made if missing."""
    from clrefract.synth import MakeOptions, make_dataset

    root = Path(data) / f"{scene}_128"
    if not (root / "scene.json").is_file():
        make_dataset(scene, root, MakeOptions(views=100, res=128))
    return root


def main() -> None:
    from clrefract.dataset import Dataset
    from clrefract.metrics import psnr_ssim
    from clrefract.render import render_camera
    from clrefract.report import scene_truth
    from clrefract.tracer import Tracer, TraceSettings

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", default="sphere,prism,drop")
    ap.add_argument("--widths", default="1,0.5,0.25", help="interface widths, mm")
    ap.add_argument("--ratios", default="4,8,16", help="steps per interface width")
    ap.add_argument("--precision", default="float32", choices=("float32", "float64"))
    ap.add_argument("--data", default="bench_results/data")
    ap.add_argument("--json", default="bench_results/interface_images.json")
    args = ap.parse_args()

    rows = []
    cols = ("scene", "width_mm", "step_mm", "psnr", "ssim", "steps_per_ray", "seconds")
    print("  ".join(f"{c:>13}" for c in cols))
    for scene in filter(None, args.scenes.split(",")):
        ds = Dataset(quick_dataset(scene, args.data))
        truth = scene_truth(ds)
        env = ds.envmap()
        refs = [ds.image(cam) for cam in ds.test]
        for width in floats(args.widths):
            field = dataclasses.replace(truth, width=width)
            for ratio in floats(args.ratios):
                step = width / ratio
                settings = TraceSettings(step=step, precision=args.precision)
                tracer = Tracer(field, field.tracing_box(ds.box), settings)
                t0 = time.perf_counter()
                scores, steps, rays = [], 0, 0
                for cam, ref in zip(ds.test, refs):
                    r = render_camera(tracer, cam, env)
                    scores.append(psnr_ssim(r.image, ref))
                    steps += r.steps
                    rays += cam.width * cam.height
                psnr, ssim = np.mean(scores, axis=0)
                row = {
                    "scene": scene,
                    "width_mm": width,
                    "step_mm": step,
                    "psnr": float(psnr),
                    "ssim": float(ssim),
                    "steps_per_ray": steps / rays,
                    "seconds": time.perf_counter() - t0,
                }
                rows.append(row)
                print(
                    "  ".join(
                        f"{row[c]:>13.4g}" if isinstance(row[c], float) else f"{row[c]:>13}"
                        for c in cols
                    ),
                    flush=True,
                )
    out = Path(args.json)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps({"args": vars(args), "rows": rows}, indent=2))
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
