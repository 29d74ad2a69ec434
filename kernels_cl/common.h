/* Precision and lane width, fixed at build time.
 *
 * REAL is float or double. Each work-item carries LANES rays as one OpenCL vector (realv):
 * PoCL vectorises explicit vector types but not loops across work-items, so on CPUs LANES is
 * 8 or 16; on GPUs LANES is 1 and realv is a scalar. Masks come from comparisons of realv and
 * are only combined with && || ! (which agree between scalars and vectors).
 */
#ifdef REAL_IS_DOUBLE
#pragma OPENCL EXTENSION cl_khr_fp64 : enable
#define REAL double
#define REAL_EPS 1e-12
#else
#define REAL float
#define REAL_EPS 1e-6f
#endif

#ifndef LANES
#define LANES 1
#endif

#define CAT_(a, b) a##b
#define CAT(a, b) CAT_(a, b)

#if LANES == 1
typedef REAL realv;
#define VLOAD(i, p) ((p)[(i)])
#define VSTORE(v, i, p) ((p)[(i)] = (v))
#define ANY(m) (m)
#define SEL(a, b, m) ((m) ? (b) : (a))
#define TO_INTV(v) ((int)(v))
#define TO_REALV(v) ((REAL)(v))
#define VSTORE_INT(v, i, p) ((p)[(i)] = (v))
typedef int intv;
typedef int maskv;
#else
typedef CAT(REAL, LANES) realv;
typedef CAT(int, LANES) intv;
#ifdef REAL_IS_DOUBLE
#define MASK_T long
#else
#define MASK_T int
#endif
typedef CAT(MASK_T, LANES) maskv;
#define VLOAD(i, p) CAT(vload, LANES)((i), (p))
#define VSTORE(v, i, p) CAT(vstore, LANES)((v), (i), (p))
/* any() by halving ORs: PoCL's tested the lanes one by one, a branch each, on every step of
 * every ray loop. A mask lane is 0 or -1. */
inline __attribute__((always_inline)) int mask_any(maskv m) {
#if LANES == 16
    CAT(MASK_T, 8) m8 = m.lo | m.hi;
#elif LANES == 8
    CAT(MASK_T, 8) m8 = m;
#endif
#if LANES >= 8
    CAT(MASK_T, 4) m4 = m8.lo | m8.hi;
#elif LANES == 4
    CAT(MASK_T, 4) m4 = m;
#endif
#if LANES >= 4
    CAT(MASK_T, 2) m2 = m4.lo | m4.hi;
#else
    CAT(MASK_T, 2) m2 = m;
#endif
    return (m2.x | m2.y) != 0;
}
#define ANY(m) mask_any(m)
#define SEL(a, b, m) select((a), (b), (m))
#define TO_INTV(v) CAT(convert_int, LANES)(v)
#define TO_REALV(v) CAT(convert_, CAT(REAL, LANES))(v)
#define VSTORE_INT(v, i, p) CAT(vstore, LANES)((v), (i), (p))
#endif

#define RV(c) ((realv)(c))

/* Every field defines field_eval(FIELD_PARAMS, x, y, z, &gx, &gy, &gz) -> eta, with
 * scalar parameters in fp and bulk data (grid values, tables, weights) in fd. */
#define FIELD_PARAMS __global const REAL *restrict fp, __global const REAL *restrict fd
#define FIELD_ARGS fp, fd

/* The geometry is data, not build defines, so that one program serves every box and grid
 * shape: fp ends with lo (x y z), hi (x y z), the window margin, the node counts of a field's
 * grid (0 without one), its node spacing and their inverses and the margin's, from fp[GEO_AT]
 * (GEO_AT from the build: the number of the field's own parameters; clrefract/fields/base.py
 * Box.geometry). The host derives the spacings and inverses in float64: an evaluation that
 * divided for them ran a tenth slower. Helpers that read the geometry take fp. */
#define BOX_LO_X (fp[GEO_AT])
#define BOX_LO_Y (fp[GEO_AT + 1])
#define BOX_LO_Z (fp[GEO_AT + 2])
#define BOX_HI_X (fp[GEO_AT + 3])
#define BOX_HI_Y (fp[GEO_AT + 4])
#define BOX_HI_Z (fp[GEO_AT + 5])
#define MARGIN (fp[GEO_AT + 6])
#define VOX_NX ((int)fp[GEO_AT + 7])
#define VOX_NY ((int)fp[GEO_AT + 8])
#define VOX_NZ ((int)fp[GEO_AT + 9])
#define VOX_HX (fp[GEO_AT + 10])
#define VOX_HY (fp[GEO_AT + 11])
#define VOX_HZ (fp[GEO_AT + 12])
#define VOX_IHX (fp[GEO_AT + 13])
#define VOX_IHY (fp[GEO_AT + 14])
#define VOX_IHZ (fp[GEO_AT + 15])
#define INV_MARGIN (fp[GEO_AT + 16])

/* Status codes shared with the host (clrefract.tracer.Status). */
#define ST_EXITED 0
#define ST_MISSED 1
#define ST_TRAPPED 2
#define ST_NONFINITE 3

/* C2 quintic smoothstep on [0, 1] and its first two derivatives. */
inline realv smoother(realv t) {
    t = clamp(t, RV(0), RV(1));
    return t * t * t * (t * (t * RV(6) - RV(15)) + RV(10));
}
inline realv smoother_d(realv t) {
    realv in = SEL(RV(0), RV(1), t > RV(0) && t < RV(1));
    return in * RV(30) * t * t * (t * (t - RV(2)) + RV(1));
}
inline realv smoother_dd(realv t) {
    realv in = SEL(RV(0), RV(1), t > RV(0) && t < RV(1));
    return in * RV(60) * t * (RV(1) - t) * (RV(1) - RV(2) * t);
}

/* Float atomic add on global memory: the float-atomics extension where the build enables it
 * (FLOAT_ATOMICS, OpenCL C 3.0), else a compare-and-swap loop (portable OpenCL 1.2) whose
 * failed swap hands back the value to try next: one plain read a call, however contended
 * (Oclgrind reports that read as racing with the swaps; tools/oclgrind_check.py). */
#ifdef REAL_IS_DOUBLE
#pragma OPENCL EXTENSION cl_khr_int64_base_atomics : enable
inline void atomic_add_real(volatile __global REAL *p, REAL v) {
#if defined(FLOAT_ATOMICS) && defined(__opencl_c_ext_fp64_global_atomic_add)
    atomic_fetch_add_explicit((volatile __global atomic_double *)p, v, memory_order_relaxed);
#else
    union { long i; double f; } old, upd;
    long seen;
    old.f = *p;
    while (1) {
        upd.f = old.f + v;
        seen = atom_cmpxchg((volatile __global long *)p, old.i, upd.i);
        if (seen == old.i) break;
        old.i = seen;
    }
#endif
}
#else
inline void atomic_add_real(volatile __global REAL *p, REAL v) {
#if defined(FLOAT_ATOMICS) && defined(__opencl_c_ext_fp32_global_atomic_add)
    atomic_fetch_add_explicit((volatile __global atomic_float *)p, v, memory_order_relaxed);
#else
    union { int i; float f; } old, upd;
    int seen;
    old.f = *p;
    while (1) {
        upd.f = old.f + v;
        seen = atomic_cmpxchg((volatile __global int *)p, old.i, upd.i);
        if (seen == old.i) break;
        old.i = seen;
    }
#endif
}
#endif

/* The box window needs the geometry; programs without a box (Adam, the driver probe, the
 * volume baseline) build without GEO_AT. */
#ifdef GEO_AT
/* Box window: 0 within MARGIN of a wall, 1 beyond 2 MARGIN; learned fields are 1 + W (g - 1)
 * so that rays leave the box in straight lines. Returns W and its gradient. */
inline realv box_window(__global const REAL *restrict fp, realv x, realv y, realv z, realv *wx,
                        realv *wy, realv *wz) {
    const REAL im = INV_MARGIN;
    realv dx0 = (x - RV(BOX_LO_X)) * im - RV(1), dx1 = (RV(BOX_HI_X) - x) * im - RV(1);
    realv dy0 = (y - RV(BOX_LO_Y)) * im - RV(1), dy1 = (RV(BOX_HI_Y) - y) * im - RV(1);
    realv dz0 = (z - RV(BOX_LO_Z)) * im - RV(1), dz1 = (RV(BOX_HI_Z) - z) * im - RV(1);
    realv sx0 = smoother(dx0), sx1 = smoother(dx1);
    realv sy0 = smoother(dy0), sy1 = smoother(dy1);
    realv sz0 = smoother(dz0), sz1 = smoother(dz1);
    realv ax = sx0 * sx1, ay = sy0 * sy1, az = sz0 * sz1;
    realv gax = (smoother_d(dx0) * sx1 - sx0 * smoother_d(dx1)) * im;
    realv gay = (smoother_d(dy0) * sy1 - sy0 * smoother_d(dy1)) * im;
    realv gaz = (smoother_d(dz0) * sz1 - sz0 * smoother_d(dz1)) * im;
    *wx = gax * ay * az;
    *wy = ax * gay * az;
    *wz = ax * ay * gaz;
    return ax * ay * az;
}

/* Box window along one axis, a(x) = s(d0) s(d1) with d0 = (x - lo)/m - 1,
 * d1 = (hi - x)/m - 1, with its first and second derivatives (for the backward pass); im is
 * 1/m. */
inline __attribute__((always_inline)) realv window_axis_v(realv x, REAL lo, REAL hi, REAL im,
                                                          realv *da, realv *dda) {
    realv d0 = (x - RV(lo)) * im - RV(1), d1 = (RV(hi) - x) * im - RV(1);
    realv s0 = smoother(d0), s1 = smoother(d1);
    realv p0 = smoother_d(d0), p1 = smoother_d(d1);
    realv in0 = SEL(RV(0), RV(1), d0 > RV(0) && d0 < RV(1));
    realv in1 = SEL(RV(0), RV(1), d1 > RV(0) && d1 < RV(1));
    realv q0 = in0 * RV(60) * d0 * (RV(1) - d0) * (RV(1) - RV(2) * d0);
    realv q1 = in1 * RV(60) * d1 * (RV(1) - d1) * (RV(1) - RV(2) * d1);
    *da = (p0 * s1 - s0 * p1) * im;
    *dda = (q0 * s1 - RV(2) * p0 * p1 + s0 * q1) * (im * im);
    return s0 * s1;
}
/* Box window W with its gradient g and Hessian H (xx yy zz xy xz yz). */
inline __attribute__((always_inline)) realv window_hess_v(__global const REAL *restrict fp,
                                                          realv x, realv y, realv z, realv *g,
                                                          realv *H) {
    realv dax, ddax, day, dday, daz, ddaz;
    const REAL im = INV_MARGIN;
    realv ax = window_axis_v(x, BOX_LO_X, BOX_HI_X, im, &dax, &ddax);
    realv ay = window_axis_v(y, BOX_LO_Y, BOX_HI_Y, im, &day, &dday);
    realv az = window_axis_v(z, BOX_LO_Z, BOX_HI_Z, im, &daz, &ddaz);
    g[0] = dax * ay * az; g[1] = ax * day * az; g[2] = ax * ay * daz;
    H[0] = ddax * ay * az; H[1] = ax * dday * az; H[2] = ax * ay * ddaz;
    H[3] = dax * day * az; H[4] = dax * ay * daz; H[5] = ax * day * daz;
    return ax * ay * az;
}
#endif
