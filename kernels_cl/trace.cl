/* Curved-ray tracing in the optical-path form: x' = v, v' = D(x) = eta grad eta, |v| = eta.
 * INTEGRATOR_RKN4 (Sharma's Runge-Kutta-Nystrom, 3 evaluations, 4th order),
 * INTEGRATOR_RK4 (classic 4-stage on (x, v)), INTEGRATOR_EULER, or INTEGRATOR_DOPRI5
 * (Dormand-Prince 5(4), 7 evaluations; with ADAPTIVE_TOL its step adapts, forward only),
 * chosen at build time. */

/* region: which side of a field's kinks a step integrates on (fields with FIELD_INTERFACE
 * only; -2: by position) */
inline void field_D(FIELD_PARAMS, realv region, realv x, realv y, realv z, realv *dx, realv *dy,
                    realv *dz) {
    realv gx, gy, gz;
#ifdef FIELD_INTERFACE
    realv eta = field_eval_region(FIELD_ARGS, x, y, z, region, &gx, &gy, &gz);
#else
    realv eta = field_eval(FIELD_ARGS, x, y, z, &gx, &gy, &gz);
#endif
    *dx = eta * gx;
    *dy = eta * gy;
    *dz = eta * gz;
}

#if defined(INTEGRATOR_DOPRI5)
/* Dormand-Prince 5(4) on y = (x, v), y' = (v, D(x)): 7 stages, the 5th-order solution and
 * the difference to the embedded 4th-order one (*err: its largest component, mm or |v|
 * units). Each stage costs one field evaluation. */
__constant REAL DP_A[7][6] = {
    {0, 0, 0, 0, 0, 0},
    {(REAL)(1.0 / 5), 0, 0, 0, 0, 0},
    {(REAL)(3.0 / 40), (REAL)(9.0 / 40), 0, 0, 0, 0},
    {(REAL)(44.0 / 45), (REAL)(-56.0 / 15), (REAL)(32.0 / 9), 0, 0, 0},
    {(REAL)(19372.0 / 6561), (REAL)(-25360.0 / 2187), (REAL)(64448.0 / 6561),
     (REAL)(-212.0 / 729), 0, 0},
    {(REAL)(9017.0 / 3168), (REAL)(-355.0 / 33), (REAL)(46732.0 / 5247), (REAL)(49.0 / 176),
     (REAL)(-5103.0 / 18656), 0},
    {(REAL)(35.0 / 384), 0, (REAL)(500.0 / 1113), (REAL)(125.0 / 192), (REAL)(-2187.0 / 6784),
     (REAL)(11.0 / 84)}};
/* b5 - b4 */
__constant REAL DP_E[7] = {(REAL)(71.0 / 57600),     0,
                           (REAL)(-71.0 / 16695),    (REAL)(71.0 / 1920),
                           (REAL)(-17253.0 / 339200), (REAL)(22.0 / 525),
                           (REAL)(-1.0 / 40)};

inline void ode_dopri(FIELD_PARAMS, realv h, realv region, realv x, realv y, realv z, realv vx,
                      realv vy, realv vz, realv *ix, realv *iy, realv *iz, realv *ivx,
                      realv *ivy, realv *ivz, realv *err) {
    realv Vx[7], Vy[7], Vz[7], Kx[7], Ky[7], Kz[7];
    for (int i = 0; i < 7; ++i) {
        realv sx = RV(0), sy = RV(0), sz = RV(0), tx = RV(0), ty = RV(0), tz = RV(0);
        for (int j = 0; j < i; ++j) {
            REAL a = DP_A[i][j];
            sx += a * Vx[j]; sy += a * Vy[j]; sz += a * Vz[j];
            tx += a * Kx[j]; ty += a * Ky[j]; tz += a * Kz[j];
        }
        Vx[i] = vx + h * tx; Vy[i] = vy + h * ty; Vz[i] = vz + h * tz;
        field_D(FIELD_ARGS, region, x + h * sx, y + h * sy, z + h * sz, &Kx[i], &Ky[i], &Kz[i]);
    }
    realv sx = RV(0), sy = RV(0), sz = RV(0), tx = RV(0), ty = RV(0), tz = RV(0);
    realv ex = RV(0), ey = RV(0), ez = RV(0), fx = RV(0), fy = RV(0), fz = RV(0);
    for (int j = 0; j < 7; ++j) {
        REAL b = DP_A[6][j < 6 ? j : 0] * (j < 6 ? (REAL)1 : (REAL)0), e = DP_E[j];
        sx += b * Vx[j]; sy += b * Vy[j]; sz += b * Vz[j];
        tx += b * Kx[j]; ty += b * Ky[j]; tz += b * Kz[j];
        ex += e * Vx[j]; ey += e * Vy[j]; ez += e * Vz[j];
        fx += e * Kx[j]; fy += e * Ky[j]; fz += e * Kz[j];
    }
    *ix = h * sx; *iy = h * sy; *iz = h * sz;
    *ivx = h * tx; *ivy = h * ty; *ivz = h * tz;
    *err = h * fmax(fmax(fmax(fabs(ex), fabs(ey)), fmax(fabs(ez), fabs(fx))),
                    fmax(fabs(fy), fabs(fz)));
}
#endif

#if defined(INTEGRATOR_RKN4)
/* One RKN4 step's increments; P (or 0) receives the points of its second and third stages,
 * which the discrete adjoint (adjoint_discrete.cl) replays with this very arithmetic. */
inline void rkn4_incr(FIELD_PARAMS, realv h, realv region, realv x, realv y, realv z, realv vx,
                      realv vy, realv vz, realv *ix, realv *iy, realv *iz, realv *ivx, realv *ivy,
                      realv *ivz, realv *P) {
    realv ax, ay, az, bx, by, bz, cx, cy, cz;
    field_D(FIELD_ARGS, region, x, y, z, &ax, &ay, &az);
    ax *= h; ay *= h; az *= h;
    realv h2 = RV(0.5) * h, h8 = RV(0.125) * h;
    realv bpx = x + h2 * vx + h8 * ax, bpy = y + h2 * vy + h8 * ay, bpz = z + h2 * vz + h8 * az;
    field_D(FIELD_ARGS, region, bpx, bpy, bpz, &bx, &by, &bz);
    bx *= h; by *= h; bz *= h;
    realv cpx = x + h * vx + h2 * bx, cpy = y + h * vy + h2 * by, cpz = z + h * vz + h2 * bz;
    field_D(FIELD_ARGS, region, cpx, cpy, cpz, &cx, &cy, &cz);
    cx *= h; cy *= h; cz *= h;
    if (P) {
        P[0] = bpx; P[1] = bpy; P[2] = bpz;
        P[3] = cpx; P[4] = cpy; P[5] = cpz;
    }
    const REAL s = (REAL)1 / (REAL)6;
    *ix = h * (vx + s * (ax + RV(2) * bx));
    *iy = h * (vy + s * (ay + RV(2) * by));
    *iz = h * (vz + s * (az + RV(2) * bz));
    *ivx = s * (ax + RV(4) * bx + cx);
    *ivy = s * (ay + RV(4) * by + cy);
    *ivz = s * (az + RV(4) * bz + cz);
}
#endif

/* One step's increments (dx, dv) from (x, v); h per lane (interface steps shorten it). The
 * caller adds them (compensated in trace_rays where built with TRACE_COMPENSATED: at 1e-3 mm
 * steps, float32 x + h v would lose the increment's low bits on every step). */
inline void ode_incr(FIELD_PARAMS, realv h, realv region, realv x0, realv y0, realv z0, realv vx0, realv vy0,
                     realv vz0, realv *ix, realv *iy, realv *iz, realv *ivx, realv *ivy,
                     realv *ivz) {
    realv x_ = x0, y_ = y0, z_ = z0, vx_ = vx0, vy_ = vy0, vz_ = vz0;
    realv *x = &x_, *y = &y_, *z = &z_, *vx = &vx_, *vy = &vy_, *vz = &vz_;
#if defined(INTEGRATOR_RKN4)
    rkn4_incr(FIELD_ARGS, h, region, *x, *y, *z, *vx, *vy, *vz, ix, iy, iz, ivx, ivy, ivz, 0);
#elif defined(INTEGRATOR_RK4)
    realv h2 = RV(0.5) * h;
    realv k1x, k1y, k1z, k2x, k2y, k2z, k3x, k3y, k3z, k4x, k4y, k4z;
    field_D(FIELD_ARGS, region, *x, *y, *z, &k1x, &k1y, &k1z);
    realv u2x = *vx + h2 * k1x, u2y = *vy + h2 * k1y, u2z = *vz + h2 * k1z;
    field_D(FIELD_ARGS, region, *x + h2 * *vx, *y + h2 * *vy, *z + h2 * *vz, &k2x, &k2y, &k2z);
    realv u3x = *vx + h2 * k2x, u3y = *vy + h2 * k2y, u3z = *vz + h2 * k2z;
    field_D(FIELD_ARGS, region, *x + h2 * u2x, *y + h2 * u2y, *z + h2 * u2z, &k3x, &k3y, &k3z);
    realv u4x = *vx + h * k3x, u4y = *vy + h * k3y, u4z = *vz + h * k3z;
    field_D(FIELD_ARGS, region, *x + h * u3x, *y + h * u3y, *z + h * u3z, &k4x, &k4y, &k4z);
    const realv s = h / RV(6);
    *ix = s * (*vx + RV(2) * (u2x + u3x) + u4x);
    *iy = s * (*vy + RV(2) * (u2y + u3y) + u4y);
    *iz = s * (*vz + RV(2) * (u2z + u3z) + u4z);
    *ivx = s * (k1x + RV(2) * (k2x + k3x) + k4x);
    *ivy = s * (k1y + RV(2) * (k2y + k3y) + k4y);
    *ivz = s * (k1z + RV(2) * (k2z + k3z) + k4z);
#elif defined(INTEGRATOR_DOPRI5)
    realv e_;
    ode_dopri(FIELD_ARGS, h, region, *x, *y, *z, *vx, *vy, *vz, ix, iy, iz, ivx, ivy, ivz, &e_);
#elif defined(INTEGRATOR_EULER)
    realv ax, ay, az;
    field_D(FIELD_ARGS, region, *x, *y, *z, &ax, &ay, &az);
    *ix = h * *vx;
    *iy = h * *vy;
    *iz = h * *vz;
    *ivx = h * ax;
    *ivy = h * ay;
    *ivz = h * az;
#else
#error "no INTEGRATOR_* defined"
#endif
}

inline void ode_step(FIELD_PARAMS, realv h, realv *x, realv *y, realv *z, realv *vx, realv *vy,
                     realv *vz) {
    realv ix, iy, iz, ivx, ivy, ivz;
    ode_incr(FIELD_ARGS, h, RV(-2), *x, *y, *z, *vx, *vy, *vz, &ix, &iy, &iz, &ivx, &ivy, &ivz);
    *x += ix; *y += iy; *z += iz;
    *vx += ivx; *vy += ivy; *vz += ivz;
}

/* Kahan summation s += d with compensation c, into (ns, nc): applied only where accepted.
 * Built only with TRACE_COMPENSATED (the tracer sets it where rounding calls for it:
 * clrefract/tracer.py compensated_sums); else a plain sum, c stays 0 and folds away. */
#ifdef TRACE_COMPENSATED
#define KAHAN(s, c, d, ns, nc)                                                                  \
    do {                                                                                      \
        realv y_ = (d) - (c);                                                                 \
        (ns) = (s) + y_;                                                                      \
        (nc) = ((ns) - (s)) - y_;                                                             \
    } while (0)
#else
#define KAHAN(s, c, d, ns, nc)                                                                  \
    do {                                                                                      \
        (ns) = (s) + (d);                                                                     \
        (nc) = (c);                                                                           \
    } while (0)
#endif

/* The state (x, v) plus the increments (ix .. ivz), compensated: the sums in nx .. nvz, their
 * compensations in ncx .. ncvz (from cx .. cvz). */
#define KAHAN_STATE                                                                             \
    realv nx, ny, nz, nvx, nvy, nvz, ncx, ncy, ncz, ncvx, ncvy, ncvz;                          \
    KAHAN(x, cx, ix, nx, ncx);                                                                 \
    KAHAN(y, cy, iy, ny, ncy);                                                                 \
    KAHAN(z, cz, iz, nz, ncz);                                                                 \
    KAHAN(vx, cvx, ivx, nvx, ncvx);                                                            \
    KAHAN(vy, cvy, ivy, nvy, ncvy);                                                            \
    KAHAN(vz, cvz, ivz, nvz, ncvz)

inline maskv outside_box(__global const REAL *restrict fp, realv x, realv y, realv z) {
    return x < RV(BOX_LO_X) || x > RV(BOX_HI_X) || y < RV(BOX_LO_Y) || y > RV(BOX_HI_Y) ||
           z < RV(BOX_LO_Z) || z > RV(BOX_HI_Z);
}

/* Distance along the unit direction d from a point inside the box to its boundary. */
inline realv box_exit_t(__global const REAL *restrict fp, realv x, realv y, realv z, realv dx,
                        realv dy, realv dz) {
    realv tx = (SEL(RV(BOX_LO_X), RV(BOX_HI_X), dx > RV(0)) - x) / dx;
    realv ty = (SEL(RV(BOX_LO_Y), RV(BOX_HI_Y), dy > RV(0)) - y) / dy;
    realv tz = (SEL(RV(BOX_LO_Z), RV(BOX_HI_Z), dz > RV(0)) - z) / dz;
    tx = SEL(tx, RV(INFINITY), dx == RV(0));
    ty = SEL(ty, RV(INFINITY), dy == RV(0));
    tz = SEL(tz, RV(INFINITY), dz == RV(0));
    return fmax(fmin(fmin(tx, ty), tz), RV(0));
}

#ifdef FIELD_INTERFACE
/* Steps onto a kink. field_interface(x) is about a signed distance in mm, and the field's
 * derivatives jump where it equals INTERFACE_LO or INTERFACE_HI (the Luneburg surface, the
 * two edges of a solid's interface band). A step that integrates across such a jump costs a
 * fixed-step scheme its order (RK4 on the Luneburg lens: first order). So every step uses one
 * region's formula at all its stages (field_eval_region, continued a little past the edges),
 * and a step whose end would lie in another region is shortened to land on the edge, found
 * by regula falsi (Anderson-Bjorck) on the step fraction with trial steps; the next step then uses
 * the far region's formula. Lanes that do not cross keep their full step. An event-located
 * step like this is what keeps RK4 fourth order through the Luneburg surface. */
#ifndef INTERFACE_ITERS
#define INTERFACE_ITERS 10
#endif
#ifdef REAL_IS_DOUBLE
#define INTERFACE_TOL 1e-10
#else
#define INTERFACE_TOL 2e-5f
#endif

/* -1 below INTERFACE_LO, 0 between, +1 above INTERFACE_HI */
inline realv region_of(FIELD_PARAMS, realv s) {
    return SEL(SEL(RV(0), RV(1), s > RV(INTERFACE_HI)), RV(-1), s < RV(INTERFACE_LO));
}

/* On entry: the full step's increments from (x, v) in *region, and the interface value *s_at
 * at x. On exit: the increments of the step to take, its length *h, the region the next step
 * uses and the interface value at the step's end. */
inline void interface_step(FIELD_PARAMS, maskv active, realv *h, realv *region, realv *s_at,
                           realv x, realv y, realv z, realv vx, realv vy, realv vz, realv *ix,
                           realv *iy, realv *iz, realv *ivx, realv *ivy, realv *ivz) {
    const REAL lo = INTERFACE_LO, hi = INTERFACE_HI;
    realv s0 = *s_at;
    realv s1 = field_interface(FIELD_ARGS, x + *ix, y + *iy, z + *iz);
    *s_at = s1;
    realv next = region_of(FIELD_ARGS, s1);
    /* a crossing: the step's end lies more than TOL beyond a level on the far side from the
     * region the step integrates in (an end closer than that is on the kink: the step
     * straddles it by < TOL). Judged by the region, not by s0: a step that starts on a kink
     * it has just landed on must not integrate across it again with its old formula. */
    realv r0 = *region;
    maskv c_hi = (r0 < RV(0.5) && s1 > RV(hi + INTERFACE_TOL)) ||
                 (r0 > RV(0.5) && s1 < RV(hi - INTERFACE_TOL));
    maskv c_lo = (r0 > RV(-0.5) && s1 < RV(lo - INTERFACE_TOL)) ||
                 (r0 < RV(-0.5) && s1 > RV(lo + INTERFACE_TOL));
    maskv cross = active && (c_hi || c_lo);
    if (!ANY(cross)) {
        *region = next;
        return;
    }
    /* a step across both levels (a band thinner than the step) stops at the nearer first */
    maskv use_hi = c_hi && (!c_lo || fabs(s0 - hi) < fabs(s0 - lo));
    realv level = SEL(RV(lo), RV(hi), use_hi);
    maskv up = s1 > s0;
    realv above = SEL(RV(0), RV(1), level >= RV(hi));
    realv below = SEL(RV(0), RV(-1), level <= RV(lo));
    realv far = SEL(below, above, up);
    realv g1 = s1 - level;
    /* the start is on the region's side of the level, if only by rounding */
    realv g0 = SEL(s0 - level, RV(-0.01 * INTERFACE_TOL) * sign(g1), (s0 - level) * g1 >= RV(0));
    realv a = RV(0), b = RV(1), ga = g0, gb = g1, t = RV(1);
    realv tx, ty, tz, tvx, tvy, tvz;
    maskv open = cross;
    for (int it = 0; it < INTERFACE_ITERS; ++it) {
        t = SEL(t, clamp((a * gb - b * ga) / (gb - ga), fmin(a, b), fmax(a, b)), open);
        ode_incr(FIELD_ARGS, t * *h, *region, x, y, z, vx, vy, vz, &tx, &ty, &tz, &tvx, &tvy,
                 &tvz);
        realv st_ = field_interface(FIELD_ARGS, x + tx, y + ty, z + tz);
        realv gt = st_ - level;
        *s_at = SEL(*s_at, st_, open);
        *ix = SEL(*ix, tx, open); *iy = SEL(*iy, ty, open); *iz = SEL(*iz, tz, open);
        *ivx = SEL(*ivx, tvx, open); *ivy = SEL(*ivy, tvy, open); *ivz = SEL(*ivz, tvz, open);
        /* Anderson-Bjorck: (b, gb) is the newest point, a the other end of the bracket; a
         * retained end's value is scaled down so that it does not stick */
        maskv flip = (gt < RV(0)) != (gb < RV(0));
        realv m = RV(1) - gt / gb;
        m = SEL(RV(0.5), m, m > RV(0));
        maskv upd = open && !(fabs(gt) <= RV(0.25 * INTERFACE_TOL));
        realv na = SEL(a, b, flip), nga = SEL(m * ga, gb, flip);
        a = SEL(a, na, upd);
        ga = SEL(ga, nga, upd);
        b = SEL(b, t, upd);
        gb = SEL(gb, gt, upd);
        open = upd;
        if (!ANY(open)) break;
    }
    *h = SEL(*h, t * *h, cross);
    *region = SEL(next, far, cross);
}
#endif

#ifdef SKIP_EMPTY
/* Empty-space skipping (its backward pass is in adjoint.cl). occ holds, per cell of an
 * OCC_N^3 grid over the box, 0 where eta may vary and else the Chebyshev distance in cells
 * to the nearest such cell (clrefract/occupancy.py). In a cell at distance k >= 1, eta is constant up to k - 1 cells
 * beyond it, so the ray flies straight (x'' = 0) out of its cell and k - 1 cells on: the
 * arc length returned (0 in occupied cells). */
#define OCC_HX ((BOX_HI_X - BOX_LO_X) / (REAL)OCC_N)
#define OCC_HY ((BOX_HI_Y - BOX_LO_Y) / (REAL)OCC_N)
#define OCC_HZ ((BOX_HI_Z - BOX_LO_Z) / (REAL)OCC_N)
inline realv empty_jump(__global const REAL *restrict fp, __global const int *occ, realv x,
                        realv y, realv z, realv ux, realv uy, realv uz) {
    realv fx = clamp(floor((x - RV(BOX_LO_X)) / OCC_HX), RV(0), RV(OCC_N - 1));
    realv fy = clamp(floor((y - RV(BOX_LO_Y)) / OCC_HY), RV(0), RV(OCC_N - 1));
    realv fz = clamp(floor((z - RV(BOX_LO_Z)) / OCC_HZ), RV(0), RV(OCC_N - 1));
#if LANES == 1
    realv k = (REAL)occ[((int)fx * OCC_N + (int)fy) * OCC_N + (int)fz];
#else
    /* a gather: no vector indexing in OpenCL C */
    REAL ax[LANES], ay[LANES], az[LANES], ak[LANES];
    VSTORE(fx, 0, ax); VSTORE(fy, 0, ay); VSTORE(fz, 0, az);
    for (int l = 0; l < LANES; ++l)
        ak[l] = (REAL)occ[((int)ax[l] * OCC_N + (int)ay[l]) * OCC_N + (int)az[l]];
    realv k = VLOAD(0, ak);
#endif
    realv tx = (RV(BOX_LO_X) + (fx + SEL(RV(0), RV(1), ux > RV(0))) * OCC_HX - x) / ux;
    realv ty = (RV(BOX_LO_Y) + (fy + SEL(RV(0), RV(1), uy > RV(0))) * OCC_HY - y) / uy;
    realv tz = (RV(BOX_LO_Z) + (fz + SEL(RV(0), RV(1), uz > RV(0))) * OCC_HZ - z) / uz;
    tx = SEL(tx, RV(INFINITY), ux == RV(0));
    ty = SEL(ty, RV(INFINITY), uy == RV(0));
    tz = SEL(tz, RV(INFINITY), uz == RV(0));
    const REAL hmin = fmin(fmin(OCC_HX, OCC_HY), OCC_HZ);
    /* past the cell's face by 1e-3 cell, so that the next lookup is the next cell */
    realv t = fmax(fmin(fmin(tx, ty), tz), RV(0)) + (k - RV(1)) * hmin + RV((REAL)1e-3 * hmin);
    return SEL(RV(0), t, k >= RV(1));
}
/* Checkpoints by lattice index (the steps a ray without skipping would have taken to get
 * here): lanes reach them at different loop iterations, so each lane stores its own. The
 * state (x, v) is at index j1 = j0 + m; every multiple of C in (j0, j1] gets the straight
 * line back from it (exact for a flight, the state itself for one step, m = 1). */
inline void ckpt_lanes(__global REAL *ckpt, size_t col, size_t i, int every, int slots,
                       maskv mask, realv j0, realv m, REAL h, realv x, realv y, realv z,
                       realv vx, realv vy, realv vz) {
    REAL a[8][LANES];
    VSTORE(SEL(RV(0), RV(1), mask), 0, a[0]); VSTORE(j0, 0, a[1]); VSTORE(m, 0, a[2]);
    VSTORE(x, 0, a[3]); VSTORE(y, 0, a[4]); VSTORE(z, 0, a[5]);
    REAL b[3][LANES];
    VSTORE(vx, 0, b[0]); VSTORE(vy, 0, b[1]); VSTORE(vz, 0, b[2]);
    for (int l = 0; l < LANES; ++l) {
        if (a[0][l] == (REAL)0) continue;
        int lo = (int)a[1][l], hi = lo + (int)a[2][l];
        for (int j = (lo / every + 1) * every; j <= hi && j / every <= slots; j += every) {
            __global REAL *c = ckpt + (size_t)(j / every - 1) * 6 * col + i * LANES + l;
            REAL back = (REAL)(j - hi) * h;
            c[0] = a[3][l] + back * b[0][l]; c[col] = a[4][l] + back * b[1][l];
            c[2 * col] = a[5][l] + back * b[2][l];
            c[3 * col] = b[0][l]; c[4 * col] = b[1][l]; c[5 * col] = b[2][l];
        }
    }
}
#define SKIP_ARG , __global const int *occ
/* the forward pass also returns each ray's lattice index, where the backward pass starts */
#define TRACE_SKIP_ARG , __global const int *occ, __global int *lattice
#else
#define SKIP_ARG
#define TRACE_SKIP_ARG
#endif

/* Where a ray from origin o along u enters the box, and its v = eta u there (the origin,
 * where it starts inside or misses). u is normalised in place. Returns the hit mask.
 * Shared by the forward pass and the discrete adjoint, which replays from the same state. */
inline maskv ray_entry(FIELD_PARAMS, realv ox, realv oy, realv oz, realv *ux, realv *uy,
                       realv *uz, realv *x, realv *y, realv *z, realv *vx, realv *vy,
                       realv *vz) {
    realv un = rsqrt(*ux * *ux + *uy * *uy + *uz * *uz);
    *ux *= un; *uy *= un; *uz *= un;
    /* slab test against the box */
    realv t1 = (RV(BOX_LO_X) - ox) / *ux, t2 = (RV(BOX_HI_X) - ox) / *ux;
    realv tmin = fmin(t1, t2), tmax = fmax(t1, t2);
    t1 = (RV(BOX_LO_Y) - oy) / *uy; t2 = (RV(BOX_HI_Y) - oy) / *uy;
    tmin = fmax(tmin, fmin(t1, t2)); tmax = fmin(tmax, fmax(t1, t2));
    t1 = (RV(BOX_LO_Z) - oz) / *uz; t2 = (RV(BOX_HI_Z) - oz) / *uz;
    tmin = fmax(tmin, fmin(t1, t2)); tmax = fmin(tmax, fmax(t1, t2));
    tmin = fmax(tmin, RV(0));
    maskv hit = tmax >= tmin;
    realv t0 = SEL(RV(0), tmin, hit);
    *x = ox + t0 * *ux; *y = oy + t0 * *uy; *z = oz + t0 * *uz;
    realv g0x, g0y, g0z;
    realv eta0 = field_eval(FIELD_ARGS, *x, *y, *z, &g0x, &g0y, &g0z);
    *vx = eta0 * *ux; *vy = eta0 * *uy; *vz = eta0 * *uz;
    return hit;
}

/* Trace rays: straight to the box, integrate inside, straight out of the exit face.
 * Outputs the exit point, the exit v (direction times |v|), a status, the step count and
 * the last state inside the box (where the backward pass starts). With ckpt_every = C > 0,
 * the state after every C-th step goes to slot (k / C - 1) of ckpt (6 columns of the padded
 * ray count per slot, max_steps / C slots): the backward pass restarts from them.
 * A step that leaves the box is undone and replaced by a straight flight from its start:
 * exact because fields are 1 with zero gradient within MARGIN (> step) of the walls. */
__kernel void trace_rays(FIELD_PARAMS, const REAL h, const int max_steps,
                         __global const REAL *ox, __global const REAL *oy,
                         __global const REAL *oz, __global const REAL *dx,
                         __global const REAL *dy, __global const REAL *dz, __global REAL *px,
                         __global REAL *py, __global REAL *pz, __global REAL *qx,
                         __global REAL *qy, __global REAL *qz, __global int *status,
                         __global int *steps, __global REAL *lx, __global REAL *ly,
                         __global REAL *lz, const int ckpt_every,
                         __global REAL *ckpt TRACE_SKIP_ARG) {
    const size_t i = get_global_id(0);
    const size_t col = get_global_size(0) * LANES;
    realv sx = VLOAD(i, ox), sy = VLOAD(i, oy), sz = VLOAD(i, oz); /* kept for missed rays */
    realv ux = VLOAD(i, dx), uy = VLOAD(i, dy), uz = VLOAD(i, dz);
    realv x, y, z, vx, vy, vz;
    maskv hit = ray_entry(FIELD_ARGS, sx, sy, sz, &ux, &uy, &uz, &x, &y, &z, &vx, &vy, &vz);

    maskv active = hit;
    realv st = SEL(RV(ST_MISSED), RV(ST_EXITED), hit);
    realv n = RV(0);
    /* compensation terms of the Kahan sums of x and v */
    realv cx = RV(0), cy = RV(0), cz = RV(0), cvx = RV(0), cvy = RV(0), cvz = RV(0);
#ifdef FIELD_INTERFACE
    realv s_cur = field_interface(FIELD_ARGS, x, y, z); /* kink function at the ray's point */
    realv reg = region_of(FIELD_ARGS, s_cur);
#else
    const realv reg = RV(-2);
#endif
#ifdef ADAPTIVE_TOL
    realv hcur = RV(h); /* per-lane step of the adaptive pair, at most h */
#endif
#ifdef SKIP_EMPTY
    realv lat = RV(0); /* lattice index of the state: steps plus the steps flown over */
    const int slots = ckpt_every > 0 ? max(max_steps / ckpt_every, 1) : 0;
#endif
#ifdef SKIP_EMPTY
    /* the cap counts lattice steps, flown or taken, as without skipping: the same rays are
     * trapped; flights cost iterations too, hence the longer loop */
    for (int k = 0; k < 2 * max_steps + 2 && ANY(active); ++k) {
        maskv capped = active && lat >= RV(max_steps);
        if (ANY(capped)) {
            st = SEL(st, RV(ST_TRAPPED), capped);
            active = active && !capped;
            if (!ANY(active)) break;
        }
#else
    for (int k = 0; k < max_steps && ANY(active); ++k) {
#endif
        realv ix, iy, iz, ivx, ivy, ivz;
        realv hk = RV(h);
        maskv jumped = active && !active; /* all false, of the mask type */
#ifdef SKIP_EMPTY
        {
            realv sp = sqrt(vx * vx + vy * vy + vz * vz);
            realv L = empty_jump(fp, occ, x, y, z, vx / sp, vy / sp, vz / sp);
            /* whole steps only (dx/dsigma = v): the ray stays on the step lattice it would
             * have followed, so that steps resume where they would have been and images
             * match those without skipping to rounding, not to the integrator's error */
            realv nj = floor(L / (sp * h));
            realv sg = nj * h;
            jumped = active && sg > RV(0);
            if (ANY(jumped)) {
                realv jx = x + sg * vx, jy = y + sg * vy, jz = z + sg * vz;
                /* a flight out of the box ends the ray: it leaves straight from here */
                maskv leaves = jumped && outside_box(fp, jx, jy, jz);
                maskv mv = jumped && !leaves;
                x = SEL(x, jx, mv); y = SEL(y, jy, mv); z = SEL(z, jz, mv);
                cx = SEL(cx, RV(0), mv); cy = SEL(cy, RV(0), mv); cz = SEL(cz, RV(0), mv);
                active = active && !leaves;
                jumped = mv;
                if (ckpt_every > 0 && ANY(mv))
                    ckpt_lanes(ckpt, col, i, ckpt_every, slots, mv, lat, nj, h, x, y, z, vx, vy,
                               vz);
                lat = SEL(lat, lat + nj, mv);
#ifdef FIELD_INTERFACE
                s_cur = SEL(s_cur, field_interface(FIELD_ARGS, x, y, z), mv);
                reg = SEL(reg, region_of(FIELD_ARGS, s_cur), mv);
#endif
            }
        }
#endif
#ifdef ADAPTIVE_TOL
        /* error per step below ADAPTIVE_TOL (mm, and |v| units); a rejected step is retried
         * shorter from the same state. A step of 1e-4 h is accepted whatever its error, so
         * that a ray cannot stall; max_steps counts attempts, so none can hang. */
        hk = hcur;
        realv err;
        ode_dopri(FIELD_ARGS, hk, reg, x, y, z, vx, vy, vz, &ix, &iy, &iz, &ivx, &ivy, &ivz,
                  &err);
        maskv acc = !(err > RV(ADAPTIVE_TOL)) || hk <= RV((REAL)1e-4 * h);
        realv fac = RV(0.9) * pow(RV(ADAPTIVE_TOL) / fmax(err, RV(1e-30)), RV(0.2));
        fac = clamp(fac, RV(0.2), RV(5));
        hcur = SEL(hcur, clamp(hk * fac, RV((REAL)1e-4 * h), RV(h)), active && isfinite(fac));
        maskv moving = active && acc && !jumped;
#else
        ode_incr(FIELD_ARGS, hk, reg, x, y, z, vx, vy, vz, &ix, &iy, &iz, &ivx, &ivy, &ivz);
        maskv moving = active && !jumped;
#endif
#ifdef FIELD_INTERFACE
        realv s_new = s_cur, reg_new = reg;
        interface_step(FIELD_ARGS, moving, &hk, &reg_new, &s_new, x, y, z, vx, vy, vz, &ix, &iy,
                       &iz, &ivx, &ivy, &ivz);
#endif
        KAHAN_STATE;
        maskv bad = !isfinite(nx + ny + nz + nvx + nvy + nvz);
        maskv go = moving && !outside_box(fp, nx, ny, nz) && !bad;
        x = SEL(x, nx, go); y = SEL(y, ny, go); z = SEL(z, nz, go);
        vx = SEL(vx, nvx, go); vy = SEL(vy, nvy, go); vz = SEL(vz, nvz, go);
        cx = SEL(cx, ncx, go); cy = SEL(cy, ncy, go); cz = SEL(cz, ncz, go);
        cvx = SEL(cvx, ncvx, go); cvy = SEL(cvy, ncvy, go); cvz = SEL(cvz, ncvz, go);
        st = SEL(st, RV(ST_NONFINITE), moving && bad);
#ifdef ADAPTIVE_TOL
        n += SEL(RV(0), RV(1), active && !jumped); /* attempts: each costs 7 evaluations */
#else
        n += SEL(RV(0), RV(1), go);
#endif
        /* rejected adaptive steps and straight flights stay active without stepping */
        active = go || (active && !moving);
#ifdef FIELD_INTERFACE
        s_cur = SEL(s_cur, s_new, go);
        reg = SEL(reg, reg_new, go);
#endif
#ifdef SKIP_EMPTY
        if (ckpt_every > 0 && ANY(go))
            ckpt_lanes(ckpt, col, i, ckpt_every, slots, go, lat, RV(1), h, x, y, z, vx, vy, vz);
        lat += SEL(RV(0), RV(1), go);
#else
        if (ckpt_every > 0 && (k + 1) % ckpt_every == 0) {
            __global REAL *c = ckpt + (size_t)((k + 1) / ckpt_every - 1) * 6 * col;
            VSTORE(x, i, c); VSTORE(y, i, c + col); VSTORE(z, i, c + 2 * col);
            VSTORE(vx, i, c + 3 * col); VSTORE(vy, i, c + 4 * col); VSTORE(vz, i, c + 5 * col);
        }
#endif
    }
    st = SEL(st, RV(ST_TRAPPED), active);
#ifdef SKIP_EMPTY
    VSTORE_INT(TO_INTV(lat), i, lattice);
#endif

    realv speed = sqrt(vx * vx + vy * vy + vz * vz);
    realv iv = RV(1) / speed;
    realv ex = vx * iv, ey = vy * iv, ez = vz * iv;
    VSTORE(x, i, lx); VSTORE(y, i, ly); VSTORE(z, i, lz);
    maskv out = st == RV(ST_EXITED);
    realv te = SEL(RV(0), box_exit_t(fp, x, y, z, ex, ey, ez), out);
    x += te * ex; y += te * ey; z += te * ez;
    maskv missed = st == RV(ST_MISSED);
    x = SEL(x, sx, missed); y = SEL(y, sy, missed); z = SEL(z, sz, missed);
    vx = SEL(vx, ux, missed); vy = SEL(vy, uy, missed); vz = SEL(vz, uz, missed);

    VSTORE(x, i, px); VSTORE(y, i, py); VSTORE(z, i, pz);
    VSTORE(vx, i, qx); VSTORE(vy, i, qy); VSTORE(vz, i, qz);
    VSTORE_INT(TO_INTV(st), i, status);
    VSTORE_INT(TO_INTV(n), i, steps);
}

/* Fixed number of steps from given (x, v), no box: for trajectories and oracles. */
__kernel void propagate_rays(FIELD_PARAMS, const REAL h, const int n_steps, __global REAL *px,
                             __global REAL *py, __global REAL *pz, __global REAL *qx,
                             __global REAL *qy, __global REAL *qz) {
    const size_t i = get_global_id(0);
    realv x = VLOAD(i, px), y = VLOAD(i, py), z = VLOAD(i, pz);
    realv vx = VLOAD(i, qx), vy = VLOAD(i, qy), vz = VLOAD(i, qz);
    for (int k = 0; k < n_steps; ++k)
        ode_step(FIELD_ARGS, RV(h), &x, &y, &z, &vx, &vy, &vz);
    VSTORE(x, i, px); VSTORE(y, i, py); VSTORE(z, i, pz);
    VSTORE(vx, i, qx); VSTORE(vy, i, qy); VSTORE(vz, i, qz);
}

__kernel void eval_field(FIELD_PARAMS, __global const REAL *x, __global const REAL *y,
                         __global const REAL *z, __global REAL *eta, __global REAL *gx,
                         __global REAL *gy, __global REAL *gz) {
    const size_t i = get_global_id(0);
    realv ax, ay, az;
    realv e = field_eval(FIELD_ARGS, VLOAD(i, x), VLOAD(i, y), VLOAD(i, z), &ax, &ay, &az);
    VSTORE(e, i, eta); VSTORE(ax, i, gx); VSTORE(ay, i, gy); VSTORE(az, i, gz);
}
