/* Discrete adjoint (exact gradient of the discretised forward pass), after adjoint.cl.
 *
 * The forward pass keeps the ray state every K steps (checkpoints, O(max_steps / K) per
 * ray). Backwards, segment by segment from the last, the K steps of a segment are replayed
 * from its checkpoint (the first segment from the box entry, recomputed with ray_entry) into
 * a per-ray scratch buffer (K steps of 9 reals: the start and two stage points), and then each step is reversed exactly: the
 * transpose of the Runge-Kutta-Nystrom step's Jacobian (stages in reverse order, each a
 * vector-Jacobian product with D = eta grad eta: H_D (symmetric) from field_adjoint, and the
 * parameter splat w mu . dD/dtheta with w = h). The result is the gradient of the forward
 * renderer itself, to rounding, with no drift and no discretisation error.
 *
 * What it differentiates: fixed-step RKN4 (the only integrator the fits use) without
 * interface steps (fields with adjoints have none), then the straight flight out of the box
 * from the last in-box state: the loss sees that state's v (the exit direction), so
 * vbar(N) = mu = dJ/dv and xbar(N) = 0. The step count N is piecewise constant in the
 * parameters (as every branch is): the gradient is that of the branch taken. The entry
 * state depends on no parameter (eta = 1 on the box walls). The forward pass's Kahan
 * compensation restarts at 0 at each checkpoint here, so the replay can differ from the
 * forward states by rounding; snap returns the largest such difference (mm).
 */

#ifdef FIELD_INTERFACE
#error "the discrete adjoint does not differentiate interface steps"
#endif
#if !defined(INTEGRATOR_RKN4)
#error "the discrete adjoint reverses INTEGRATOR_RKN4 steps"
#endif

#define SCRATCH_COLS 9 /* per replayed step: x, the second and the third stage's points */
#define DISCRETE_INLINE inline __attribute__((always_inline))

/* Reverse one RKN4 step that started at X = P[0..2] with stage points Xb = P[3..5],
 * Xc = P[6..8]: (xb, vb) holds the cotangent of the step's end on entry and of its start on
 * return; the parameters get w (h or 0) times theirs. The step is
 *     A = h D(X), B = h D(Xb), Xb = X + h/2 v + h/8 A, C = h D(Xc), Xc = X + h v + h/2 B,
 *     X' = X + h v + h (A + 2B) / 6,  v' = v + (A + 4B + C) / 6,
 * reversed stage by stage from C to A; each stage's vector-Jacobian product is h H_D(point)
 * times its cotangent (H_D symmetric), and its parameter part w cotangent . dD/dtheta. */
DISCRETE_INLINE void rkn4_step_vjp(FIELD_PARAMS, __global REAL *grad FIELD_ACC_PARAM, const REAL hh,
                          realv w, const realv *P, realv *xb, realv *vb) {
    const realv h = RV(hh), h2 = RV(0.5) * h, h8 = RV(0.125) * h;
    const REAL s = (REAL)1 / (REAL)6;
    realv ab[3], bb[3], cb[3], nx[3], nv[3];
    for (int a = 0; a < 3; ++a) {
        ab[a] = s * (h * xb[a] + vb[a]);
        bb[a] = s * (RV(2) * h * xb[a] + RV(4) * vb[a]);
        cb[a] = s * vb[a];
        nx[a] = xb[a];
        nv[a] = vb[a] + h * xb[a];
    }
    realv d[3], g[3];
    adjoint_f(FIELD_ARGS, grad FIELD_ACC_ARG, w, P[6], P[7], P[8], cb[0], cb[1], cb[2], &d[0],
              &d[1], &d[2], &g[0], &g[1], &g[2]);
    for (int a = 0; a < 3; ++a) {
        g[a] *= h;
        nx[a] += g[a];
        nv[a] += h * g[a];
        bb[a] += h2 * g[a];
    }
    adjoint_f(FIELD_ARGS, grad FIELD_ACC_ARG, w, P[3], P[4], P[5], bb[0], bb[1], bb[2], &d[0],
              &d[1], &d[2], &g[0], &g[1], &g[2]);
    for (int a = 0; a < 3; ++a) {
        g[a] *= h;
        nx[a] += g[a];
        nv[a] += h2 * g[a];
        ab[a] += h8 * g[a];
    }
    adjoint_f(FIELD_ARGS, grad FIELD_ACC_ARG, w, P[0], P[1], P[2], ab[0], ab[1], ab[2], &d[0],
              &d[1], &d[2], &g[0], &g[1], &g[2]);
    for (int a = 0; a < 3; ++a) {
        xb[a] = nx[a] + h * g[a];
        vb[a] = nv[a];
    }
}

__kernel void adjoint_discrete(FIELD_PARAMS, const REAL h, __global const REAL *ox,
                               __global const REAL *oy, __global const REAL *oz,
                               __global const REAL *dxs, __global const REAL *dys,
                               __global const REAL *dzs, __global const int *steps,
                               __global const REAL *mux, __global const REAL *muy,
                               __global const REAL *muz, __global REAL *grad,
                               __global REAL *partial, __global REAL *bx, __global REAL *by,
                               __global REAL *bz, const int max_steps, const int ckpt_every,
                               __global const REAL *ckpt, __global REAL *scratch,
                               __global REAL *snap, const REAL growth_max,
                               __global REAL *growth, __global REAL *oax,
                               __global REAL *oay, __global REAL *oaz) {
    const size_t i = get_global_id(0);
    const size_t col = get_global_size(0) * LANES;
    const int K = ckpt_every;
    realv ux = VLOAD(i, dxs), uy = VLOAD(i, dys), uz = VLOAD(i, dzs);
    realv ex, ey, ez, evx, evy, evz;
    ray_entry(FIELD_ARGS, VLOAD(i, ox), VLOAD(i, oy), VLOAD(i, oz), &ux, &uy, &uz, &ex, &ey,
              &ez, &evx, &evy, &evz);
    /* cotangents of x (0 at the end: the loss sees v only) and of v */
    realv pb[3] = {RV(0), RV(0), RV(0)};
    realv qb[3] = {VLOAD(i, mux), VLOAD(i, muy), VLOAD(i, muz)};
    intv ni = VLOAD(i, steps);
    realv n = TO_REALV(ni);
    int nmax = 0; /* the work-item's longest ray: segments past it are skipped */
    {
        int na[LANES];
        VSTORE_INT(ni, 0, na);
        for (int l = 0; l < LANES; ++l)
            nmax = max(nmax, na[l]);
    }
    FIELD_ACC_DECL
    realv worst = RV(0);
    const realv inv_m0 = RV(1) / fmax(qb[0] * qb[0] + qb[1] * qb[1] + qb[2] * qb[2], RV(1e-30));
    const realv g2 = RV(growth_max * growth_max);
    realv grown = RV(1), alive = RV(1);
    for (int seg = (nmax - 1) / K; seg >= 0 && nmax > 0; --seg) {
        const int s0 = seg * K, s1 = min(s0 + K, nmax);
        realv x, y, z, vx, vy, vz;
        if (seg == 0) {
            x = ex; y = ey; z = ez; vx = evx; vy = evy; vz = evz;
        } else {
            __global const REAL *c = ckpt + (size_t)(seg - 1) * 6 * col;
            x = VLOAD(i, c); y = VLOAD(i, c + col); z = VLOAD(i, c + 2 * col);
            vx = VLOAD(i, c + 3 * col); vy = VLOAD(i, c + 4 * col); vz = VLOAD(i, c + 5 * col);
        }
        /* replay the segment as trace_rays steps, keeping each step's start and stage
         * points (9 columns per step) */
        realv cx = RV(0), cy = RV(0), cz = RV(0), cvx = RV(0), cvy = RV(0), cvz = RV(0);
        for (int s = s0; s < s1; ++s) {
            realv Q[9];
            Q[0] = x; Q[1] = y; Q[2] = z;
            maskv live = RV(s) < n;
            realv ix, iy, iz, ivx, ivy, ivz;
            rkn4_incr(FIELD_ARGS, RV(h), RV(-2), x, y, z, vx, vy, vz, &ix, &iy, &iz, &ivx,
                      &ivy, &ivz, Q + 3);
            __global REAL *c = scratch + (size_t)(s - s0) * SCRATCH_COLS * col;
            for (int a = 0; a < SCRATCH_COLS; ++a)
                VSTORE(Q[a], i, c + a * col);
            KAHAN_STATE;
            x = SEL(x, nx, live); y = SEL(y, ny, live); z = SEL(z, nz, live);
            vx = SEL(vx, nvx, live); vy = SEL(vy, nvy, live); vz = SEL(vz, nvz, live);
            cx = SEL(cx, ncx, live); cy = SEL(cy, ncy, live); cz = SEL(cz, ncz, live);
            cvx = SEL(cvx, ncvx, live); cvy = SEL(cvy, ncvy, live); cvz = SEL(cvz, ncvz, live);
        }
        /* the replay against the forward pass's next checkpoint, where the ray reached it */
        if (s1 == s0 + K && s1 / K - 1 < max_steps / K) {
            __global const REAL *c = ckpt + (size_t)(s1 / K - 1) * 6 * col;
            realv dx = x - VLOAD(i, c), dy = y - VLOAD(i, c + col), dz = z - VLOAD(i, c + 2 * col);
            worst = SEL(worst, fmax(worst, sqrt(dx * dx + dy * dy + dz * dz)), RV(s1) <= n);
        }
        /* reverse the segment's steps */
        for (int s = s1 - 1; s >= s0; --s) {
            maskv act = RV(s) < n && alive > RV(0);
            if (!ANY(act))
                continue;
            __global const REAL *c = scratch + (size_t)(s - s0) * SCRATCH_COLS * col;
            realv Q[9];
            for (int a = 0; a < SCRATCH_COLS; ++a)
                Q[a] = VLOAD(i, c + a * col);
            realv w = SEL(RV(0), RV(h), act);
            realv np[3] = {pb[0], pb[1], pb[2]}, nq[3] = {qb[0], qb[1], qb[2]};
            rkn4_step_vjp(FIELD_ARGS, grad FIELD_ACC_ARG, h, w, Q, np, nq);
            for (int a = 0; a < 3; ++a) {
                pb[a] = SEL(pb[a], np[a], act);
                qb[a] = SEL(qb[a], nq[a], act);
            }
            realv m2 = (qb[0] * qb[0] + qb[1] * qb[1] + qb[2] * qb[2]) * inv_m0;
            grown = SEL(grown, fmax(grown, m2), act);
            if (growth_max > (REAL)0)
                alive = SEL(alive, RV(0), act && m2 > g2);
        }
    }
    VSTORE(ex, i, bx); VSTORE(ey, i, by); VSTORE(ez, i, bz); VSTORE(worst, i, snap);
    VSTORE(sqrt(grown), i, growth);
    /* dJ/dx at the entry (0 where the cap cut the ray: not its origin's) */
    VSTORE(SEL(RV(0), pb[0], alive > RV(0)), i, oax);
    VSTORE(SEL(RV(0), pb[1], alive > RV(0)), i, oay);
    VSTORE(SEL(RV(0), pb[2], alive > RV(0)), i, oaz);
    FIELD_ACC_FLUSH(grad, partial, i);
}
