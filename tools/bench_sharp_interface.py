"""The accuracy end of the speed/accuracy trade: eikonal exit directions through a smoothed
glass sphere against exact Snell refraction, as the interface width and the step shrink.

    python tools/bench_sharp_interface.py [--json bench_results/sharp_interface.json]
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from clrefract.fields.analytic import Sphere
from clrefract.snell import SnellRenderer
from clrefract.tracer import Status, Tracer, TraceSettings


def rays(n: int, radius: float, max_b: float, seed: int = 0):
    rng = np.random.default_rng(seed)
    b = radius * np.sqrt(rng.uniform(0, max_b**2, n))
    phi = rng.uniform(0, 2 * np.pi, n)
    o = np.column_stack([b * np.cos(phi), b * np.sin(phi), np.full(n, -120.0)])
    return o, np.tile([0.0, 0.0, 1.0], (n, 1))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rays", type=int, default=2000)
    ap.add_argument("--max-impact", type=float, default=0.9, help="largest b / R")
    ap.add_argument("--json", default="bench_results/sharp_interface.json")
    args = ap.parse_args()
    radius, eta = 20.0, 1.5
    o, d = rays(args.rays, radius, args.max_impact)
    exact = SnellRenderer(Sphere(radius=radius, eta=eta)).trace(o, d).direction
    rows = []
    for precision in ("float64", "float32"):
        for width in (4.0, 2.0, 1.0, 0.5, 0.25):
            for ratio in (2, 4, 8, 16):
                step = width / ratio
                tr = Tracer(
                    Sphere(radius=radius, eta=eta, width=width),
                    settings=TraceSettings(
                        step=step, precision=precision, max_steps=int(2000 / step)
                    ),
                )
                t0 = time.perf_counter()
                res = tr.trace(o, d)
                sec = time.perf_counter() - t0
                ok = res.status == Status.EXITED
                ang = np.degrees(np.arccos(np.clip((exact[ok] * res.direction[ok]).sum(1), -1, 1)))
                rows.append(
                    {
                        "precision": precision,
                        "width_mm": width,
                        "step_mm": step,
                        "max_err_deg": float(ang.max()),
                        "mean_err_deg": float(ang.mean()),
                        "trapped": int((~ok).sum()),
                        "seconds": sec,
                    }
                )
    cols = list(rows[0])
    print(
        f"Eikonal vs exact Snell, sphere R={radius} eta={eta}, {args.rays} rays, "
        f"impact <= {args.max_impact} R (RKN4)"
    )
    print("  ".join(f"{c:>13}" for c in cols))
    for r in rows:
        print(
            "  ".join(f"{r[c]:>13.4g}" if isinstance(r[c], float) else f"{r[c]:>13}" for c in cols)
        )
    out = Path(args.json)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(rows, indent=2))
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
