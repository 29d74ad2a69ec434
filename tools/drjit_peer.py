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
the traced program as literals (the sum is unrolled), or clrefract's hash grid + MLP
(``drjit_trace_hashgrid``, ``drjit_eval_hashgrid``: its layout from
clrefract/fields/hashgrid.py, its parameters exported by bench_trace.hashgrid_export; the
levels and the MLP unrolled, the weights literals, the tables gathered, eta's gradient in
forward mode as clrefract's kernel computes it).

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


def _aligned(a, npt):
    """A copy of `a` at a 64-byte boundary: Dr.Jit maps NumPy's memory and compiles aligned
    and unaligned loads apart, so inputs at other addresses missed its kernel cache (a
    hash grid's kernel: 25 s to build again)."""
    a = np.asarray(a, dtype=npt).reshape(-1)
    buf = np.empty(a.size + 64, dtype=npt)
    off = (-buf.ctypes.data % 64) // buf.itemsize
    out = buf[off : off + a.size]
    out[:] = a
    return out


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


def _blobs_fn(blobs, Fl, Arr3):
    """eta and grad eta of the blob field, the sum over blobs unrolled with literal
    parameters."""
    inv2s2 = [-0.5 / (s * s) for (_, _, s) in blobs]
    inv_s2 = [1.0 / (s * s) for (_, _, s) in blobs]

    def field(x):
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
        return eta, Arr3(gx, gy, gz)

    return field


HASH_PRIMES = (1, 2654435761, 805459861)  # clrefract's (instant-ngp's) spatial hash


def _smoother(t):
    t = _min(_max(t, 0.0), 1.0)
    return t * t * t * (t * (t * 6.0 - 15.0) + 10.0)


def _smoother_d(t):
    inside = (t > 0.0) & (t < 1.0)
    return dr.select(inside, 30.0 * t * t * (t * (t - 2.0) + 1.0), 0.0)


def _hashgrid_fn(grid, Fl, Arr3, npt):
    """eta and grad eta of clrefract's hash grid + MLP (clrefract/fields/hashgrid.py's
    layout), from the parameters `grid` (hashgrid_export's dict) as a Dr.Jit user would
    write it: the levels and the MLP unrolled at trace time, the tables gathered from
    device arrays, the weights as literals, the gradient in forward mode alongside."""
    lo = [float(v) for v in grid["box_lo"]]
    size = [float(b) - float(a) for a, b in zip(grid["box_lo"], grid["box_hi"])]
    margin = float(grid["margin"])
    feats_per = int(grid["features"])
    mask = (1 << int(grid["log2_table"])) - 1
    smooth = grid["interp"] == "smoothstep"
    ramp = grid["output"] == "ramp"
    k_out = float(grid["eta_max"]) - 1.0
    tables = [Fl(_aligned(t.reshape(-1), npt)) for t in grid["tables"]]
    layers = [(np.asarray(w, float), np.asarray(b, float)) for w, b in grid["layers"]]

    def axis(uc, inside, n, scale):
        p = uc * float(n)
        c = _min(_max(dr.floor(p), 0.0), float(n - 1))
        t = p - c
        if smooth:
            return UInt32(c), t * t * (3.0 - 2.0 * t), inside * (6.0 * scale) * t * (1.0 - t)
        return UInt32(c), t, inside * scale

    def window_axis(x, a, b):
        d0 = (x - a) / margin - 1.0
        d1 = (b - x) / margin - 1.0
        s0, s1 = _smoother(d0), _smoother(d1)
        return s0 * s1, (_smoother_d(d0) * s1 - s0 * _smoother_d(d1)) / margin

    def field(x):
        xs = [x.x, x.y, x.z]
        u = [(xs[a] - lo[a]) / size[a] for a in range(3)]
        uc = [_min(_max(u[a], 0.0), 1.0) for a in range(3)]
        ins = [dr.select(u[a] == uc[a], Fl(1.0), Fl(0.0)) for a in range(3)]
        f, fx, fy, fz = [], [], [], []
        for lvl, n in enumerate(grid["resolutions"]):
            (i, sx, dsx), (j, sy, dsy), (k, sz, dsz) = (
                axis(uc[a], ins[a], n, n / size[a]) for a in range(3)
            )
            if grid["dense"][lvl]:
                s1 = n + 1
                base = (i * s1 + j) * s1 + k
                offs = [0, 1, s1, s1 + 1, s1 * s1, s1 * s1 + 1, s1 * s1 + s1, s1 * s1 + s1 + 1]
                idx = [base + o for o in offs]
            else:
                hy0, hz0 = j * HASH_PRIMES[1], k * HASH_PRIMES[2]
                hy1, hz1 = hy0 + HASH_PRIMES[1], hz0 + HASH_PRIMES[2]
                idx = [
                    (ii ^ hy ^ hz) & mask
                    for ii in (i, i + 1)
                    for hy in (hy0, hy1)
                    for hz in (hz0, hz1)
                ]
            corners = []
            for c in range(8):
                a, b, d = c >> 2, (c >> 1) & 1, c & 1
                ax_ = sx if a else 1.0 - sx
                ay_ = sy if b else 1.0 - sy
                az_ = sz if d else 1.0 - sz
                ayz = ay_ * az_
                corners.append(
                    (
                        ax_ * ayz,
                        (dsx if a else -dsx) * ayz,
                        ax_ * (dsy if b else -dsy) * az_,
                        ax_ * ay_ * (dsz if d else -dsz),
                    )
                )
            for q in range(feats_per):
                v, gx, gy, gz = Fl(0.0), Fl(0.0), Fl(0.0), Fl(0.0)
                for c in range(8):
                    t = dr.gather(Fl, tables[lvl], idx[c] * feats_per + q)
                    w, wx, wy, wz = corners[c]
                    v = dr.fma(w, t, v)
                    gx = dr.fma(wx, t, gx)
                    gy = dr.fma(wy, t, gy)
                    gz = dr.fma(wz, t, gz)
                f.append(v)
                fx.append(gx)
                fy.append(gy)
                fz.append(gz)
        # MLP, forward mode: h = W a + b, dh = W da, softplus on the hidden layers
        for W, b in layers[:-1]:
            nf, nx, ny, nz = [], [], [], []
            for row, bias in zip(W, b):
                v, gx, gy, gz = Fl(float(bias)), Fl(0.0), Fl(0.0), Fl(0.0)
                for w, a, ax_, ay_, az_ in zip(row, f, fx, fy, fz):
                    w = float(w)
                    v = dr.fma(a, w, v)
                    gx = dr.fma(ax_, w, gx)
                    gy = dr.fma(ay_, w, gy)
                    gz = dr.fma(az_, w, gz)
                e = dr.exp(-dr.abs(v))
                r = 1.0 / (1.0 + e)
                sig = dr.select(v >= 0.0, r, e * r)
                nf.append(_max(v, 0.0) + dr.log(1.0 + e))
                nx.append(sig * gx)
                ny.append(sig * gy)
                nz.append(sig * gz)
            f, fx, fy, fz = nf, nx, ny, nz
        W, b = layers[-1]
        o, ox, oy, oz = Fl(float(b[0])), Fl(0.0), Fl(0.0), Fl(0.0)
        for w, a, ax_, ay_, az_ in zip(W[0], f, fx, fy, fz):
            w = float(w)
            o = dr.fma(a, w, o)
            ox = dr.fma(ax_, w, ox)
            oy = dr.fma(ay_, w, oy)
            oz = dr.fma(az_, w, oz)
        if ramp:
            t = (o + 1.0) * 0.5
            g1, dg = k_out * _smoother(t), (0.5 * k_out) * _smoother_d(t)
        else:
            e = dr.exp(-dr.abs(o))
            r = 1.0 / (1.0 + e)
            sig = dr.select(o >= 0.0, r, e * r)
            g1 = k_out * sig
            dg = g1 * (1.0 - sig)
        (wa, da), (wb, db), (wc, dc) = (
            window_axis(xs[a], lo[a], lo[a] + size[a]) for a in range(3)
        )
        win = wa * wb * wc
        grad = Arr3(
            da * wb * wc * g1 + win * dg * ox,
            wa * db * wc * g1 + win * dg * oy,
            wa * wb * dc * g1 + win * dg * oz,
        )
        return 1.0 + win * g1, grad

    return field


def _drjit_run(origins, directions, blobs, box_lo, box_hi, h, max_steps, dtype):
    Fl, Arr3, _ = _types(dtype)
    return _drjit_trace(
        origins, directions, _blobs_fn(blobs, Fl, Arr3), box_lo, box_hi, h, max_steps, dtype
    )


def _drjit_trace(origins, directions, field, box_lo, box_hi, h, max_steps, dtype):
    """The traced RKN4 loop through `field` (x -> (eta, grad eta), Dr.Jit arrays)."""
    Fl, Arr3, npt = _types(dtype)
    lo = [float(v) for v in box_lo]
    hi = [float(v) for v in box_hi]
    h = float(h)
    max_steps = int(max_steps)

    def field_D(x):
        eta, g = field(x)
        return eta, Arr3(eta * g.x, eta * g.y, eta * g.z)

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

    o = Arr3(*[Fl(_aligned(origins[:, i], npt)) for i in range(3)])
    d = Arr3(*[Fl(_aligned(directions[:, i], npt)) for i in range(3)])
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


def drjit_trace_hashgrid(
    origins, directions, grid, box_lo, box_hi, h, max_steps, dtype="float32", warmup=True
):
    """Trace rays through clrefract's hash grid + MLP field with Dr.Jit (LLVM backend);
    `grid`: the field's parameters (bench_trace.hashgrid_export). Returns the dict of
    drjit_trace_blobs."""
    origins = np.asarray(origins, dtype=np.float64).reshape(-1, 3)
    directions = np.asarray(directions, dtype=np.float64).reshape(-1, 3)
    Fl, Arr3, npt = _types(dtype)
    field = _hashgrid_fn(grid, Fl, Arr3, npt)

    def run():
        return _drjit_trace(origins, directions, field, box_lo, box_hi, h, max_steps, dtype)

    if warmup:
        run()
    t0 = time.perf_counter()
    res = run()
    res["seconds"] = time.perf_counter() - t0
    return res


def drjit_eval_hashgrid(points, grid, dtype="float32"):
    """eta (n,) and grad eta (n, 3) of the hash grid at points (n, 3), by the Dr.Jit field
    the tracer above uses."""
    Fl, Arr3, npt = _types(dtype)
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    x = Arr3(*[Fl(_aligned(pts[:, i], npt)) for i in range(3)])
    eta, g = _hashgrid_fn(grid, Fl, Arr3, npt)(x)
    dr.eval(eta, g)
    return np.asarray(eta.numpy(), np.float64), np.asarray(g.numpy(), np.float64).T.copy()


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
