"""Forward tracing benchmark: throughput per field kind beside Dr.Jit, the speed/accuracy
trade of the integrators on the Luneburg lens, and long rays traced in one pass beside two.

    python tools/bench_trace.py [--rays 262144] [--part fields|long-rays] [--fields blobs,drop]
        [--json bench_results/trace.json]

Prints two tables and writes them as JSON. Absolute times on a shared machine are noise;
compare the rows of one run.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from clrefract.fields.analytic import Blobs, Drop, Luneburg, Prism, Sphere  # noqa: E402
from clrefract.fields.base import Box  # noqa: E402
from clrefract.runtime import default_runtime  # noqa: E402
from clrefract.tracer import Status, Tracer, TraceSettings  # noqa: E402

BOX = Box()


def workload(n: int, seed: int = 0):
    """Rays from a plane below the box, aimed through it with a small spread."""
    rng = np.random.default_rng(seed)
    o = np.column_stack([rng.uniform(-45, 45, (n, 2)), np.full(n, -120.0)])
    d = np.column_stack([rng.normal(0, 0.05, (n, 2)), np.ones(n)])
    return o, d / np.linalg.norm(d, axis=1, keepdims=True)


def best_of(fn, repeats: int):
    best, out = np.inf, None
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t0)
    return best, out


def hashgrid_export(field) -> dict:
    """A hash grid's layout and parameters as drjit_peer's hash grid takes them."""
    c = field.config
    return dict(
        box_lo=field.box.lo,
        box_hi=field.box.hi,
        margin=field.box.margin,
        features=c.features,
        log2_table=c.log2_table,
        resolutions=c.resolutions,
        dense=c.dense,
        interp=c.interp,
        output=c.output,
        eta_max=c.eta_max,
        tables=list(field.tables),
        layers=field.mlp_layers(),
    )


def hashgrids() -> list[tuple[str, object]]:
    """The hash grid at the fit's default shape (FitConfig's levels, table, MLP; the sigmoid
    output of a fit from empty space: a ramp costs the same per evaluation) and at
    HashGridConfig's larger one (instant-ngp's), as initialised."""
    from dataclasses import replace

    from clrefract.fields.hashgrid import HashGridConfig, HashGridField
    from clrefract.fit.config import FitConfig
    from clrefract.fit.kinds import hashgrid_config

    fit = replace(hashgrid_config(FitConfig(field="hashgrid"), 1.5), output="sigmoid")
    out = []
    for cfg in (fit, HashGridConfig()):
        name = f"hashgrid-{cfg.levels}x{cfg.features}-2^{cfg.log2_table}-{cfg.hidden}x{cfg.layers}"
        out.append((name, HashGridField(cfg, BOX, seed=0)))
    return out


def field_error(eval_fn, field, n: int = 4096, seed: int = 7) -> float:
    """Largest difference of eta and of grad eta (n random points in the box) from the
    field's float64 NumPy reference."""
    pts = np.random.default_rng(seed).uniform(BOX.lo, BOX.hi, (n, 3))
    eta, grad = eval_fn(pts)
    eta_ref, grad_ref = field.eval(pts)
    return float(max(np.abs(eta - eta_ref).max(), np.abs(grad - grad_ref).max()))


def bench_fields(n: int, step: float, repeats: int, only: str = "") -> list[dict]:
    """Throughput rows per field and lane width; `only`: comma-separated name prefixes."""
    o, d = workload(n)
    blobs = Blobs.random(4, amplitude=0.1, seed=3)
    fields = [
        ("blobs", blobs),
        ("luneburg", Luneburg(radius=20.0)),
        ("sphere", Sphere()),
        ("prism", Prism()),
        ("drop", Drop()),
    ]
    from clrefract.fields.voxel import VoxelGrid

    for interp in ("trilinear", "smoothstep", "bspline"):
        fields.append(
            (f"voxel-128-{interp}", VoxelGrid.from_field(Sphere(width=4.0), BOX, 128, interp))
        )
    fields += hashgrids()
    if only:
        fields = [(k, f) for k, f in fields if any(k.startswith(p) for p in only.split(","))]
    try:
        import drjit_peer
    except ImportError as exc:
        print(f"(Dr.Jit peer unavailable: {exc})", file=sys.stderr)
        drjit_peer = None
    rows = []
    dev = default_runtime().info.kind
    lane_choices = sorted({1, default_runtime().default_lanes("float32")})
    cap = 4 * 174 * int(1 / step + 1)
    for name, f in fields:
        hashed = name.startswith("hash")
        # expensive fields get fewer rays so every row takes similar time
        m = n if not hashed else max(n // 32, 4096)
        peer = drjit_peer is not None and (name == "blobs" or hashed)
        # the float64 trace the fields with a Dr.Jit peer are checked against
        ref = None
        if peer:
            settings = TraceSettings(step=step, precision="float64", lanes=8)
            ref = Tracer(f, BOX, settings).trace(o[:m], d[:m]).direction
        field_rows = []
        for lanes in lane_choices:
            tr = Tracer(f, BOX, TraceSettings(step=step, lanes=lanes))
            tr.trace(o[:256], d[:256])
            sec, res = best_of(lambda: tr.trace(o[:m], d[:m]), repeats)  # noqa: B023
            steps = int(res.steps.sum())
            row = {
                "engine": f"clrefract ({dev}, {lanes} lanes)",
                "field": name,
                "rays": m,
                "steps": steps,
                "seconds": sec,
                "steps_per_s": steps / sec,
            }
            if ref is not None:
                row["max_dir_diff_vs_f64"] = float(np.abs(res.direction - ref).max())
            if hashed:
                row["max_field_err"] = field_error(tr.eval_field, f)
            field_rows.append(row)
        rows += field_rows
        if not peer:
            continue
        if hashed:
            grid = hashgrid_export(f)
            args = (o[:m], d[:m], grid, BOX.lo, BOX.hi, step, cap)
            run = drjit_peer.drjit_trace_hashgrid
        else:
            c, a, s = (np.asarray(v) for v in (f.centers, f.amplitudes, f.sigmas))
            args = (o, d, c, a, s, BOX.lo, BOX.hi, step, cap)
            run = drjit_peer.drjit_trace_blobs
        run(*args)  # JIT warm-up
        sec, res = best_of(lambda: run(*args, warmup=False), repeats)  # noqa: B023
        steps = int(np.sum(res["steps"]))
        row = {
            "engine": "Dr.Jit LLVM (peer)",
            "field": name,
            "rays": m,
            "steps": steps,
            "seconds": sec,
            "steps_per_s": steps / sec,
            "max_dir_diff_vs_f64": float(np.abs(res["direction"] - ref).max()),
        }
        if hashed:
            pts_eval = lambda p: drjit_peer.drjit_eval_hashgrid(p, grid)  # noqa: B023, E731
            row["max_field_err"] = field_error(pts_eval, f)
        for r in field_rows:
            r["vs_drjit"] = r["steps_per_s"] / row["steps_per_s"]
        rows.append(row)
    return rows


def luneburg_rays(n: int, radius: float, seed: int = 1):
    rng = np.random.default_rng(seed)
    yz = rng.uniform(-1, 1, (4 * n, 2))
    yz = radius * yz[(yz**2).sum(1) < 0.9][:n]
    o = np.column_stack([np.full(len(yz), -120.0), yz])
    d = np.tile([1.0, 0.0, 0.0], (len(yz), 1))
    # exact exit direction: -P / R with P the entry point on the lens
    p = np.column_stack([-np.sqrt(radius**2 - (yz**2).sum(1)), yz])
    return o, d, -p / radius


def bench_tradeoff(n: int, repeats: int) -> list[dict]:
    radius = 20.0
    o, d, exact = luneburg_rays(n, radius)
    rows = []
    for precision in ("float32", "float64"):
        for integrator in ("rkn4", "rk4", "euler"):
            for step in (2.0, 1.0, 0.5, 0.25, 0.125, 0.0625):
                tr = Tracer(
                    Luneburg(radius=radius),
                    BOX,
                    TraceSettings(step=step, integrator=integrator, precision=precision),
                )
                tr.trace(o[:64], d[:64])
                sec, res = best_of(lambda: tr.trace(o, d), repeats)  # noqa: B023
                cosang = np.clip((res.direction * exact).sum(1), -1, 1)
                err = np.degrees(np.arccos(cosang))
                rows.append(
                    {
                        "precision": precision,
                        "integrator": integrator,
                        "step": step,
                        "max_err_deg": float(err.max()),
                        "mean_err_deg": float(err.mean()),
                        "seconds": sec,
                        "rays_per_s": len(o) / sec,
                    }
                )
    return rows


def bench_interior(n: int, repeats: int) -> list[dict]:
    """The same trade where the field is smooth: inside the lens, from the entry point P
    along d for sigma = 0.45 pi R (short of the exit, where D jumps), against the closed
    form x = P cos(sigma/R) + R d sin(sigma/R), v = -P/R sin(sigma/R) + d cos(sigma/R)."""
    radius = 20.0
    rng = np.random.default_rng(2)
    p = rng.normal(size=(n, 3))
    p = radius * p / np.linalg.norm(p, axis=1, keepdims=True)
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    d = np.where(((d * p).sum(1) < -0.3 * radius)[:, None], d, -d)  # entering steeply ...
    keep = (d * p).sum(1) < -0.3 * radius  # ... or dropped
    p, d = p[keep], d[keep]
    rows = []
    for precision in ("float32", "float64"):
        for integrator in ("rkn4", "rk4", "euler"):
            for n_steps in (8, 16, 32, 64, 128, 256):
                sigma = 0.45 * np.pi * radius
                h = sigma / n_steps
                tr = Tracer(
                    Luneburg(radius=radius),
                    BOX,
                    TraceSettings(step=h, integrator=integrator, precision=precision),
                )
                sec, (x, v) = best_of(
                    lambda: tr.propagate(p * (1 - 1e-6), d, n_steps),  # noqa: B023
                    repeats,
                )
                c, sn = np.cos(sigma / radius), np.sin(sigma / radius)
                x_ex, v_ex = p * c + radius * d * sn, -p / radius * sn + d * c
                err = np.degrees(
                    np.arctan2(np.linalg.norm(np.cross(v, v_ex), axis=1), (v * v_ex).sum(1))
                )
                rows.append(
                    {
                        "precision": precision,
                        "integrator": integrator,
                        "step": h,
                        "steps": n_steps,
                        "max_err_deg": float(err.max()),
                        "pos_err_mm": float(np.abs(x - x_ex).max()),
                        "seconds": sec,
                    }
                )
    return rows


def bench_long_rays(n: int, repeats: int) -> list[dict]:
    """Tracer.trace in two passes (the rays still going after one box diagonal, traced
    again packed together) beside one pass (the full cap for every ray), on glass where
    some rays bounce inside: the same results to the bit, and the time each takes."""
    from clrefract.fields.levelset import LevelSetField

    rot = np.linalg.qr(np.random.default_rng(5).normal(size=(3, 3)))[0]

    def cube(pts):  # a 30 mm cube, turned: flat faces and edges, as a visual hull has
        q = np.abs(pts @ rot) - 15.0
        return np.linalg.norm(np.maximum(q, 0), axis=1) + np.minimum(q.max(1), 0)

    cases = [
        ("sphere eta 1.5", Sphere(), 0.25, False),
        ("sphere eta 3", Sphere(eta=3.0), 0.25, False),
        ("prism", Prism(), 0.25, False),
        (
            "level-set cube 64^3, skipping",
            LevelSetField.from_sdf(cube, BOX, 64, 1.5, 0.5),
            0.125,
            True,
        ),
    ]
    rng = np.random.default_rng(4)
    o = np.column_stack([rng.uniform(-25, 25, (n, 2)), np.full(n, -120.0)])
    d = np.column_stack([rng.normal(0, 0.05, (n, 2)), np.ones(n)])
    rows = []
    for name, field, step, skip in cases:
        two = Tracer(field, BOX, TraceSettings(step=step, skip_empty=skip))
        one = Tracer(field, BOX, TraceSettings(step=step, skip_empty=skip))
        one.long_ray_steps = one.max_steps
        one.trace(o, d)  # PoCL specialises a kernel per launch size: not timed
        t_one, a = best_of(lambda: one.trace(o, d), repeats)  # noqa: B023
        two.trace(o, d)
        t_two, b = best_of(lambda: two.trace(o, d), repeats)  # noqa: B023
        same = all(
            np.array_equal(getattr(a, k), getattr(b, k)) for k in ("direction", "status", "steps")
        )
        rows.append(
            {
                "field": name,
                "rays": n,
                "second_pass": int((a.steps > two.long_ray_steps).sum()),
                "trapped": int((a.status == Status.TRAPPED).sum()),
                "one_pass_s": t_one,
                "two_passes_s": t_two,
                "speedup": t_one / t_two,
                "same_bits": same,
            }
        )
    return rows


def print_table(rows: list[dict], cols: list[str]) -> None:
    widths = {c: max(len(c), *(len(_cell(r.get(c))) for r in rows)) for c in cols}
    print("  ".join(c.ljust(widths[c]) for c in cols))
    for r in rows:
        print("  ".join(_cell(r.get(c)).ljust(widths[c]) for c in cols))


def _cell(v) -> str:
    if isinstance(v, float):
        return f"{v:.4g}"
    return "" if v is None else str(v)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rays", type=int, default=1 << 18)
    ap.add_argument("--step", type=float, default=0.5)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--tradeoff-rays", type=int, default=20000)
    ap.add_argument("--json", default="bench_results/trace.json")
    ap.add_argument("--part", choices=("all", "fields", "long-rays"), default="all")
    ap.add_argument("--fields", default="", help="throughput rows of these fields only")
    args = ap.parse_args()
    info = default_runtime().info
    print(f"device: {info.platform} / {info.name}\n")
    report = {"device": info.name}
    if args.part in ("all", "fields"):
        fields = bench_fields(args.rays, args.step, args.repeats, args.fields)
        print(f"Throughput, step {args.step} mm, RKN4 float32 (ray-steps per second):")
        cols = ["engine", "field", "rays", "steps", "seconds", "steps_per_s", "vs_drjit"]
        print_table(fields, [*cols, "max_dir_diff_vs_f64", "max_field_err"])
        report.update(throughput=fields)
    if args.part == "all":
        trade = bench_tradeoff(args.tradeoff_rays, args.repeats)
        print("\nSpeed/accuracy on the Luneburg lens (exit direction vs closed form):")
        cols = ["precision", "integrator", "step", "max_err_deg", "mean_err_deg", "seconds"]
        print_table(trade, [*cols, "rays_per_s"])
        inner = bench_interior(args.tradeoff_rays, args.repeats)
        print("\nThe same inside the lens only (smooth field: no kink at the lens surface):")
        cols = ["precision", "integrator", "step", "steps", "max_err_deg", "pos_err_mm"]
        print_table(inner, [*cols, "seconds"])
        report.update(tradeoff=trade, interior=inner)
    if args.part in ("all", "long-rays"):
        long = bench_long_rays(max(args.rays // 4, 4096), args.repeats)
        print("\nLong rays: every ray to the full cap in one pass, or those past a diagonal again:")
        cols = ["field", "rays", "second_pass", "trapped", "one_pass_s", "two_passes_s"]
        print_table(long, [*cols, "speedup", "same_bits"])
        report["long_rays"] = long
    out = Path(args.json)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(report, indent=2))
    print(f"\nwrote {out}")


if __name__ == "__main__":
    main()
