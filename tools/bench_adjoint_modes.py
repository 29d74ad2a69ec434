"""Continuous against discrete adjoint: agreement with central finite differences of the
forward renderer (float64, small scene) and backward-pass time and state memory (float32).

    python tools/bench_adjoint_modes.py [--rays 4096] [--step 1.0] [--json PATH]
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from clrefract.fields.base import Box  # noqa: E402
from clrefract.fields.voxel import VoxelGrid  # noqa: E402
from clrefract.gradcheck import directional_errors, lens_scene  # noqa: E402
from clrefract.gradient import GradientEngine  # noqa: E402
from clrefract.tracer import TraceSettings

BOX = Box(margin=4.0)


def fd_agreement(mode: str, step: float, interp: str, n_dirs: int = 3, eps: float = 1e-7):
    """Relative errors of <g, u> against central differences of the forward loss."""
    vals, o, d, env, target = lens_scene(100)
    eng = GradientEngine(
        VoxelGrid(vals, BOX, interp),
        BOX,
        TraceSettings(step=step, precision="float64", lanes=4, adjoint=mode),
    )
    g = eng.loss_and_grad(o, d, target, env).grad
    dirs = np.random.default_rng(1).normal(size=(n_dirs, g.size))
    return directional_errors(eng, o, d, env, target, g, vals.ravel().copy(), dirs, eps).tolist()


def timing(mode: str, every: int, n_rays: int, step: float, repeats: int):
    vals, o, d, env, target = lens_scene(n_rays, res=32)
    eng = GradientEngine(
        VoxelGrid(vals, BOX, "bspline"),
        BOX,
        TraceSettings(step=step, adjoint=mode, checkpoint_every=every),
    )
    eng.loss_and_grad(o[:64], d[:64], target[:64], env)  # build and warm up
    fwd = tot = np.inf
    for _ in range(repeats):
        t0 = time.perf_counter()
        eng.forward(o, d)
        fwd = min(fwd, time.perf_counter() - t0)
        t0 = time.perf_counter()
        eng.loss_and_grad(o, d, target, env)
        tot = min(tot, time.perf_counter() - t0)
    return {
        "adjoint": mode,
        "K": eng.checkpoint_every,
        "forward_s": fwd,
        "backward_s": tot - fwd,
        "state_bytes_per_ray": eng.state_bytes_per_ray(),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rays", type=int, default=4096)
    ap.add_argument("--step", type=float, default=1.0)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--json", default="bench_results/adjoint_modes.json")
    args = ap.parse_args()
    out: dict = {"fd": [], "timing": []}
    print("FD agreement, float64, 100 rays, 12^3 grid, eps 1e-7 (relative error per direction):")
    for interp in ("smoothstep", "bspline"):
        for step in (2.0, 0.5):
            for mode in ("continuous", "discrete"):
                e = fd_agreement(mode, step, interp)
                out["fd"].append({"interp": interp, "step": step, "adjoint": mode, "errors": e})
                print(
                    f"  {interp:10} step {step:3}  {mode:10}  " + "  ".join(f"{x:.2e}" for x in e)
                )
    print(f"Backward pass, {args.rays} rays, 32^3 bspline, float32, step {args.step}:")
    rows = [
        timing("continuous", 8, args.rays, args.step, args.repeats),
        timing("discrete", 8, args.rays, args.step, args.repeats),
        timing("discrete", 0, args.rays, args.step, args.repeats),
    ]
    base = rows[0]["backward_s"]
    for r in rows:
        r["ratio_to_continuous"] = r["backward_s"] / base
        print(
            f"  {r['adjoint']:10} K {r['K']:3}  forward {r['forward_s']:.3f} s  backward "
            f"{r['backward_s']:.3f} s  x{r['ratio_to_continuous']:.2f}  "
            f"{r['state_bytes_per_ray']} B/ray"
        )
    out["timing"] = rows
    path = Path(args.json)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(out, indent=2))
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
