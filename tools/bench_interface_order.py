"""Order of convergence through the Luneburg lens surface, with and without steps that land
on the kink: the exit-direction error against the closed form, per step (log-log), per
integrator and precision.

    python tools/bench_interface_order.py [--out bench_results/interface_order]

Writes <out>.json (errors, field evaluations per ray, fitted slopes) and <out>.png.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from clrefract.convergence import loglog_slope, luneburg_exit_errors

STEPS = [2.0, 1.0, 0.5, 0.25, 0.125, 0.0625]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="bench_results/interface_order")
    ap.add_argument("--rays", type=int, default=64)
    args = ap.parse_args()
    runs = []
    for precision in ("float64", "float32"):
        for integrator in ("rkn4", "rk4"):
            for on in (True, False):
                r = luneburg_exit_errors(STEPS, integrator, precision, on, n=args.rays)
                # the slope over the steps above the rounding floor
                keep = [i for i, e in enumerate(r["error"]) if e > 1e-11]
                if precision == "float32":
                    keep = [i for i in keep if r["error"][i] > 1e-6]
                xs = [r["step"][i] for i in keep]
                ys = [r["error"][i] for i in keep]
                r["slope"] = loglog_slope(xs, ys) if len(keep) >= 2 else float("nan")
                r.update(precision=precision, integrator=integrator, interface_steps=on)
                runs.append(r)
                print(
                    f"{precision} {integrator:5s} interface_steps={on!s:5s} slope "
                    f"{r['slope']:5.2f}  errors " + " ".join(f"{e:.1e}" for e in r["error"])
                )
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.with_suffix(".json").write_text(json.dumps({"steps": STEPS, "runs": runs}, indent=1))
    plot(runs, out.with_suffix(".png"))
    print(f"wrote {out.with_suffix('.json')} and {out.with_suffix('.png')}")


def plot(runs, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.5, 5))
    for r in runs:
        style = "-" if r["interface_steps"] else "--"
        marker = "o" if r["integrator"] == "rkn4" else "s"
        colour = "C0" if r["precision"] == "float64" else "C1"
        if not r["interface_steps"]:
            colour = "C2" if r["precision"] == "float64" else "C3"
        label = (
            f"{r['integrator']} {r['precision']} "
            f"{'interface steps' if r['interface_steps'] else 'fixed step'} "
            + (f"(slope {r['slope']:.1f})" if np.isfinite(r["slope"]) else "(rounding floor)")
        )
        ax.loglog(
            r["step"], r["error"], style, marker=marker, color=colour, label=label, alpha=0.85
        )
    h = np.array(STEPS)
    ax.loglog(h, 1e-7 * (h / h[0]) ** 4 * 20, ":", color="grey", label="slope 4")
    ax.loglog(h, 1e-1 * (h / h[0]), "-.", color="grey", label="slope 1")
    ax.set_xlabel("step (mm of optical path)")
    ax.set_ylabel("max |exit direction - closed form|")
    ax.set_title("Luneburg lens R = 20 mm: exit-direction error")
    ax.legend(fontsize=6.5)
    ax.grid(True, which="both", alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=120)


if __name__ == "__main__":
    main()
