/* Backward-pass pieces of the hash grid + MLP field (field_hashgrid.cl): eta, grad eta,
 * Hess(eta) mu, and the splat of w * d/dtheta [eta (mu . grad eta)] into the parameters
 * (the contract of voxel_adjoint.cl; adjoint.cl calls field_adjoint).
 *
 * eta = 1 + W G(o), G = (eta_max - 1) sigmoid(o) (or the ramp, HG_RAMP), o = MLP(features(x)).
 * Forward mode carries, for every feature and hidden unit, its value a, gradient grad a and
 * Hess(a) mu (7 numbers): d softplus(h) = s dh, Hess softplus(h) mu = s' (mu . dh) dh +
 * s Hess(h) mu (s = sigmoid(h)); smoothstep corner weights have second derivatives.
 * The parameters reach the splat only through o and o_mu = mu . grad o:
 *     w d/dtheta [eta (mu . grad eta)] = ob do/dtheta + omb do_mu/dtheta,
 *     ob  = w [(mu . grad eta) W G' + eta ((mu . grad W) G' + W G'' o_mu)],
 *     omb = w eta W G',
 * reversed through the (value, mu-tangent) pairs of the MLP and of the encoding.
 *
 * Where the sums go: the MLP weights are shared by every ray, so no global atomics on
 * them: each work-item sums their gradient over its lanes and its whole ray in its own slot
 * of `partial`, partial[gid * HG_NSHARED + p], which no other work-item touches (the host
 * adds the slots up). Table entries are touched by few rays each: atomic adds into grad,
 * which has the layout of fd (on this 2-core CPU they are about a third of the cost).
 */

/* MLP parameters: the shared block, offsets relative to its start in fd */
#define HG_NSHARED (HG_BO + 1 - HG_MLP_OFFSET)
#define HG_A(off) ((off) - HG_MLP_OFFSET)

/* The work-item's slot of `partial` (a parameter of adjoint_rays) is its accumulator: a
 * private array of that size (25-50 KB for 64-wide layers) would be copied for every
 * work-item of the work-group onto one PoCL thread's stack, and overflow it. */
#define FIELD_ACC_DECL                                                                       \
    __global REAL *restrict hg_acc = partial + get_global_id(0) * HG_NSHARED;               \
    for (int p_ = 0; p_ < HG_NSHARED; ++p_)                                                  \
        hg_acc[p_] = 0;
#define FIELD_ACC_PARAM , __global REAL *restrict hg_acc
#define FIELD_ACC_ARG , hg_acc
#define FIELD_ACC_FLUSH(grad, partial, gid)

/* Corner weights of level l at the (clamped, normalised) points: table indices idx, weight
 * cw, its gradient (cgx cgy cgz) and Hess(weight) mu (chx chy chz), for the 8 corners. */
HG_INLINE void hg_corners2(FIELD_PARAMS, const int l, realv cx, realv cy, realv cz, realv ix,
                           realv iy, realv iz, realv mx, realv my, realv mz, uint *idx,
                           realv *cw, realv *cgx, realv *cgy, realv *cgz, realv *chx,
                           realv *chy, realv *chz) {
    realv sx, sy, sz, dsx, dsy, dsz, ddx, ddy, ddz;
    hg_cell(FIELD_ARGS, l, cx, cy, cz, ix, iy, iz, idx, &sx, &sy, &sz, &dsx, &dsy, &dsz, &ddx,
            &ddy, &ddz);
    for (int c = 0; c < 8; ++c) {
        const REAL a = (c >> 2) ? 1 : -1, b = ((c >> 1) & 1) ? 1 : -1, d = (c & 1) ? 1 : -1;
        /* per axis: factor (1 - s or s), first and second derivative */
        realv Ax = (c >> 2) ? sx : RV(1) - sx, Ay = ((c >> 1) & 1) ? sy : RV(1) - sy,
              Az = (c & 1) ? sz : RV(1) - sz;
        realv Dx = a * dsx, Dy = b * dsy, Dz = d * dsz;
        realv Sx = a * ddx, Sy = b * ddy, Sz = d * ddz;
        realv ayz = Ay * Az;
        cw[c] = Ax * ayz;
        cgx[c] = Dx * ayz;
        cgy[c] = Ax * Dy * Az;
        cgz[c] = Ax * Ay * Dz;
        realv hxx = Sx * ayz, hyy = Ax * Sy * Az, hzz = Ax * Ay * Sz;
        realv hxy = Dx * Dy * Az, hxz = Dx * Ay * Dz, hyz = Ax * Dy * Dz;
        chx[c] = hxx * mx + hxy * my + hxz * mz;
        chy[c] = hxy * mx + hyy * my + hyz * mz;
        chz[c] = hxz * mx + hyz * my + hzz * mz;
    }
}

/* Features with their gradient (f*x f*y f*z) and Hess(feature) mu (h*x h*y h*z). */
HG_INLINE void hg_encode2(FIELD_PARAMS, realv x, realv y, realv z, realv mx, realv my,
                          realv mz, realv *f, realv *fgx, realv *fgy, realv *fgz, realv *fhx,
                          realv *fhy, realv *fhz) {
    HG_NORMALISE
    for (int l = 0; l < HG_LEVELS; ++l) {
        uint idx[8 * LANES];
        REAL vals[8 * HG_FEATURES * LANES];
        realv cw[8], cgx[8], cgy[8], cgz[8], chx[8], chy[8], chz[8];
        hg_corners2(FIELD_ARGS, l, cx, cy, cz, ix, iy, iz, mx, my, mz, idx, cw, cgx, cgy, cgz,
                    chx, chy, chz);
        hg_gather(fd, l, idx, vals);
        for (int q = 0; q < HG_FEATURES; ++q) {
            realv v = RV(0), gx = RV(0), gy = RV(0), gz = RV(0), hx = RV(0), hy = RV(0),
                  hz = RV(0);
            for (int c = 0; c < 8; ++c) {
                realv t = VLOAD(c * HG_FEATURES + q, vals);
                v += cw[c] * t;
                gx += cgx[c] * t; gy += cgy[c] * t; gz += cgz[c] * t;
                hx += chx[c] * t; hy += chy[c] * t; hz += chz[c] * t;
            }
            const int o = l * HG_FEATURES + q;
            f[o] = v;
            fgx[o] = gx; fgy[o] = gy; fgz[o] = gz;
            fhx[o] = hx; fhy[o] = hy; fhz[o] = hz;
        }
    }
}

/* Reverse of the encoding: feature adjoints fb (of the value) and fmb (of the mu-tangent)
 * go to the table entries, tb = fb w + fmb (mu . grad w), by atomic adds. */
HG_INLINE void hg_encode2_reverse(FIELD_PARAMS, __global REAL *grad, realv x, realv y,
                                  realv z, realv mx, realv my, realv mz, const realv *fb,
                                  const realv *fmb) {
    HG_NORMALISE
    for (int l = 0; l < HG_LEVELS; ++l) {
        uint idx[8 * LANES];
        REAL tv[8 * HG_FEATURES * LANES];
        realv cw[8], cgx[8], cgy[8], cgz[8], chx[8], chy[8], chz[8];
        hg_corners2(FIELD_ARGS, l, cx, cy, cz, ix, iy, iz, mx, my, mz, idx, cw, cgx, cgy, cgz,
                    chx, chy, chz);
        for (int c = 0; c < 8; ++c) {
            realv wm = mx * cgx[c] + my * cgy[c] + mz * cgz[c];
            for (int q = 0; q < HG_FEATURES; ++q) {
                const int o = l * HG_FEATURES + q;
                VSTORE(fb[o] * cw[c] + fmb[o] * wm, c * HG_FEATURES + q, tv);
            }
        }
        hg_scatter(grad, l, idx, tv); /* inactive lanes, the window's margin: 0, skipped */
    }
}

/* Second-order forward mode through a dense layer, h = W a + b: value, grad h = W grad a
 * and Hess(h) mu = W Hess(a) mu. The layer's input is 7 arrays (a, its gradient gx gy gz
 * and Hess(a) mu as hx hy hz); hg_units2_4 computes units j .. j+3 (each input loaded once
 * for 28 multiply-adds), hg_units2_1 one unit (widths not a multiple of 4). */
#define HG_IN7 const realv *a, const realv *gx, const realv *gy, const realv *gz, \
               const realv *hx, const realv *hy, const realv *hz
#define HG_OUT7 realv *v, realv *vx, realv *vy, realv *vz, realv *wx, realv *wy, realv *wz
HG_INLINE void hg_units2_4(__global const REAL *W, __global const REAL *B, const int n_in,
                           const int j, HG_IN7, HG_OUT7) {
    __global const REAL *w0 = W + j * n_in, *w1 = w0 + n_in, *w2 = w1 + n_in,
                        *w3 = w2 + n_in;
    realv v0 = RV(B[j]), v1 = RV(B[j + 1]), v2 = RV(B[j + 2]), v3 = RV(B[j + 3]);
    realv x0 = RV(0), x1 = RV(0), x2 = RV(0), x3 = RV(0);
    realv y0 = RV(0), y1 = RV(0), y2 = RV(0), y3 = RV(0);
    realv z0 = RV(0), z1 = RV(0), z2 = RV(0), z3 = RV(0);
    realv p0 = RV(0), p1 = RV(0), p2 = RV(0), p3 = RV(0);
    realv q0 = RV(0), q1 = RV(0), q2 = RV(0), q3 = RV(0);
    realv r0 = RV(0), r1 = RV(0), r2 = RV(0), r3 = RV(0);
    for (int i = 0; i < n_in; ++i) {
        const realv A = a[i], AX = gx[i], AY = gy[i], AZ = gz[i];
        const realv HX = hx[i], HY = hy[i], HZ = hz[i];
        const REAL c0 = w0[i], c1 = w1[i], c2 = w2[i], c3 = w3[i];
        v0 += c0 * A; x0 += c0 * AX; y0 += c0 * AY; z0 += c0 * AZ;
        p0 += c0 * HX; q0 += c0 * HY; r0 += c0 * HZ;
        v1 += c1 * A; x1 += c1 * AX; y1 += c1 * AY; z1 += c1 * AZ;
        p1 += c1 * HX; q1 += c1 * HY; r1 += c1 * HZ;
        v2 += c2 * A; x2 += c2 * AX; y2 += c2 * AY; z2 += c2 * AZ;
        p2 += c2 * HX; q2 += c2 * HY; r2 += c2 * HZ;
        v3 += c3 * A; x3 += c3 * AX; y3 += c3 * AY; z3 += c3 * AZ;
        p3 += c3 * HX; q3 += c3 * HY; r3 += c3 * HZ;
    }
    v[0] = v0; v[1] = v1; v[2] = v2; v[3] = v3;
    vx[0] = x0; vx[1] = x1; vx[2] = x2; vx[3] = x3;
    vy[0] = y0; vy[1] = y1; vy[2] = y2; vy[3] = y3;
    vz[0] = z0; vz[1] = z1; vz[2] = z2; vz[3] = z3;
    wx[0] = p0; wx[1] = p1; wx[2] = p2; wx[3] = p3;
    wy[0] = q0; wy[1] = q1; wy[2] = q2; wy[3] = q3;
    wz[0] = r0; wz[1] = r1; wz[2] = r2; wz[3] = r3;
}

HG_INLINE void hg_units2_1(__global const REAL *W, __global const REAL *B, const int n_in,
                           const int j, HG_IN7, HG_OUT7) {
    __global const REAL *w = W + j * n_in;
    realv v0 = RV(B[j]), x0 = RV(0), y0 = RV(0), z0 = RV(0), p0 = RV(0), q0 = RV(0),
          r0 = RV(0);
    for (int i = 0; i < n_in; ++i) {
        const REAL c = w[i];
        v0 += c * a[i]; x0 += c * gx[i]; y0 += c * gy[i]; z0 += c * gz[i];
        p0 += c * hx[i]; q0 += c * hy[i]; r0 += c * hz[i];
    }
    *v = v0; *vx = x0; *vy = y0; *vz = z0; *wx = p0; *wy = q0; *wz = r0;
}

/* Units j0 .. j0 + NB - 1 of a hidden layer, then softplus: writes the activations' 7
 * numbers to the o* arrays and keeps for the reverse pass s = sigmoid(h) in S, q = s'
 * (mu . grad h) in Q and the activation's mu-tangent s (mu . grad h) in M. */
#define HG_2ND_BLOCK(UNITS, NB, W, B, n_in, j0, a, ax, ay, az, ahx, ahy, ahz, oa, oax, oay,  \
                     oaz, ohx, ohy, ohz, S, Q, M)                                            \
    {                                                                                        \
        realv v_[NB], gx_[NB], gy_[NB], gz_[NB], hx_[NB], hy_[NB], hz_[NB];                  \
        UNITS(W, B, n_in, j0, a, ax, ay, az, ahx, ahy, ahz, v_, gx_, gy_, gz_, hx_, hy_,     \
              hz_);                                                                          \
        for (int u_ = 0; u_ < NB; ++u_) {                                                    \
            const int jj = (j0) + u_;                                                        \
            realv s_;                                                                        \
            realv act = hg_softplus(v_[u_], &s_);                                            \
            realv hm_ = mx * gx_[u_] + my * gy_[u_] + mz * gz_[u_];                          \
            realv q_ = s_ * (RV(1) - s_) * hm_;                                              \
            (oa)[jj] = act;                                                                  \
            (oax)[jj] = s_ * gx_[u_]; (oay)[jj] = s_ * gy_[u_]; (oaz)[jj] = s_ * gz_[u_];    \
            (ohx)[jj] = q_ * gx_[u_] + s_ * hx_[u_];                                         \
            (ohy)[jj] = q_ * gy_[u_] + s_ * hy_[u_];                                         \
            (ohz)[jj] = q_ * gz_[u_] + s_ * hz_[u_];                                         \
            (S)[jj] = s_;                                                                    \
            (Q)[jj] = q_;                                                                    \
            (M)[jj] = s_ * hm_;                                                              \
        }                                                                                    \
    }

#define HG_2ND_LAYER(W, B, n_in, a, ax, ay, az, ahx, ahy, ahz, oa, oax, oay, oaz, ohx, ohy,  \
                     ohz, S, Q, M)                                                           \
    {                                                                                        \
        int j4_ = 0;                                                                         \
        for (; j4_ + 4 <= HG_HIDDEN; j4_ += 4)                                               \
            HG_2ND_BLOCK(hg_units2_4, 4, W, B, n_in, j4_, a, ax, ay, az, ahx, ahy, ahz, oa,  \
                         oax, oay, oaz, ohx, ohy, ohz, S, Q, M)                              \
        for (; j4_ < HG_HIDDEN; ++j4_)                                                       \
            HG_2ND_BLOCK(hg_units2_1, 1, W, B, n_in, j4_, a, ax, ay, az, ahx, ahy, ahz, oa,  \
                         oax, oay, oaz, ohx, ohy, ohz, S, Q, M)                              \
    }

/* Reverse of a dense layer h = W a + b with the (value, mu-tangent) adjoints hb, hmb of its
 * outputs h: the shared-gradient sums dW += hb a^T + hmb am^T and db += hb go to acc (at
 * the layer's offsets in the shared block); the inputs' adjoints ab = W^T hb, amb = W^T hmb. */
HG_INLINE void hg_layer_reverse(__global const REAL *restrict W, const int n_in,
                                __global REAL *restrict accw, __global REAL *restrict accb,
                                const realv *hb, const realv *hmb, const realv *a,
                                const realv *am, realv *ab, realv *amb) {
    for (int i = 0; i < n_in; ++i)
        ab[i] = amb[i] = RV(0);
    int j = 0;
    for (; j + 4 <= HG_HIDDEN; j += 4) { /* 4 rows: each input loaded once */
        const realv b0 = hb[j], b1 = hb[j + 1], b2 = hb[j + 2], b3 = hb[j + 3];
        const realv m0 = hmb[j], m1 = hmb[j + 1], m2 = hmb[j + 2], m3 = hmb[j + 3];
        __global const REAL *w0 = W + j * n_in, *w1 = w0 + n_in, *w2 = w1 + n_in,
                            *w3 = w2 + n_in;
        __global REAL *g0 = accw + j * n_in, *g1 = g0 + n_in, *g2 = g1 + n_in,
                      *g3 = g2 + n_in;
        accb[j] += HG_HSUM(b0);
        accb[j + 1] += HG_HSUM(b1);
        accb[j + 2] += HG_HSUM(b2);
        accb[j + 3] += HG_HSUM(b3);
        for (int i = 0; i < n_in; ++i) {
            const realv A = a[i], AM = am[i];
            const REAL c0 = w0[i], c1 = w1[i], c2 = w2[i], c3 = w3[i];
            g0[i] += HG_HSUM(b0 * A + m0 * AM);
            g1[i] += HG_HSUM(b1 * A + m1 * AM);
            g2[i] += HG_HSUM(b2 * A + m2 * AM);
            g3[i] += HG_HSUM(b3 * A + m3 * AM);
            ab[i] += c0 * b0 + c1 * b1 + c2 * b2 + c3 * b3;
            amb[i] += c0 * m0 + c1 * m1 + c2 * m2 + c3 * m3;
        }
    }
    for (; j < HG_HIDDEN; ++j) {
        const realv b = hb[j], bm = hmb[j];
        __global const REAL *w = W + j * n_in;
        __global REAL *g = accw + j * n_in;
        accb[j] += HG_HSUM(b);
        for (int i = 0; i < n_in; ++i) {
            const REAL c = w[i];
            g[i] += HG_HSUM(b * a[i] + bm * am[i]);
            ab[i] += c * b;
            amb[i] += c * bm;
        }
    }
}

/* The adjoints of a hidden layer's pre-activations from those of its activations:
 * act = softplus(h), act_mu = s h_mu, so hb = ab s + amb q, hmb = amb s. In place. */
HG_INLINE void hg_softplus_reverse(const realv *S, const realv *Q, realv *ab, realv *amb) {
    for (int j = 0; j < HG_HIDDEN; ++j) {
        realv b = ab[j], bm = amb[j];
        ab[j] = b * S[j] + bm * Q[j];
        amb[j] = bm * S[j];
    }
}

/* On CPUs (LANES > 1) PoCL runs a work-group as a loop over its work-items and gives every
 * work-item its own copy of the kernel's private arrays, all on one thread's stack: with
 * the ~100 KB of scratch below and work-groups of hundreds of work-items that overflows.
 * A function that is never inlined keeps its arrays in its own frame, one per call. */
#if LANES > 1
#define HG_ADJ_FN __attribute__((noinline))
#else
#define HG_ADJ_FN inline
#endif

/* The splat at one point. With `given` the output's adjoints ob and omb are the caller's
 * (ob_in, omb_in: a least-squares fit's residuals, hashgrid_distil.cl) instead of the
 * adjoint's formula; w and the window then play no part. */
HG_ADJ_FN realv hg_point_adjoint(FIELD_PARAMS, realv x, realv y, realv z, realv mx, realv my,
                                 realv mz, realv w, const int given, realv ob_in, realv omb_in,
                                 realv *gx, realv *gy, realv *gz, realv *hx, realv *hy,
                                 realv *hz, __global REAL *grad FIELD_ACC_PARAM) {
    /* features: value, gradient, Hess mu; after the first layer the same arrays hold the
     * features' mu-tangents (fgx) and, in the reverse pass, their adjoints (fhx, fhy) */
    realv f[HG_NF], fgx[HG_NF], fgy[HG_NF], fgz[HG_NF], fhx[HG_NF], fhy[HG_NF], fhz[HG_NF];
    hg_encode2(FIELD_ARGS, x, y, z, mx, my, mz, f, fgx, fgy, fgz, fhx, fhy, fhz);
    /* hidden layers: a (value) ax ay az (gradient) bx by bz (Hess mu), and per unit for the
     * reverse pass S (sigmoid), Q (s' h_mu) and M (mu-tangent of the activation) */
    realv a1[HG_HIDDEN], ax1[HG_HIDDEN], ay1[HG_HIDDEN], az1[HG_HIDDEN];
    realv bx1[HG_HIDDEN], by1[HG_HIDDEN], bz1[HG_HIDDEN];
    realv S1[HG_HIDDEN], Q1[HG_HIDDEN], M1[HG_HIDDEN];
    HG_2ND_LAYER(fd + HG_W0, fd + HG_B0, HG_NF, f, fgx, fgy, fgz, fhx, fhy, fhz, a1, ax1, ay1,
                 az1, bx1, by1, bz1, S1, Q1, M1)
#if HG_LAYERS == 2
    realv a2[HG_HIDDEN], ax2[HG_HIDDEN], ay2[HG_HIDDEN], az2[HG_HIDDEN];
    realv bx2[HG_HIDDEN], by2[HG_HIDDEN], bz2[HG_HIDDEN];
    realv S2[HG_HIDDEN], Q2[HG_HIDDEN], M2[HG_HIDDEN];
    HG_2ND_LAYER(fd + HG_W1, fd + HG_B1, HG_HIDDEN, a1, ax1, ay1, az1, bx1, by1, bz1, a2, ax2,
                 ay2, az2, bx2, by2, bz2, S2, Q2, M2)
#define HG_LAST(v) v##2
#else
#define HG_LAST(v) v##1
#endif
    /* output unit */
    realv o = RV(fd[HG_BO]), ox = RV(0), oy = RV(0), oz = RV(0);
    realv ohx = RV(0), ohy = RV(0), ohz = RV(0);
    for (int j = 0; j < HG_HIDDEN; ++j) {
        const REAL c = fd[HG_WO + j];
        o += c * HG_LAST(a)[j];
        ox += c * HG_LAST(ax)[j];
        oy += c * HG_LAST(ay)[j];
        oz += c * HG_LAST(az)[j];
        ohx += c * HG_LAST(bx)[j];
        ohy += c * HG_LAST(by)[j];
        ohz += c * HG_LAST(bz)[j];
    }
    /* output map and window: eta = 1 + W G(o) */
    const REAL k = fp[0] - (REAL)1;
    realv G1, G2;
    realv G = hg_output(o, k, &G1, &G2);
    realv gW[3], HW[6];
    realv Wn = window_hess_v(fp, x, y, z, gW, HW);
    realv gWx = gW[0], gWy = gW[1], gWz = gW[2];
    realv Hxx = HW[0], Hyy = HW[1], Hzz = HW[2], Hxy = HW[3], Hxz = HW[4], Hyz = HW[5];
    realv eta = RV(1) + Wn * G;
    realv Gx = G1 * ox, Gy = G1 * oy, Gz = G1 * oz; /* grad G */
    realv ex = G * gWx + Wn * Gx, ey = G * gWy + Wn * Gy, ez = G * gWz + Wn * Gz;
    realv om = mx * ox + my * oy + mz * oz;      /* o_mu */
    realv mW = mx * gWx + my * gWy + mz * gWz;   /* mu . grad W */
    realv mG = G1 * om;                          /* mu . grad G */
    /* Hess(eta) mu = (mu.gW) grad G + G HW mu + (mu.grad G) gW + W Hess(G) mu,
     * Hess(G) mu = G'' o_mu grad o + G' Hess(o) mu */
    *hx = mW * Gx + G * (Hxx * mx + Hxy * my + Hxz * mz) + mG * gWx +
          Wn * (G2 * om * ox + G1 * ohx);
    *hy = mW * Gy + G * (Hxy * mx + Hyy * my + Hyz * mz) + mG * gWy +
          Wn * (G2 * om * oy + G1 * ohy);
    *hz = mW * Gz + G * (Hxz * mx + Hyz * my + Hzz * mz) + mG * gWz +
          Wn * (G2 * om * oz + G1 * ohz);
    *gx = ex; *gy = ey; *gz = ez;

    /* reverse pass into the parameters */
    realv me = mx * ex + my * ey + mz * ez;
    realv ob = ob_in, omb = omb_in;
    if (!given) {
        ob = w * (me * Wn * G1 + eta * (mW * G1 + Wn * G2 * om));
        omb = w * eta * Wn * G1;
    }
    if (!ANY(ob != RV(0) || omb != RV(0)))
        return eta;
    /* output unit: d wo_j = ob a_j + omb a_mu,j; then the last hidden layer's adjoints
     * (into its x-gradient arrays, free now) */
    hg_acc[HG_A(HG_BO)] += HG_HSUM(ob);
    realv *hb = HG_LAST(ax), *hmb = HG_LAST(ay);
    for (int j = 0; j < HG_HIDDEN; ++j) {
        const REAL c = fd[HG_WO + j];
        hg_acc[HG_A(HG_WO) + j] += HG_HSUM(ob * HG_LAST(a)[j] + omb * HG_LAST(M)[j]);
        hb[j] = c * ob;
        hmb[j] = c * omb;
    }
    hg_softplus_reverse(HG_LAST(S), HG_LAST(Q), hb, hmb);
#if HG_LAYERS == 2
    hg_layer_reverse(fd + HG_W1, HG_HIDDEN, hg_acc + HG_A(HG_W1), hg_acc + HG_A(HG_B1), hb,
                     hmb, a1, M1, ax1, ay1);
    hg_softplus_reverse(S1, Q1, ax1, ay1);
    hb = ax1;
    hmb = ay1;
#endif
    /* first layer: inputs are the features, their mu-tangents into fgx */
    for (int i = 0; i < HG_NF; ++i)
        fgx[i] = mx * fgx[i] + my * fgy[i] + mz * fgz[i];
    hg_layer_reverse(fd + HG_W0, HG_NF, hg_acc + HG_A(HG_W0), hg_acc + HG_A(HG_B0), hb, hmb, f,
                     fgx, fhx, fhy);
    hg_encode2_reverse(FIELD_ARGS, grad, x, y, z, mx, my, mz, fhx, fhy);
    return eta;
#undef HG_LAST
}

inline realv field_adjoint(FIELD_PARAMS, realv x, realv y, realv z, realv mx, realv my,
                           realv mz, realv w, realv *gx, realv *gy, realv *gz, realv *hx,
                           realv *hy, realv *hz, __global REAL *grad FIELD_ACC_PARAM) {
    return hg_point_adjoint(FIELD_ARGS, x, y, z, mx, my, mz, w, 0, RV(0), RV(0), gx, gy, gz,
                            hx, hy, hz, grad FIELD_ACC_ARG);
}
