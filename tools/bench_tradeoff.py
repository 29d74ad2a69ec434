"""The speed/accuracy trade study (issue 12): exit-direction error against throughput, per
scene, integrator, precision and step or tolerance, with the Pareto front.

    python tools/bench_tradeoff.py [--rays 2048] [--out bench_results/tradeoff]

Error: the largest and the median |exit direction - reference| over a bundle of parallel
rays (reference: the Luneburg closed form; for the other scenes float64 Dormand-Prince at
tol 1e-11, which agrees with fixed-step RK4 at 0.02 mm to ~1e-9). Speed: rays traced per
second and ray-steps per second (build excluded), and field evaluations per ray. Writes
<out>.json (one row per configuration) and <out>.png (error against rays/s, one panel per
scene, the Pareto front drawn).
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from clrefract.fields.analytic import Blobs, Luneburg, Sphere
from clrefract.tracer import EVALS_PER_STEP, Status, Tracer

SCENES = {
    "sphere": lambda: Sphere(radius=20.0, eta=1.5, width=1.0),
    "luneburg": lambda: Luneburg(radius=20.0),
    # compact enough to be 1 at the box walls (the tracer's contract)
    "plume": lambda: Blobs(
        centers=[[0, 0, 0], [6, -4, 3], [-5, 5, -2]],
        amplitudes=[2e-3, 1e-3, 1.5e-3],
        sigmas=[6.0, 4.0, 5.0],
    ),
}
FIXED = {
    "rkn4": [2.0, 1.0, 0.5, 0.25, 0.125],
    "rk4": [2.0, 1.0, 0.5, 0.25, 0.125],
    "euler": [0.5, 0.125, 0.03125],
}
TOLS = [1e-4, 1e-6, 1e-8, 1e-10]


def bundle(n: int, radius: float = 18.0, seed: int = 0):
    rng = np.random.default_rng(seed)
    b = radius * np.sqrt(rng.uniform(0, 1, n))
    phi = rng.uniform(0, 2 * np.pi, n)
    yz = np.column_stack([b * np.cos(phi), b * np.sin(phi)])
    return np.column_stack([np.full(n, -120.0), yz]), np.tile([1.0, 0.0, 0.0], (n, 1))


def reference(name, field, o, d):
    if name == "luneburg":
        p = np.column_stack([-np.sqrt(field.radius**2 - (o[:, 1:] ** 2).sum(1)), o[:, 1:]])
        return -p / field.radius
    tr = Tracer(field, step=2.0, integrator="dopri5", tol=1e-11, precision="float64")
    return tr.trace(o, d).direction


def measure(field, o, d, ref, repeats: int, **kw) -> dict:
    tr = Tracer(field, **kw)
    tr.trace(o, d)  # build, and PoCL specialises per launch size: both outside the timing
    best = np.inf
    for _ in range(repeats):
        t0 = time.perf_counter()
        res = tr.trace(o, d)
        best = min(best, time.perf_counter() - t0)
    err = np.linalg.norm(res.direction - ref, axis=1)
    steps = float(res.steps.mean())
    return {
        "error_max": float(err.max()),
        "error_median": float(np.median(err)),
        "exited": float(np.mean(res.status == Status.EXITED)),
        "steps_per_ray": steps,
        "evals_per_ray": steps * EVALS_PER_STEP[kw["integrator"]],
        "rays_per_s": len(o) / best,
        "ray_steps_per_s": len(o) * steps / best,
        "seconds": best,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rays", type=int, default=2048)
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--scenes", nargs="+", default=list(SCENES))
    ap.add_argument("--out", default="bench_results/tradeoff")
    args = ap.parse_args()
    o, d = bundle(args.rays)
    rows = []
    for name in args.scenes:
        field = SCENES[name]()
        ref = reference(name, field, o, d)
        configs = [dict(integrator=i, step=h) for i, hs in FIXED.items() for h in hs] + [
            dict(integrator="dopri5", step=4.0, tol=t) for t in TOLS
        ]
        for precision in ("float32", "float64"):
            for cfg in configs:
                if precision == "float32" and cfg.get("tol", 1) < 1e-9:
                    continue  # refused: below float32's rounding
                r = measure(field, o, d, ref, args.repeats, precision=precision, **cfg)
                r.update(scene=name, precision=precision, **cfg)
                rows.append(r)
                what = f"tol {cfg['tol']:g}" if "tol" in cfg else f"step {cfg['step']:g}"
                print(
                    f"{name:8s} {precision} {cfg['integrator']:6s} {what:11s} "
                    f"err max {r['error_max']:.1e} med {r['error_median']:.1e}  "
                    f"{r['rays_per_s']:9.0f} rays/s {r['ray_steps_per_s']:.2e} steps/s "
                    f"{r['evals_per_ray']:7.0f} evals/ray",
                    flush=True,
                )
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.with_suffix(".json").write_text(json.dumps(rows, indent=1))
    plot(rows, args.scenes, out.with_suffix(".png"))
    print(f"wrote {out.with_suffix('.json')} and {out.with_suffix('.png')}")


def pareto(rows):
    """Rows not beaten in both error and speed by another row."""
    return [
        r
        for r in rows
        if not any(
            s["error_max"] <= r["error_max"]
            and s["rays_per_s"] >= r["rays_per_s"]
            and (s["error_max"] < r["error_max"] or s["rays_per_s"] > r["rays_per_s"])
            for s in rows
        )
    ]


def plot(rows, scenes, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(scenes), figsize=(5.2 * len(scenes), 4.6), squeeze=False)
    colours = {"rkn4": "C0", "rk4": "C1", "euler": "C2", "dopri5": "C3"}
    for ax, name in zip(axes[0], scenes):
        sub = [r for r in rows if r["scene"] == name]
        for r in sub:
            ax.scatter(
                r["rays_per_s"],
                max(r["error_max"], 1e-13),
                color=colours[r["integrator"]],
                marker="o" if r["precision"] == "float32" else "^",
                s=22,
                alpha=0.8,
            )
        front = sorted(pareto(sub), key=lambda r: r["rays_per_s"])
        ax.plot(
            [r["rays_per_s"] for r in front],
            [max(r["error_max"], 1e-13) for r in front],
            "k--",
            lw=0.8,
        )
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_title(name)
        ax.set_xlabel("rays per second")
        ax.grid(True, which="both", alpha=0.3)
    axes[0][0].set_ylabel("max exit-direction error")
    for i, c in colours.items():
        axes[0][0].scatter([], [], color=c, label=i)
    axes[0][0].scatter([], [], color="grey", marker="o", label="float32")
    axes[0][0].scatter([], [], color="grey", marker="^", label="float64")
    axes[0][0].plot([], [], "k--", lw=0.8, label="Pareto front")
    axes[0][0].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)


if __name__ == "__main__":
    main()
