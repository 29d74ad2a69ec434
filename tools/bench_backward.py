"""Backward-pass benchmark: time and peak memory against the number of RK4 steps, clrefract's
adjoint beside PyTorch autograd through the same RK4 loop on the same voxel field (the
reference paper's stack).

    python tools/bench_backward.py [--rays 4096] [--json bench_results/backward.json]

Each configuration runs in a fresh process so that its peak resident memory is its own.
"""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import resource
import sys
import time
from pathlib import Path

import numpy as np

RES = 32
BOX_HALF = 50.0


def scene(n_rays: int, seed: int = 0):
    rng = np.random.default_rng(seed)
    ax = np.linspace(-BOX_HALF, BOX_HALF, RES)
    X, Y, Z = np.meshgrid(ax, ax, ax, indexing="ij")
    vals = 1 + 0.2 * np.exp(-(X**2 + Y**2 + Z**2) / (2 * 15**2))
    vals += 0.01 * rng.normal(size=vals.shape)
    o = np.column_stack([rng.uniform(-35, 35, (n_rays, 2)), np.full(n_rays, -120.0)])
    d = np.column_stack([rng.normal(0, 0.03, (n_rays, 2)), np.ones(n_rays)])
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return vals, o, d


def _env(seed: int = 1):
    from clrefract.envmap import EnvMap

    return EnvMap.procedural(512, 256, seed=seed)


def run_clrefract(n_rays: int, step: float, repeats: int, q) -> None:
    from clrefract.fields.base import Box
    from clrefract.fields.voxel import VoxelGrid
    from clrefract.gradient import GradientEngine
    from clrefract.tracer import TraceSettings

    vals, o, d = scene(n_rays)
    env = _env()
    target = env.lookup(d).astype(np.float64)
    field = VoxelGrid(vals, Box(), interp="smoothstep")
    eng = GradientEngine(field, Box(), TraceSettings(step=step, precision="float32"))
    base = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    eng.loss_and_grad(o[:64], d[:64], target[:64], env)
    fwd, tot = np.inf, np.inf
    steps = 0
    for _ in range(repeats):
        t0 = time.perf_counter()
        eng.forward(o, d)
        fwd = min(fwd, time.perf_counter() - t0)
        t0 = time.perf_counter()
        r = eng.loss_and_grad(o, d, target, env)
        tot = min(tot, time.perf_counter() - t0)
        steps = r.steps
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    q.put(
        {
            "engine": "clrefract adjoint",
            "step": step,
            "steps_per_ray": steps / n_rays,
            "forward_s": fwd,
            "backward_s": tot - fwd,
            "ratio": (tot - fwd) / fwd,
            "peak_rss_mib": peak / 1024,
            "rss_growth_mib": (peak - base) / 1024,
        }
    )


def run_torch(n_rays: int, step: float, repeats: int, q) -> None:
    import torch

    torch.set_num_threads(2)
    vals, o, d = scene(n_rays)
    env = _env()
    img = torch.tensor(env.image, dtype=torch.float32).permute(2, 0, 1)[None]
    target = torch.tensor(env.lookup(d), dtype=torch.float32)
    theta = torch.tensor(vals, dtype=torch.float32, requires_grad=True)
    hcell = 2 * BOX_HALF / (RES - 1)

    def eta_grad(x):
        # smoothstep-weighted trilinear interpolation, value and gradient, differentiable
        u = ((x + BOX_HALF) / hcell).clamp(0, RES - 1 - 1e-4)
        i = u.floor().long()
        t = u - i
        s = t * t * (3 - 2 * t)
        ds = 6 * t * (1 - t) / hcell
        eta = torch.zeros(len(x))
        g = torch.zeros(len(x), 3)
        for a in (0, 1):
            wx, dx = (s[:, 0], ds[:, 0]) if a else (1 - s[:, 0], -ds[:, 0])
            for b in (0, 1):
                wy, dy = (s[:, 1], ds[:, 1]) if b else (1 - s[:, 1], -ds[:, 1])
                for c in (0, 1):
                    wz, dz = (s[:, 2], ds[:, 2]) if c else (1 - s[:, 2], -ds[:, 2])
                    th = theta[i[:, 0] + a, i[:, 1] + b, i[:, 2] + c]
                    eta = eta + wx * wy * wz * th
                    g = g + torch.stack([dx * wy * wz, wx * dy * wz, wx * wy * dz], 1) * th[:, None]
        return eta, g

    def D(x):
        e, g = eta_grad(x)
        return e[:, None] * g

    x0 = torch.tensor(o + (np.abs(o[:, 2:3]) - BOX_HALF) * d, dtype=torch.float32)
    v0 = torch.tensor(d, dtype=torch.float32)
    n_steps = int(np.ceil(2 * BOX_HALF / step))

    def forward():
        x, v = x0, v0
        for _ in range(n_steps):  # Sharma's RKN, as clrefract's forward pass
            A = step * D(x)
            B = step * D(x + step / 2 * v + step / 8 * A)
            C = step * D(x + step * v + step / 2 * B)
            x = x + step * (v + (A + 2 * B) / 6)
            v = v + (A + 4 * B + C) / 6
        dd = v / v.norm(dim=1, keepdim=True)
        uu = torch.atan2(dd[:, 1], dd[:, 0]) / torch.pi
        vv = 2 * torch.acos(dd[:, 2].clamp(-1, 1)) / torch.pi - 1
        grid = torch.stack([uu, vv], 1)[None, None]
        rad = torch.nn.functional.grid_sample(
            img, grid, align_corners=False, padding_mode="border"
        )[0, :, 0].T
        return ((rad - target) ** 2).mean()

    base = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    fwd, tot = np.inf, np.inf
    for _ in range(repeats):
        with torch.no_grad():
            t0 = time.perf_counter()
            forward()
            fwd = min(fwd, time.perf_counter() - t0)
        theta.grad = None
        t0 = time.perf_counter()
        forward().backward()
        tot = min(tot, time.perf_counter() - t0)
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    q.put(
        {
            "engine": "PyTorch autograd",
            "step": step,
            "steps_per_ray": n_steps,
            "forward_s": fwd,
            "backward_s": tot - fwd,
            "ratio": (tot - fwd) / fwd,
            "peak_rss_mib": peak / 1024,
            "rss_growth_mib": (peak - base) / 1024,
        }
    )


def in_process(fn, *args) -> dict:
    ctx = mp.get_context("spawn")
    q = ctx.Queue()
    p = ctx.Process(target=fn, args=(*args, q))
    p.start()
    out = q.get()
    p.join()
    return out


def main() -> None:
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rays", type=int, default=4096)
    ap.add_argument("--steps", type=float, nargs="+", default=[2.0, 1.0, 0.5, 0.25])
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--no-torch", action="store_true")
    ap.add_argument("--json", default="bench_results/backward.json")
    args = ap.parse_args()
    rows = []
    for h in args.steps:
        rows.append(in_process(run_clrefract, args.rays, h, args.repeats))
        if not args.no_torch:
            try:
                rows.append(in_process(run_torch, args.rays, h, args.repeats))
            except ImportError:
                print("(PyTorch not installed: pip install torch)", file=sys.stderr)
    cols = [
        "engine",
        "step",
        "steps_per_ray",
        "forward_s",
        "backward_s",
        "ratio",
        "peak_rss_mib",
        "rss_growth_mib",
    ]
    print(f"Backward pass, {args.rays} rays, voxel grid {RES}^3 smoothstep, float32:")
    print("  ".join(f"{c:>17}" for c in cols))
    for r in rows:
        print(
            "  ".join(f"{r[c]:>17.4g}" if isinstance(r[c], float) else f"{r[c]:>17}" for c in cols)
        )
    out = Path(args.json)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps({"rays": args.rays, "rows": rows}, indent=2))
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
