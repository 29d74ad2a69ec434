"""Exit-direction error against the step on the Luneburg lens (closed form, SPEC section 2).

A bundle of rays along +x enters the lens at P and must leave in direction -P / R. Shared by
tests/test_interface_steps.py and tools/bench_interface_order.py.
"""

from __future__ import annotations

import numpy as np

from .fields.analytic import Luneburg
from .tracer import EVALS_PER_STEP, Tracer, TraceSettings


def luneburg_bundle(n: int = 32, radius: float = 20.0, max_b: float = 0.9, seed: int = 0):
    """Origins, directions and the closed-form exit directions of n parallel rays."""
    rng = np.random.default_rng(seed)
    b = radius * max_b * np.sqrt(rng.uniform(0, 1, n))
    phi = rng.uniform(0, 2 * np.pi, n)
    yz = np.column_stack([b * np.cos(phi), b * np.sin(phi)])
    o = np.column_stack([np.full(n, -6 * radius), yz])
    d = np.tile([1.0, 0.0, 0.0], (n, 1))
    p = np.column_stack([-np.sqrt(radius**2 - b**2), yz])
    return o, d, -p / radius


def luneburg_exit_errors(
    steps,
    integrator="rkn4",
    precision="float64",
    interface_steps=True,
    n: int = 32,
    radius: float = 20.0,
) -> dict:
    """Largest |d - d_exact| over the bundle, and the field evaluations per ray, per step."""
    o, d, want = luneburg_bundle(n, radius)
    evals = EVALS_PER_STEP[integrator]
    errors, work = [], []
    for h in steps:
        settings = TraceSettings(
            step=float(h),
            integrator=integrator,
            precision=precision,
            interface_steps=interface_steps,
        )
        tr = Tracer(Luneburg(radius=radius), settings=settings)
        res = tr.trace(o, d)
        errors.append(float(np.linalg.norm(res.direction - want, axis=1).max()))
        work.append(float(evals * res.steps.mean()))
    return {"step": [float(h) for h in steps], "error": errors, "evals_per_ray": work}


def loglog_slope(x, y) -> float:
    """Least-squares slope of log y against log x: the observed order."""
    return float(np.polyfit(np.log(x), np.log(y), 1)[0])
