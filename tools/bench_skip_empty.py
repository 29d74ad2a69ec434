"""Empty-space skipping: the same exit rays, fewer steps, less time, for objects that fill
a small part of the box; and in training, the same loss and gradient (forward and backward
pass, the fit's occupancy rule: fit/occupancy.py) for less time. The rendering part includes
a hash grid from the hull, as fits score and validate it (render.run_tracer), and the time
to sample each field's occupancy on the device.

    python tools/bench_skip_empty.py [--rays 16384] [--json bench_results/skip_empty.json]
        [--part render|train|both]
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
from scipy.ndimage import binary_dilation

from clrefract.fields.analytic import Luneburg, Sphere
from clrefract.fields.base import Box
from clrefract.fields.levelset import LevelSetField
from clrefract.fields.voxel import VoxelGrid
from clrefract.gradcheck import smooth_env
from clrefract.gradient import GradientEngine
from clrefract.occupancy import distance_of, live_cells_levelset, live_cells_nodes
from clrefract.tracer import Tracer, TraceSettings


def hashgrid_ball():
    """The fit's default hash grid from the hull (ramp output, eta exactly 1 in air) fitted
    on the device to a ball of radius 10 at a 0.5 mm interface, in a box as a fit's object
    box is around it; its step is the fit's (w/4)."""
    from clrefract.fields.hashgrid import HashGridField
    from clrefract.fit import FitConfig, hashgrid_config, step_mm
    from clrefract.runtime import default_runtime

    cfg = FitConfig(field="hashgrid", width=0.5)
    field = HashGridField(hashgrid_config(cfg, 1.5), Box((-30,) * 3, (30,) * 3, 4.0), seed=0)
    pts = np.random.default_rng(2).uniform(-30, 30, (400_000, 3))
    r = np.linalg.norm(pts, axis=1)
    device = (default_runtime(), "float32")
    field.fit_surface(pts, r - 10.0, pts / r[:, None], 1.5, 0.5, 600, device=device)
    return field, step_mm(cfg)


def timed(tr, o, d, repeats=3):
    tr.trace(o, d)  # warm-up: PoCL specialises per launch size
    best, res = np.inf, None
    for _ in range(repeats):
        t0 = time.perf_counter()
        res = tr.trace(o, d)
        best = min(best, time.perf_counter() - t0)
    return res, best


def timed_grad(eng, o, d, tgt, env, repeats=3):
    eng.loss_and_grad(o, d, tgt, env)  # warm-up
    best, res = np.inf, None
    for _ in range(repeats):
        t0 = time.perf_counter()
        res = eng.loss_and_grad(o, d, tgt, env)
        best = min(best, time.perf_counter() - t0)
    return res, best


def train_rows(o, d, rows_out) -> None:
    """One gradient (forward, loss, backward) with and without skipping, the occupancy as a
    fit builds it: a level set's band, a voxel grid's free nodes (the ball grown 2 nodes)."""
    box = Box((-50, -50, -50), (50, 50, 50), 4.0)
    env = smooth_env(1024)
    rng = np.random.default_rng(1)
    tgt = env.lookup(d + rng.normal(0, 0.02, d.shape)).astype(np.float64)
    ls = LevelSetField.from_sdf(lambda p: np.linalg.norm(p, axis=1) - 10.0, box, 48, 1.5, 1.0)
    vox = VoxelGrid.from_field(Sphere(radius=10.0, width=2.0), box=box, res=48, interp="bspline")
    free = binary_dilation(vox.values > 1 + 1e-9, iterations=2)
    scenes = [
        ("levelset ball R10 48^3", ls, live_cells_levelset(ls, box, 32, 0.0625), None, 0.25),
        ("voxel ball R10 48^3", vox, live_cells_nodes(free, vox, box, 32), free.ravel(), 0.5),
    ]
    for name, f, live, mask, step in scenes:
        ref = None
        for precision in ("float64", "float32"):
            # as a fit runs: checkpoints every 8 steps, adjoints that grow 30x cut
            kw = dict(step=step, precision=precision, checkpoint_every=8, growth_max=30.0)
            a, ta = timed_grad(GradientEngine(f, box, TraceSettings(**kw)), o, d, tgt, env)
            eng = GradientEngine(f, box, TraceSettings(skip_empty=True, **kw))
            eng.tracer.set_occupancy(distance_of(live))
            b, tb = timed_grad(eng, o, d, tgt, env)
            ga, gb = a.grad, b.grad
            if mask is not None:  # a fit zeroes the gradient of the nodes it does not free
                ga, gb = ga[mask], gb[mask]
            row = {
                "part": "train",
                "scene": name,
                "precision": precision,
                "step": step,
                "live_cells": float(live.mean()),
                "seconds": ta,
                "seconds_skip": tb,
                "speedup": ta / tb,
                "steps_per_ray": a.steps / len(o),
                "steps_per_ray_skip": b.steps / len(o),
                "loss_rel_diff": abs(a.loss - b.loss) / a.loss,
                "grad_rel_diff": float(np.abs(ga - gb).max() / np.abs(ga).max()),
                # rays that orbit inside the glass: float32 rounding, amplified, may change
                # their fate (exit or the step cap)
                "rays_status_differs": int((a.status != b.status).sum()),
            }
            if ref is None:
                ref = a
            else:  # float32's own error, without skipping: the scale of the differences
                gr = ref.grad[mask] if mask is not None else ref.grad
                row["own_loss_err"] = abs(a.loss - ref.loss) / ref.loss
                row["own_grad_err"] = float(np.abs(ga - gr).max() / np.abs(gr).max())
            rows_out.append(row)
            print(
                f"{name:22s} {precision}  live {100 * row['live_cells']:4.1f}%  {ta:.3f}s -> "
                f"{tb:.3f}s (x{ta / tb:.1f})  steps {row['steps_per_ray']:.0f} -> "
                f"{row['steps_per_ray_skip']:.0f}  loss diff {row['loss_rel_diff']:.1e}  "
                f"grad diff {row['grad_rel_diff']:.1e}  fate differs {row['rays_status_differs']}",
                flush=True,
            )
            if "own_loss_err" in row:
                print(
                    f"{'':22s} (float32 against float64 without skipping: loss "
                    f"{row['own_loss_err']:.1e}, grad {row['own_grad_err']:.1e})"
                )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rays", type=int, default=16384)
    ap.add_argument("--json", default="bench_results/skip_empty.json")
    ap.add_argument("--part", choices=("render", "train", "both"), default="both")
    args = ap.parse_args()
    rng = np.random.default_rng(0)
    n = args.rays
    # a camera-like bundle over the whole box face: most rays miss the small object
    o = np.column_stack([np.full(n, -120.0), rng.uniform(-45, 45, (n, 2))])
    d = np.column_stack([np.ones(n), rng.normal(0, 0.02, (n, 2))])
    rows = []
    if args.part in ("train", "both"):
        print("training: one loss and gradient (forward + backward), same rays")
        train_rows(o, d / np.linalg.norm(d, axis=1, keepdims=True), rows)
    if args.part == "train":
        scenes = []
    else:
        print("rendering: forward trace")
        scenes = [
            ("sphere R10 w1", Sphere(radius=10.0, eta=1.5, width=1.0), 0.125),
            ("luneburg R10", Luneburg(radius=10.0), 0.25),
            (
                "voxel sphere R10 65^3",
                VoxelGrid.from_field(Sphere(radius=10.0, width=2.0), res=65),
                0.5,
            ),
            ("hashgrid ball R10", *hashgrid_ball()),
        ]
    for name, f, step in scenes:
        box = f.tracing_box(Box())
        for precision in ("float32", "float64"):
            a, ta = timed(Tracer(f, box, TraceSettings(step=step, precision=precision)), o, d)
            t0 = time.perf_counter()  # the occupancy, sampled on the device
            skip = Tracer(f, box, TraceSettings(step=step, precision=precision, skip_empty=True))
            t_occ = time.perf_counter() - t0
            b, tb = timed(skip, o, d)
            dd = np.abs(a.direction - b.direction).max(1)
            row = {
                "part": "render",
                "scene": name,
                "precision": precision,
                "step": step,
                "seconds": ta,
                "seconds_skip": tb,
                "speedup": ta / tb,
                "occupancy_seconds": t_occ,
                "steps_per_ray": float(a.steps.mean()),
                "steps_per_ray_skip": float(b.steps.mean()),
                "max_direction_diff": float(dd.max()),
                "rays_over_1e-6": float(np.mean(dd > 1e-6)),
            }
            rows.append(row)
            print(
                f"{name:22s} {precision}  {ta:.3f}s -> {tb:.3f}s (x{ta / tb:.1f}, occupancy "
                f"{t_occ:.2f}s)  steps "
                f"{row['steps_per_ray']:.0f} -> {row['steps_per_ray_skip']:.0f}  max |dd| "
                f"{dd.max():.1e}, rays > 1e-6: {100 * row['rays_over_1e-6']:.2f}%",
                flush=True,
            )
    Path(args.json).parent.mkdir(parents=True, exist_ok=True)
    Path(args.json).write_text(json.dumps(rows, indent=1))
    print(f"wrote {args.json}")


if __name__ == "__main__":
    main()
