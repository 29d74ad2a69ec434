"""The hash grid's distillation (fitting it to a solid: a hash-grid start, and the refit
after every line-search step) in one piece against its batch cut into one piece per core
on threads, side by side in one run: steps per second, and how far the two fits differ.

The solid is a sphere in the quick protocol's box with the fit's default hash grid and its
ramp output at a 0.5 mm interface; 400,000 points as fit_to_field takes, 8,192 a step.

    python tools/bench_distil.py [--steps 150] [--threads 0] [--json bench_results/distil.json]
"""

from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

import numpy as np

from clrefract.fields.base import Box
from clrefract.fields.hashgrid import HashGridConfig, HashGridField
from clrefract.fit import FitConfig, hashgrid_config
from clrefract.limits import host_threads


def distil(cfg: HashGridConfig, box: Box, pts, phi, normal, steps: int, threads: int):
    os.environ["CLREFRACT_HOST_THREADS"] = str(threads)
    field = HashGridField(cfg, box, seed=0)
    t0 = time.perf_counter()
    field.fit_surface(pts, phi, normal, 1.5, 0.5, iterations=steps, seed=1)
    return steps / (time.perf_counter() - t0), field.data()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--steps", type=int, default=150)
    ap.add_argument("--threads", type=int, default=0, help="0: one per core")
    ap.add_argument("--json", default="bench_results/distil.json")
    args = ap.parse_args()
    threads = args.threads or host_threads()
    cfg = hashgrid_config(FitConfig(field="hashgrid"), 1.5)  # from the hull: the ramp
    box = Box((-12.0, -12.0, -12.0), (12.0, 12.0, 12.0), 1.0)
    rng = np.random.default_rng(0)
    pts = rng.uniform(-12, 12, (400_000, 3))
    r = np.linalg.norm(pts, axis=1)
    phi, normal = r - 8.0, pts / r[:, None]
    rows = []
    params = {}
    for n in (1, threads):
        rate, params[n] = distil(cfg, box, pts, phi, normal, args.steps, n)
        rows.append({"threads": n, "steps_per_s": rate})
    for row in rows:
        row["speedup"] = row["steps_per_s"] / rows[0]["steps_per_s"]
    diff = float(np.abs(params[threads] - params[1]).max())
    print(f"{'threads':>7} {'steps/s':>8} {'speedup':>8}")
    for row in rows:
        print(f"{row['threads']:7d} {row['steps_per_s']:8.1f} {row['speedup']:8.2f}")
    print(f"largest parameter difference after {args.steps} steps: {diff:.2e}")
    out = Path(args.json)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps({"steps": args.steps, "rows": rows, "max_param_diff": diff}))
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
