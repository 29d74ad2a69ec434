"""The hash grid's distillation (fitting it to a solid: a hash-grid start, and the refit
after every line-search step) five ways, side by side in one run: NumPy on the host in one
piece and in one piece per core on threads (float64), and the OpenCL kernels on the
default device (kernels_cl/hashgrid_distil.cl) in float32 and float64, their Adam step on
the device too (kernels_cl/adam.cl), and in float32 with the Adam step on the host (the
parameters and the gradient cross to it and back each step). Steps per second,
and what each fit came to: the largest parameter difference from the host's one-piece fit,
and the RMS error of eta against the sphere at 50,000 of the points.

The solid is a sphere in the quick protocol's box with the fit's default hash grid and its
ramp output at a 0.5 mm interface; 400,000 points as fit_to_field takes, 8,192 a step.

    python tools/bench_distil.py [--steps 150] [--threads 0] [--json bench_results/distil.json]
"""

from __future__ import annotations

import argparse
import json
import os
import time
from contextlib import contextmanager, nullcontext
from pathlib import Path

import numpy as np

import clrefract.fields.hashgrid_passes as passes
from clrefract.adam import Adam
from clrefract.fields.base import Box
from clrefract.fields.hashgrid import HashGridConfig, HashGridField
from clrefract.fit import FitConfig, hashgrid_config
from clrefract.limits import host_threads
from clrefract.runtime import default_runtime


class HostAdamPasses(passes.DevicePasses):
    """The device's passes with the Adam step on the host."""

    def begin(self, params, groups):
        self._p, self._host_adam = params.copy(), Adam(len(params), groups)

    def train_step(self, pts, residual, lr_scale):
        grad = self.reverse(*residual(*self.forward(self._p, pts)))
        self._host_adam.step(self._p, grad, lr_scale)

    def result(self):
        return self._p


@contextmanager
def adam_on_host():
    own = passes.DevicePasses
    passes.DevicePasses = HostAdamPasses
    try:
        yield
    finally:
        passes.DevicePasses = own


def distil(cfg: HashGridConfig, box: Box, solid, steps: int, threads: int, device):
    """Steps per second of one fit (a device's kernels built beforehand), and the field."""
    pts, phi, normal = solid
    os.environ["CLREFRACT_HOST_THREADS"] = str(threads)
    if device is not None:
        HashGridField(cfg, box, seed=0).fit_surface(pts, phi, normal, 1.5, 0.5, 1, device=device)
    field = HashGridField(cfg, box, seed=0)
    t0 = time.perf_counter()
    field.fit_surface(pts, phi, normal, 1.5, 0.5, iterations=steps, seed=1, device=device)
    return steps / (time.perf_counter() - t0), field


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
    solid = (pts, r - 8.0, pts / r[:, None])
    truth = 1.0 + 0.5 * (r[:50_000] < 8.0)
    runtime = default_runtime()
    ways = [
        ("host, 1 piece", 1, None),
        (f"host, {threads} pieces", threads, None),
        (f"{runtime.info.name[:24]}, float32", threads, (runtime, "float32")),
        (f"{runtime.info.name[:24]}, float64", threads, (runtime, "float64")),
        (f"{runtime.info.name[:16]}, float32, host Adam", threads, (runtime, "float32")),
    ]
    rows, first = [], None
    for name, n, device in ways:
        with adam_on_host() if name.endswith("host Adam") else nullcontext():
            rate, field = distil(cfg, box, solid, args.steps, n, device)
        first = field.data() if first is None else first
        rows.append(
            {
                "way": name,
                "steps_per_s": rate,
                "speedup": rate / rows[0]["steps_per_s"] if rows else 1.0,
                "max_param_diff": float(np.abs(field.data() - first).max()),
                "eta_rms": field.eta_rms(pts[:50_000], truth),
            }
        )
    print(f"{'way':<36} {'steps/s':>8} {'speedup':>8} {'param diff':>11} {'eta rms':>8}")
    for row in rows:
        print(
            f"{row['way']:<36} {row['steps_per_s']:8.1f} {row['speedup']:8.2f} "
            f"{row['max_param_diff']:11.2e} {row['eta_rms']:8.5f}"
        )
    out = Path(args.json)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps({"steps": args.steps, "rows": rows}, indent=2))
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
