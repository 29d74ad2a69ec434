"""Dr.Jit peer implementation of the clrefract RK-Nystrom eikonal tracer.

A user of Dr.Jit (LLVM backend) would write the curved-ray tracer this way: one symbolic
``dr.while_loop`` with a per-ray active mask, compiled into a single vectorised LLVM kernel.
The algorithm is the same as the clrefract OpenCL kernel (SPEC.md section 2), so the timings
are a fair comparison:

- normalise d, slab-intersect the box; missed rays get status 1 (position = origin).
- x = o + max(tmin, 0) d, v = eta(x) d; optical-path form x'' = D(x) = eta grad eta.
- Sharma's Runge-Kutta-Nystrom step (3 field evaluations per step).
- a step that leaves the box is rolled back and the ray flies straight along v/|v| from the
  previous point to the box face: status 0.
- a ray still inside after ``max_steps`` steps: status 2, its current state.

The field is the analytic Gaussian-blob field
``eta(x) = 1 + sum_k a_k exp(-|x - c_k|^2 / (2 s_k^2))`` with the blob parameters baked into
the traced program as literals (the sum is unrolled).

``drjit_trace_blobs`` times one run of the traced computation (tracing the Python graph,
``dr.eval`` and the copy back to NumPy). With ``warmup=True`` (the default) it first runs the
same computation once untimed, so JIT compilation is excluded (Dr.Jit caches the kernel).

Run ``python tools/drjit_peer.py`` to compare with the float64 NumPy reference and print the
Dr.Jit rate in ray-steps per second.
"""

from __future__ import annotations

import argparse
import time

import drjit as dr
import numpy as np
from drjit.llvm import Array3f, Array3f64, Bool, Float, Float64, UInt32


def _max(a, b):
    # dr.maximum/dr.minimum lower to llvm.maximum/llvm.minimum, which the LLVM found by
    # drjit here fails to select ("Cannot select: fmaximum") in this kernel; a select works.
    return dr.select(a > b, a, b)


def _min(a, b):
    return dr.select(a < b, a, b)


def _types(dtype):
    dt = np.dtype(dtype)
    if dt == np.float32:
        return Float, Array3f, np.float32
    if dt == np.float64:
        return Float64, Array3f64, np.float64
    raise ValueError(f"dtype must be float32 or float64, got {dtype!r}")


def _blob_terms(centers, amps, sigmas):
    centers = np.asarray(centers, dtype=np.float64).reshape(-1, 3)
    amps = np.asarray(amps, dtype=np.float64).reshape(-1)
    sigmas = np.asarray(sigmas, dtype=np.float64).reshape(-1)
    if not (len(centers) == len(amps) == len(sigmas)):
        raise ValueError("centers, amps and sigmas must have the same length")
    return [
        (tuple(float(c) for c in centers[k]), float(amps[k]), float(sigmas[k]))
        for k in range(len(amps))
    ]


def _drjit_run(origins, directions, blobs, box_lo, box_hi, h, max_steps, dtype):
    Fl, Arr3, npt = _types(dtype)
    lo = [float(v) for v in box_lo]
    hi = [float(v) for v in box_hi]
    h = float(h)
    max_steps = int(max_steps)
    inv2s2 = [-0.5 / (s * s) for (_, _, s) in blobs]
    inv_s2 = [1.0 / (s * s) for (_, _, s) in blobs]

    def field_D(x):
        # D = eta grad eta, sum over blobs unrolled with literal parameters.
        eta = Fl(1.0)
        gx = Fl(0.0)
        gy = Fl(0.0)
        gz = Fl(0.0)
        for k, (c, a, _) in enumerate(blobs):
            dx = x.x - c[0]
            dy = x.y - c[1]
            dz = x.z - c[2]
            r2 = dx * dx + dy * dy + dz * dz
            g = a * dr.exp(r2 * inv2s2[k])
            eta = eta + g
            w = -g * inv_s2[k]
            gx = dr.fma(w, dx, gx)
            gy = dr.fma(w, dy, gy)
            gz = dr.fma(w, dz, gz)
        return eta, Arr3(eta * gx, eta * gy, eta * gz)

    def eta_of(x):
        return field_D(x)[0]

    def outside(x):
        return (
            (x.x < lo[0])
            | (x.x > hi[0])
            | (x.y < lo[1])
            | (x.y > hi[1])
            | (x.z < lo[2])
            | (x.z > hi[2])
        )

    o = Arr3(*[Fl(np.ascontiguousarray(origins[:, i], dtype=npt)) for i in range(3)])
    d = Arr3(*[Fl(np.ascontiguousarray(directions[:, i], dtype=npt)) for i in range(3)])
    d = d / dr.norm(d)

    # Slab intersection with the box.
    tmin = Fl(-np.inf)
    tmax = Fl(np.inf)
    for i in range(3):
        inv = 1.0 / d[i]
        t1 = (lo[i] - o[i]) * inv
        t2 = (hi[i] - o[i]) * inv
        tmin = _max(tmin, _min(t1, t2))
        tmax = _min(tmax, _max(t1, t2))
    t0 = _max(tmin, 0.0)
    hit = tmax >= t0

    x = dr.select(hit, o + t0 * d, o)
    v = dr.select(hit, eta_of(x) * d, d)
    status = dr.select(hit, UInt32(2), UInt32(1))
    steps = dr.zeros(UInt32, dr.width(x))
    active = Bool(hit)
    half_h = 0.5 * h
    h8 = h / 8.0
    sixth = 1.0 / 6.0

    def cond(x, v, status, steps, active):
        return active & (steps < max_steps)

    def body(x, v, status, steps, active):
        A = h * field_D(x)[1]
        B = h * field_D(x + half_h * v + h8 * A)[1]
        C = h * field_D(x + h * v + half_h * B)[1]
        x_new = x + h * (v + (A + 2.0 * B) * sixth)
        v_new = v + (A + 4.0 * B + C) * sixth
        out = outside(x_new)

        # Finished rays: fly straight from the previous point to the box face.
        vh = v / dr.norm(v)
        t = Fl(np.inf)
        for i in range(3):
            face = dr.select(vh[i] > 0.0, hi[i], lo[i])
            ti = dr.select(vh[i] != 0.0, (face - x[i]) / vh[i], np.inf)
            t = _min(t, ti)
        x_exit = x + t * vh

        x = dr.select(out, x_exit, x_new)
        v = dr.select(out, vh, v_new)
        status = dr.select(out, UInt32(0), status)
        return x, v, status, steps + 1, active & ~out

    x, v, status, steps, active = dr.while_loop(
        state=(x, v, status, steps, active),
        cond=cond,
        body=body,
        labels=("x", "v", "status", "steps", "active"),
        label="rkn_trace",
    )
    # Rays still inside report a unit direction too.
    v = dr.select(status == 2, v / dr.norm(v), v)
    dr.eval(x, v, status, steps)
    return dict(
        position=np.asarray(x.numpy()).T.copy(),
        direction=np.asarray(v.numpy()).T.copy(),
        status=np.asarray(status.numpy()).astype(np.int32),
        steps=np.asarray(steps.numpy()).astype(np.int64),
    )


def drjit_trace_blobs(
    origins,
    directions,
    centers,
    amps,
    sigmas,
    box_lo,
    box_hi,
    h,
    max_steps,
    dtype="float32",
    warmup=True,
):
    """Trace rays through a Gaussian-blob field with Dr.Jit (LLVM backend).

    origins, directions: (N, 3) arrays. centers (K, 3), amps (K,), sigmas (K,).
    Returns dict(position=(N,3), direction=(N,3) unit, status=(N,) int
    (0 exited, 1 missed the box, 2 max_steps reached), steps=(N,) int RK steps taken
    (the step that left the box counts), seconds=float wall time of one run (graph
    tracing, dr.eval, copy back to NumPy). With warmup=True an untimed run of the same
    computation comes first so that JIT compilation is excluded from ``seconds``.
    """
    origins = np.asarray(origins, dtype=np.float64).reshape(-1, 3)
    directions = np.asarray(directions, dtype=np.float64).reshape(-1, 3)
    blobs = _blob_terms(centers, amps, sigmas)
    args = (origins, directions, blobs, box_lo, box_hi, h, max_steps, dtype)
    if warmup:
        _drjit_run(*args)
    t0 = time.perf_counter()
    res = _drjit_run(*args)
    res["seconds"] = time.perf_counter() - t0
    return res


def _np_field_D(x, blobs):
    eta = np.ones(len(x))
    grad = np.zeros_like(x)
    for c, a, s in blobs:
        dx = x - np.asarray(c)
        g = a * np.exp(-np.einsum("ij,ij->i", dx, dx) / (2.0 * s * s))
        eta += g
        grad -= (g / (s * s))[:, None] * dx
    return eta, eta[:, None] * grad


def numpy_trace_blobs(origins, directions, centers, amps, sigmas, box_lo, box_hi, h, max_steps):
    """Float64 NumPy reference with the same algorithm as ``drjit_trace_blobs``.

    Returns the same dict (seconds = wall time of the call).
    """
    t_start = time.perf_counter()
    blobs = _blob_terms(centers, amps, sigmas)
    lo = np.asarray(box_lo, dtype=np.float64).reshape(3)
    hi = np.asarray(box_hi, dtype=np.float64).reshape(3)
    h = float(h)
    o = np.asarray(origins, dtype=np.float64).reshape(-1, 3)
    d = np.asarray(directions, dtype=np.float64).reshape(-1, 3)
    d = d / np.linalg.norm(d, axis=1, keepdims=True)
    n = len(o)

    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / d
        t1 = (lo - o) * inv
        t2 = (hi - o) * inv
    tmin = np.max(np.minimum(t1, t2), axis=1)
    tmax = np.min(np.maximum(t1, t2), axis=1)
    t0 = np.maximum(tmin, 0.0)
    hit = tmax >= t0

    x = o.copy()
    v = d.copy()
    x[hit] = o[hit] + t0[hit, None] * d[hit]
    v[hit] = _np_field_D(x[hit], blobs)[0][:, None] * d[hit]
    status = np.where(hit, 2, 1).astype(np.int32)
    steps = np.zeros(n, dtype=np.int64)

    idx = np.nonzero(hit)[0]
    for _ in range(int(max_steps)):
        if idx.size == 0:
            break
        xa = x[idx]
        va = v[idx]
        A = h * _np_field_D(xa, blobs)[1]
        B = h * _np_field_D(xa + 0.5 * h * va + h / 8.0 * A, blobs)[1]
        C = h * _np_field_D(xa + h * va + 0.5 * h * B, blobs)[1]
        x_new = xa + h * (va + (A + 2.0 * B) / 6.0)
        v_new = va + (A + 4.0 * B + C) / 6.0
        steps[idx] += 1
        out = np.any((x_new < lo) | (x_new > hi), axis=1)

        if out.any():
            xo = xa[out]
            vh = va[out] / np.linalg.norm(va[out], axis=1, keepdims=True)
            face = np.where(vh > 0.0, hi, lo)
            with np.errstate(divide="ignore", invalid="ignore"):
                ti = np.where(vh != 0.0, (face - xo) / vh, np.inf)
            t = ti.min(axis=1)
            io = idx[out]
            x[io] = xo + t[:, None] * vh
            v[io] = vh
            status[io] = 0
        keep = ~out
        x[idx[keep]] = x_new[keep]
        v[idx[keep]] = v_new[keep]
        idx = idx[keep]

    inside = status == 2
    v[inside] /= np.linalg.norm(v[inside], axis=1, keepdims=True)
    return dict(
        position=x,
        direction=v,
        status=status,
        steps=steps,
        seconds=time.perf_counter() - t_start,
    )


def make_scene(n_rays=1 << 16, seed=0):
    """Rays from the plane z = -80 aimed at the box [-50, 50]^3, 4 blobs inside."""
    rng = np.random.default_rng(seed)
    m = int(np.ceil(np.sqrt(n_rays)))
    g = np.linspace(-45.0, 45.0, m)
    gx, gy = np.meshgrid(g, g, indexing="ij")
    xy = np.stack([gx.ravel(), gy.ravel()], axis=1)[:n_rays]
    origins = np.column_stack([xy, np.full(len(xy), -80.0)])
    directions = np.column_stack([rng.normal(0.0, 0.02, size=(len(xy), 2)), np.ones(len(xy))])
    centers = np.array([[0.0, 0.0, 0.0], [10.0, -8.0, 6.0], [-9.0, 7.0, -5.0], [5.0, 9.0, -10.0]])
    amps = np.array([0.2, 0.1, 0.15, 0.05])
    sigmas = np.array([10.0, 8.0, 9.0, 12.0])
    return dict(
        origins=origins,
        directions=directions,
        centers=centers,
        amps=amps,
        sigmas=sigmas,
        box_lo=(-50.0, -50.0, -50.0),
        box_hi=(50.0, 50.0, 50.0),
    )


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--log2-rays", type=int, default=16)
    ap.add_argument("--h", type=float, default=1.0)
    ap.add_argument("--max-steps", type=int, default=400)
    ap.add_argument("--repeats", type=int, default=3, help="timed Dr.Jit runs (best kept)")
    args = ap.parse_args()

    scene = make_scene(1 << args.log2_rays)
    kw = dict(scene, h=args.h, max_steps=args.max_steps)

    ref = numpy_trace_blobs(**kw)
    print(f"numpy float64 reference: {ref['seconds']:.3f} s")

    for dtype in ("float32", "float64"):
        t0 = time.perf_counter()
        res = drjit_trace_blobs(**kw, dtype=dtype, warmup=False)
        first = time.perf_counter() - t0
        best = None
        for _ in range(args.repeats):
            r = drjit_trace_blobs(**kw, dtype=dtype, warmup=False)
            if best is None or r["seconds"] < best["seconds"]:
                best = r
        res = best
        total_steps = int(res["steps"].sum())
        same_status = np.array_equal(res["status"], ref["status"])
        same_steps = np.array_equal(res["steps"], ref["steps"])
        ddir = np.abs(res["direction"] - ref["direction"]).max()
        dpos = np.abs(res["position"] - ref["position"]).max()
        counts = np.bincount(res["status"], minlength=3)
        print(f"drjit {dtype}:")
        print(f"  first call (incl. JIT compile) {first:.3f} s, timed run {res['seconds']:.4f} s")
        print(f"  status counts exited/missed/max_steps: {counts.tolist()}")
        print(f"  status identical to numpy: {same_status}, steps identical: {same_steps}")
        print(f"  max |exit direction - numpy f64|: {ddir:.3e}")
        print(f"  max |exit position  - numpy f64|: {dpos:.3e} mm")
        print(
            f"  ray-steps: {total_steps} ({total_steps / len(res['steps']):.1f} per ray), "
            f"rate {total_steps / res['seconds']:.3e} ray-steps/s"
        )


if __name__ == "__main__":
    main()
