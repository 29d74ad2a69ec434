/* Multi-resolution hash grid + MLP index field (clrefract/fields/hashgrid.py holds the layout
 * and the float64 NumPy reference).
 *
 * fd: tables (HG_LEVELS x T x HG_FEATURES, C order, T = 2^HG_LOG2T) from offset 0, then the
 *     MLP from HG_MLP_OFFSET, layer by layer W (out x in, row-major) then b (out).
 * fp: eta_max, N_0 .. N_{L-1}, dense_0 .. dense_{L-1} (1 where the level is directly indexed),
 *     then the geometry (common.h).
 *
 * Encoding: u = (x - lo) / size clamped to [0,1]^3, p = u N_l, cell c = min(floor p, N_l - 1),
 * t = p - c, corner weights 1 - s(t), s(t) with s(t) = 3t^2 - 2t^3 (HG_SMOOTH) or t. Vertex
 * (i, j, k): dense index (i (N+1) + j) (N+1) + k, or hash (i ^ j*2654435761 ^ k*805459861)
 * & (T - 1) in uint32. Cells, weights and indices are computed on the LANES-wide vectors;
 * only the table gather is scalar, lane by lane, into a private array that is loaded back as
 * vectors for the interpolation (L*F features and their x, y, z derivatives per lane).
 * MLP: vectorised across the lanes (the weights are the same for every ray): forward mode
 * carries each unit's value and its 3 spatial derivatives, dh = W df,
 * d softplus(h) = sigmoid(h) dh. The last hidden layer is fused into the output unit, so only
 * one hidden layer is ever stored. o -> g = 1 + (eta_max - 1) sigmoid(o), or with HG_RAMP
 * 1 + (eta_max - 1) S((o + 1) / 2), S the C2 quintic (flat beyond o = -1 and 1);
 * eta = 1 + W (g - 1), W the box window. With LANES == 1 everything is scalar (GPU layout).
 */

#ifndef HG_SMOOTH
#define HG_SMOOTH 1
#endif
#ifndef HG_RAMP
#define HG_RAMP 0
#endif

/* PoCL builds with -Dinline= and may leave large helpers as calls; a call that takes private
 * arrays by pointer then gets per-work-group context copies of them on the stack (a crash
 * with large work-groups). Force inlining. */
#define HG_INLINE inline __attribute__((always_inline))

#define HG_T (1 << HG_LOG2T)
#define HG_NF (HG_LEVELS * HG_FEATURES)
#define HG_PRIME_Y 2654435761u
#define HG_PRIME_Z 805459861u

/* offsets of the MLP layers in fd */
#define HG_W0 (HG_MLP_OFFSET)
#define HG_B0 (HG_W0 + HG_HIDDEN * HG_NF)
#if HG_LAYERS == 2
#define HG_W1 (HG_B0 + HG_HIDDEN)
#define HG_B1 (HG_W1 + HG_HIDDEN * HG_HIDDEN)
#define HG_WO (HG_B1 + HG_HIDDEN)
#else
#define HG_WO (HG_B0 + HG_HIDDEN)
#endif
#define HG_BO (HG_WO + HG_HIDDEN)

#if LANES == 1
typedef uint hg_uintv;
#define HG_AS_UINTV(v) as_uint(v)
#else
typedef CAT(uint, LANES) hg_uintv;
#define HG_AS_UINTV(v) CAT(as_uint, LANES)(v)
#endif

/* One axis of one level for the LANES points: cell index in [0, n - 1] (as uint), weight s
 * of the high corner, ds/dx and d2s/dx2 (`inside` is 0 where the coordinate was clamped;
 * the forward pass drops the second derivative, the compiler removes it). */
HG_INLINE hg_uintv hg_axis(realv u, realv inside, REAL n, REAL scale, realv *s, realv *ds,
                           realv *dds) {
    realv p = u * n;
    intv c = clamp(TO_INTV(floor(p)), 0, (int)n - 1);
    realv t = p - TO_REALV(c);
#if HG_SMOOTH
    *s = t * t * (RV(3) - RV(2) * t);
    *ds = inside * (scale * RV(6)) * t * (RV(1) - t);
    *dds = inside * (scale * scale) * (RV(6) - RV(12) * t);
#else
    *s = t;
    *ds = inside * scale;
    *dds = RV(0);
#endif
    return HG_AS_UINTV(c);
}

/* Table indices of the 8 corners of cell (i, j, k) of level l for the LANES points, corner
 * c = 4a + 2b + d (a b d = low/high along x y z) at idx[c * LANES + lane]. */
HG_INLINE void hg_indices(__global const REAL *restrict fp, const int l, const REAL n,
                          hg_uintv i, hg_uintv j, hg_uintv k, uint *idx) {
    if (fp[1 + HG_LEVELS + l] != (REAL)0) { /* dense */
        const uint s1 = (uint)n + 1u, s2 = s1 * s1;
        hg_uintv base = (i * s1 + j) * s1 + k;
        VSTORE(base, 0, idx);
        VSTORE(base + 1u, 1, idx);
        VSTORE(base + s1, 2, idx);
        VSTORE(base + (s1 + 1u), 3, idx);
        VSTORE(base + s2, 4, idx);
        VSTORE(base + (s2 + 1u), 5, idx);
        VSTORE(base + (s2 + s1), 6, idx);
        VSTORE(base + (s2 + s1 + 1u), 7, idx);
    } else {
        const uint m = (uint)(HG_T - 1);
        hg_uintv hx1 = i + 1u;
        hg_uintv hy0 = j * HG_PRIME_Y, hy1 = hy0 + HG_PRIME_Y;
        hg_uintv hz0 = k * HG_PRIME_Z, hz1 = hz0 + HG_PRIME_Z;
        VSTORE((i ^ hy0 ^ hz0) & m, 0, idx);
        VSTORE((i ^ hy0 ^ hz1) & m, 1, idx);
        VSTORE((i ^ hy1 ^ hz0) & m, 2, idx);
        VSTORE((i ^ hy1 ^ hz1) & m, 3, idx);
        VSTORE((hx1 ^ hy0 ^ hz0) & m, 4, idx);
        VSTORE((hx1 ^ hy0 ^ hz1) & m, 5, idx);
        VSTORE((hx1 ^ hy1 ^ hz0) & m, 6, idx);
        VSTORE((hx1 ^ hy1 ^ hz1) & m, 7, idx);
    }
}

/* The table entries at idx of level l, feature f of corner c of lane q at
 * vals[(c * HG_FEATURES + f) * LANES + q]: all 8 corners of every lane in one loop
 * (independent loads, so cache misses on large tables overlap). */
HG_INLINE void hg_gather(__global const REAL *restrict fd, const int l, const uint *idx,
                         REAL *vals) {
    __global const REAL *tab = fd + (size_t)l * HG_T * HG_FEATURES;
    for (int c = 0; c < 8; ++c)
        for (int q = 0; q < LANES; ++q) {
            __global const REAL *e = tab + (size_t)idx[c * LANES + q] * HG_FEATURES;
            for (int f = 0; f < HG_FEATURES; ++f)
                vals[(c * HG_FEATURES + f) * LANES + q] = e[f];
        }
}

/* The reverse of hg_gather: atomic adds of vals (same layout) to the entries at idx of
 * level l of grad; zeros (padding or inactive lanes) are skipped. */
HG_INLINE void hg_scatter(__global REAL *grad, const int l, const uint *idx, const REAL *vals) {
    __global REAL *tab = grad + (size_t)l * HG_T * HG_FEATURES;
    for (int c = 0; c < 8; ++c)
        for (int q = 0; q < LANES; ++q) {
            __global REAL *e = tab + (size_t)idx[c * LANES + q] * HG_FEATURES;
            for (int f = 0; f < HG_FEATURES; ++f) {
                REAL v = vals[(c * HG_FEATURES + f) * LANES + q];
                if (v != 0) atomic_add_real(e + f, v);
            }
        }
}

/* Box coordinates of (x, y, z) in [0, 1] (cx cy cz), and 1 where they were not clamped
 * (ix iy iz): the derivative of a clamped coordinate is 0. */
#define HG_NORMALISE                                                                         \
    const REAL sx_ = BOX_HI_X - BOX_LO_X, sy_ = BOX_HI_Y - BOX_LO_Y,                         \
               sz_ = BOX_HI_Z - BOX_LO_Z;                                                    \
    realv ux = (x - RV(BOX_LO_X)) / sx_, uy = (y - RV(BOX_LO_Y)) / sy_,                      \
          uz = (z - RV(BOX_LO_Z)) / sz_;                                                     \
    realv cx = clamp(ux, RV(0), RV(1)), cy = clamp(uy, RV(0), RV(1)),                        \
          cz = clamp(uz, RV(0), RV(1));                                                      \
    realv ix = SEL(RV(0), RV(1), ux == cx), iy = SEL(RV(0), RV(1), uy == cy),                \
          iz = SEL(RV(0), RV(1), uz == cz);

/* The cell of level l holding the (clamped, normalised) points: table indices idx of its 8
 * corners and, per axis, the high corner's weight s, ds/dx and d2s/dx2 (hg_axis). */
HG_INLINE void hg_cell(FIELD_PARAMS, const int l, realv cx, realv cy, realv cz, realv ix,
                       realv iy, realv iz, uint *idx, realv *sx, realv *sy, realv *sz,
                       realv *dsx, realv *dsy, realv *dsz, realv *ddx, realv *ddy, realv *ddz) {
    const REAL sx_ = BOX_HI_X - BOX_LO_X, sy_ = BOX_HI_Y - BOX_LO_Y, sz_ = BOX_HI_Z - BOX_LO_Z;
    const REAL n = fp[1 + l];
    hg_uintv i = hg_axis(cx, ix, n, n / sx_, sx, dsx, ddx);
    hg_uintv j = hg_axis(cy, iy, n, n / sy_, sy, dsy, ddy);
    hg_uintv k = hg_axis(cz, iz, n, n / sz_, sz, dsz, ddz);
    hg_indices(fp, l, n, i, j, k, idx);
}

/* Corner weights of level l: table indices idx, weight cw and its gradient (cgx cgy cgz),
 * for the 8 corners. hashgrid_adjoint.cl's hg_corners2 adds Hess(weight) mu; the two are
 * written alike, with selects and no per-axis arrays (NVIDIA's driver computed the
 * features of 8 or more levels wrong from the per-axis two-element arrays this replaces,
 * and the adjoint's encoding right). */
HG_INLINE void hg_corners(FIELD_PARAMS, const int l, realv cx, realv cy, realv cz, realv ix,
                          realv iy, realv iz, uint *idx, realv *cw, realv *cgx, realv *cgy,
                          realv *cgz) {
    realv sx, sy, sz, dsx, dsy, dsz, ddx, ddy, ddz; /* dd*: unused, dropped by the compiler */
    hg_cell(FIELD_ARGS, l, cx, cy, cz, ix, iy, iz, idx, &sx, &sy, &sz, &dsx, &dsy, &dsz, &ddx,
            &ddy, &ddz);
    for (int c = 0; c < 8; ++c) {
        const REAL a = (c >> 2) ? 1 : -1, b = ((c >> 1) & 1) ? 1 : -1, d = (c & 1) ? 1 : -1;
        realv Ax = (c >> 2) ? sx : RV(1) - sx, Ay = ((c >> 1) & 1) ? sy : RV(1) - sy,
              Az = (c & 1) ? sz : RV(1) - sz;
        realv ayz = Ay * Az;
        cw[c] = Ax * ayz;
        cgx[c] = (a * dsx) * ayz;
        cgy[c] = Ax * (b * dsy) * Az;
        cgz[c] = Ax * Ay * (d * dsz);
    }
}

/* The L*F features of the LANES points and their x, y, z derivatives. Index and weight
 * arithmetic runs on the vectors; the table gather is scalar, lane by lane (hg_gather). */
HG_INLINE void hg_encode(FIELD_PARAMS, realv x, realv y, realv z, realv *feat, realv *fx,
                         realv *fy, realv *fz) {
    HG_NORMALISE
    for (int l = 0; l < HG_LEVELS; ++l) {
        uint idx[8 * LANES];
        REAL vals[8 * HG_FEATURES * LANES];
        realv cw[8], cgx[8], cgy[8], cgz[8];
        hg_corners(FIELD_ARGS, l, cx, cy, cz, ix, iy, iz, idx, cw, cgx, cgy, cgz);
        hg_gather(fd, l, idx, vals);
        for (int q = 0; q < HG_FEATURES; ++q) {
            realv v = RV(0), gx = RV(0), gy = RV(0), gz = RV(0);
            for (int c = 0; c < 8; ++c) {
                realv t = VLOAD(c * HG_FEATURES + q, vals);
                v += cw[c] * t;
                gx += cgx[c] * t;
                gy += cgy[c] * t;
                gz += cgz[c] * t;
            }
            const int o = l * HG_FEATURES + q;
            feat[o] = v;
            fx[o] = gx;
            fy[o] = gy;
            fz[o] = gz;
        }
    }
}

/* Sum of the lanes of a vector (the shared weights of a backward pass get one number per
 * work-item: hashgrid_adjoint.cl, straight_neural.cl). */
#if LANES == 1
#define HG_HSUM(v) (v)
#elif LANES == 2
#define HG_HSUM(v) ((v).s0 + (v).s1)
#elif LANES == 4
#define HG_HSUM(v) hg_hsum4(v)
#elif LANES == 8
#define HG_HSUM(v) hg_hsum4((v).lo + (v).hi)
#elif LANES == 16
#define HG_HSUM(v) hg_hsum8((v).lo + (v).hi)
#endif
#if LANES >= 4
HG_INLINE REAL hg_hsum4(CAT(REAL, 4) v) {
    CAT(REAL, 2) a = v.lo + v.hi;
    return a.x + a.y;
}
#endif
#if LANES == 16
HG_INLINE REAL hg_hsum8(CAT(REAL, 8) v) { return hg_hsum4(v.lo + v.hi); }
#endif

/* softplus(h) and sigmoid(h) = softplus'(h), sharing one exponential */
HG_INLINE realv hg_softplus(realv h, realv *sig) {
    realv e = exp(-fabs(h));
    realv r = RV(1) / (RV(1) + e);
    *sig = SEL(e * r, r, h >= RV(0));
    return fmax(h, RV(0)) + log1p(e);
}

HG_INLINE realv hg_sigmoid(realv h) {
    realv e = exp(-fabs(h));
    realv r = RV(1) / (RV(1) + e);
    return SEL(e * r, r, h >= RV(0));
}

/* The output map G(o) = g - 1 and its derivatives G', G'' in o. */
HG_INLINE realv hg_output(realv o, const REAL k, realv *G1, realv *G2) {
#if HG_RAMP
    realv t = (o + RV(1)) * RV(0.5);
    *G1 = RV(k * (REAL)0.5) * smoother_d(t);
    *G2 = RV(k * (REAL)0.25) * smoother_dd(t);
    return RV(k) * smoother(t);
#else
    realv s = hg_sigmoid(o);
    realv G = RV(k) * s;
    *G1 = G * (RV(1) - s);
    *G2 = *G1 * (RV(1) - RV(2) * s);
    return G;
#endif
}

/* Four units j .. j+3 of a dense layer, h = W a + b, and the derivatives dh = W da (forward
 * mode): each input vector is loaded once for 16 multiply-adds. */
HG_INLINE void hg_units4(__global const REAL *W, __global const REAL *B, const int n_in,
                         const int j, const realv *a, const realv *ax, const realv *ay,
                         const realv *az, realv *h, realv *hx, realv *hy, realv *hz) {
    __global const REAL *w0 = W + j * n_in, *w1 = w0 + n_in, *w2 = w1 + n_in,
                        *w3 = w2 + n_in;
    realv v0 = RV(B[j]), v1 = RV(B[j + 1]), v2 = RV(B[j + 2]), v3 = RV(B[j + 3]);
    realv x0 = RV(0), x1 = RV(0), x2 = RV(0), x3 = RV(0);
    realv y0 = RV(0), y1 = RV(0), y2 = RV(0), y3 = RV(0);
    realv z0 = RV(0), z1 = RV(0), z2 = RV(0), z3 = RV(0);
    for (int i = 0; i < n_in; ++i) {
        const realv A = a[i], AX = ax[i], AY = ay[i], AZ = az[i];
        const REAL c0 = w0[i], c1 = w1[i], c2 = w2[i], c3 = w3[i];
        v0 += c0 * A; x0 += c0 * AX; y0 += c0 * AY; z0 += c0 * AZ;
        v1 += c1 * A; x1 += c1 * AX; y1 += c1 * AY; z1 += c1 * AZ;
        v2 += c2 * A; x2 += c2 * AX; y2 += c2 * AY; z2 += c2 * AZ;
        v3 += c3 * A; x3 += c3 * AX; y3 += c3 * AY; z3 += c3 * AZ;
    }
    h[0] = v0; h[1] = v1; h[2] = v2; h[3] = v3;
    hx[0] = x0; hx[1] = x1; hx[2] = x2; hx[3] = x3;
    hy[0] = y0; hy[1] = y1; hy[2] = y2; hy[3] = y3;
    hz[0] = z0; hz[1] = z1; hz[2] = z2; hz[3] = z3;
}

/* One unit j of a dense layer (the remainder when the width is not a multiple of 4). */
HG_INLINE void hg_unit1(__global const REAL *W, __global const REAL *B, const int n_in,
                        const int j, const realv *a, const realv *ax, const realv *ay,
                        const realv *az, realv *h, realv *hx, realv *hy, realv *hz) {
    __global const REAL *w = W + j * n_in;
    realv v = RV(B[j]), x = RV(0), y = RV(0), z = RV(0);
    for (int i = 0; i < n_in; ++i) {
        const REAL c = w[i];
        v += c * a[i]; x += c * ax[i]; y += c * ay[i]; z += c * az[i];
    }
    *h = v; *hx = x; *hy = y; *hz = z;
}

/* Units j0 <= j < j0 + NB (NB = 4 or 1) of a hidden layer from inputs a: softplus, then BODY
 * with jj, act = softplus(h) and its derivatives dax day daz: either stored (HG_STORE_H1)
 * or fused into the output unit, o += wo softplus(h) (HG_FUSE_OUT). */
#define HG_LAYER_BLOCK(UNITS, NB, W, B, NIN, j0, a, ax, ay, az, BODY)                        \
    {                                                                                        \
        realv h_[NB], hx_[NB], hy_[NB], hz_[NB];                                             \
        UNITS(W, B, NIN, j0, a, ax, ay, az, h_, hx_, hy_, hz_);                              \
        for (int q_ = 0; q_ < NB; ++q_) {                                                    \
            const int jj = (j0) + q_;                                                        \
            realv sg;                                                                        \
            realv act = hg_softplus(h_[q_], &sg);                                            \
            realv dax = sg * hx_[q_], day = sg * hy_[q_], daz = sg * hz_[q_];                \
            BODY                                                                             \
        }                                                                                    \
    }

#define HG_FUSE_OUT                                                                          \
    {                                                                                        \
        const REAL wo = fd[HG_WO + jj];                                                      \
        o += wo * act;                                                                       \
        ox += wo * dax;                                                                      \
        oy += wo * day;                                                                      \
        oz += wo * daz;                                                                      \
    }
#define HG_STORE_H1                                                                          \
    {                                                                                        \
        h1[jj] = act;                                                                        \
        h1x[jj] = dax;                                                                       \
        h1y[jj] = day;                                                                       \
        h1z[jj] = daz;                                                                       \
    }

#define HG_LAYER(W, B, NIN, a, ax, ay, az, BODY)                                             \
    {                                                                                        \
        int j_ = 0;                                                                          \
        for (; j_ + 4 <= HG_HIDDEN; j_ += 4)                                                 \
            HG_LAYER_BLOCK(hg_units4, 4, W, B, NIN, j_, a, ax, ay, az, BODY)                 \
        for (; j_ < HG_HIDDEN; ++j_)                                                         \
            HG_LAYER_BLOCK(hg_unit1, 1, W, B, NIN, j_, a, ax, ay, az, BODY)                  \
    }

/* MLP output o and its gradient from the features, forward mode. */
HG_INLINE realv hg_mlp(__global const REAL *restrict fd, const realv *feat, const realv *fx,
                       const realv *fy, const realv *fz, realv *gox, realv *goy, realv *goz) {
    realv o = RV(fd[HG_BO]), ox = RV(0), oy = RV(0), oz = RV(0);
#if HG_LAYERS == 2
    realv h1[HG_HIDDEN], h1x[HG_HIDDEN], h1y[HG_HIDDEN], h1z[HG_HIDDEN];
    HG_LAYER(fd + HG_W0, fd + HG_B0, HG_NF, feat, fx, fy, fz, HG_STORE_H1)
    HG_LAYER(fd + HG_W1, fd + HG_B1, HG_HIDDEN, h1, h1x, h1y, h1z, HG_FUSE_OUT)
#else
    HG_LAYER(fd + HG_W0, fd + HG_B0, HG_NF, feat, fx, fy, fz, HG_FUSE_OUT)
#endif
    *gox = ox;
    *goy = oy;
    *goz = oz;
    return o;
}

inline realv field_eval(FIELD_PARAMS, realv x, realv y, realv z, realv *gx, realv *gy,
                        realv *gz) {
    realv feat[HG_NF], fx[HG_NF], fy[HG_NF], fz[HG_NF];
    hg_encode(FIELD_ARGS, x, y, z, feat, fx, fy, fz);
    realv ox, oy, oz;
    realv o = hg_mlp(fd, feat, fx, fy, fz, &ox, &oy, &oz);
    const REAL k = fp[0] - (REAL)1;
    realv dg, dg2;
    realv g1 = hg_output(o, k, &dg, &dg2);
    realv wx, wy, wz;
    realv w = box_window(fp, x, y, z, &wx, &wy, &wz);
    *gx = wx * g1 + w * dg * ox;
    *gy = wy * g1 + w * dg * oy;
    *gz = wz * g1 + w * dg * oz;
    return RV(1) + w * g1;
}

#if HG_RAMP && !defined(NO_INTERFACE_STEPS)
/* Interface steps (rendering only, as a level set's): the ramp's higher derivatives jump
 * where o = -1 and 1, and steps land there. */
#define FIELD_INTERFACE 1
#define INTERFACE_LO (-(REAL)1)
#define INTERFACE_HI ((REAL)1)
inline realv field_interface(FIELD_PARAMS, realv x, realv y, realv z) {
    realv feat[HG_NF], fx[HG_NF], fy[HG_NF], fz[HG_NF];
    hg_encode(FIELD_ARGS, x, y, z, feat, fx, fy, fz);
    realv ox, oy, oz;
    return hg_mlp(fd, feat, fx, fy, fz, &ox, &oy, &oz);
}
/* One region's formula continued past its edges: region -1 air (G = 0), 0 the ramp (the
 * quintic, unclamped), +1 glass (G = eta_max - 1), -2 by position. */
inline realv field_eval_region(FIELD_PARAMS, realv x, realv y, realv z, realv region, realv *gx,
                               realv *gy, realv *gz) {
    realv feat[HG_NF], fx[HG_NF], fy[HG_NF], fz[HG_NF];
    hg_encode(FIELD_ARGS, x, y, z, feat, fx, fy, fz);
    realv ox, oy, oz;
    realv o = hg_mlp(fd, feat, fx, fy, fz, &ox, &oy, &oz);
    const REAL k = fp[0] - (REAL)1;
    realv pos = SEL(SEL(RV(0), RV(1), o > RV(1)), RV(-1), o < RV(-1));
    realv reg = SEL(region, pos, region < RV(-1.5));
    realv t = (o + RV(1)) * RV(0.5);
    realv band = SEL(RV(0), RV(1), reg == RV(0));
    realv p = t * t * t * (t * (t * RV(6) - RV(15)) + RV(10));
    realv dp = RV(30) * t * t * (t - RV(1)) * (t - RV(1));
    realv g1 = RV(k) * SEL(band * p, RV(1), reg > RV(0.5));
    realv dg = RV(k * (REAL)0.5) * band * dp;
    realv wx, wy, wz;
    realv w = box_window(fp, x, y, z, &wx, &wy, &wz);
    *gx = wx * g1 + w * dg * ox;
    *gy = wy * g1 + w * dg * oy;
    *gz = wz * g1 + w * dg * oz;
    return RV(1) + w * g1;
}
#endif
