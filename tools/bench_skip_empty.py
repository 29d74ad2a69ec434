"""Empty-space skipping: the same exit rays, fewer steps, less time, for objects that fill
a small part of the box.

    python tools/bench_skip_empty.py [--rays 16384] [--json bench_results/skip_empty.json]
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from clrefract.fields.analytic import Luneburg, Sphere
from clrefract.fields.base import Box
from clrefract.fields.voxel import VoxelGrid
from clrefract.tracer import Tracer


def timed(tr, o, d, repeats=3):
    tr.trace(o, d)  # warm-up: PoCL specialises per launch size
    best, res = np.inf, None
    for _ in range(repeats):
        t0 = time.perf_counter()
        res = tr.trace(o, d)
        best = min(best, time.perf_counter() - t0)
    return res, best


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rays", type=int, default=16384)
    ap.add_argument("--json", default="bench_results/skip_empty.json")
    args = ap.parse_args()
    rng = np.random.default_rng(0)
    n = args.rays
    # a camera-like bundle over the whole box face: most rays miss the small object
    o = np.column_stack([np.full(n, -120.0), rng.uniform(-45, 45, (n, 2))])
    d = np.column_stack([np.ones(n), rng.normal(0, 0.02, (n, 2))])
    scenes = [
        ("sphere R10 w1", Sphere(radius=10.0, eta=1.5, width=1.0), 0.125),
        ("luneburg R10", Luneburg(radius=10.0), 0.25),
        (
            "voxel sphere R10 65^3",
            VoxelGrid.from_field(Sphere(radius=10.0, width=2.0), res=65),
            0.5,
        ),
    ]
    rows = []
    for name, f, step in scenes:
        box = f.tracing_box(Box())
        for precision in ("float32", "float64"):
            a, ta = timed(Tracer(f, box=box, step=step, precision=precision), o, d)
            b, tb = timed(Tracer(f, box=box, step=step, precision=precision, skip_empty=True), o, d)
            dd = np.abs(a.direction - b.direction).max(1)
            row = {
                "scene": name,
                "precision": precision,
                "step": step,
                "seconds": ta,
                "seconds_skip": tb,
                "speedup": ta / tb,
                "steps_per_ray": float(a.steps.mean()),
                "steps_per_ray_skip": float(b.steps.mean()),
                "max_direction_diff": float(dd.max()),
                "rays_over_1e-6": float(np.mean(dd > 1e-6)),
            }
            rows.append(row)
            print(
                f"{name:22s} {precision}  {ta:.3f}s -> {tb:.3f}s (x{ta / tb:.1f})  steps "
                f"{row['steps_per_ray']:.0f} -> {row['steps_per_ray_skip']:.0f}  max |dd| "
                f"{dd.max():.1e}, rays > 1e-6: {100 * row['rays_over_1e-6']:.2f}%",
                flush=True,
            )
    Path(args.json).parent.mkdir(parents=True, exist_ok=True)
    Path(args.json).write_text(json.dumps(rows, indent=1))
    print(f"wrote {args.json}")


if __name__ == "__main__":
    main()
