/* Voxel-grid index field (clrefract/fields/voxel.py holds the float64 NumPy reference).
 *
 * Node-centred samples: VOX_NX x VOX_NY x VOX_NZ nodes, node (0,0,0) on the box's low corner
 * and node (n-1) on its high corner along each axis (spacing = size / (n - 1)). The value of
 * node (i, j, k) is fd[(i * VOX_NY + j) * VOX_NZ + k] (NumPy C order of values[i, j, k]).
 * fp holds only the geometry: the box and the node counts (common.h).
 *
 * g(x) interpolates the nodes of the cell holding x with weights w0 = 1 - s(t), w1 = s(t) per
 * axis, t in [0, 1] the position inside the cell: s(t) = t (trilinear, C0) or, with
 * VOX_SMOOTH, s(t) = 3t^2 - 2t^3 (C1, so grad eta is continuous and the diagonal of
 * Hess(eta) is not zero inside a cell). With VOX_BSPLINE it blends the 4 nodes c-1 .. c+2
 * per axis around the cell c (64 per point) with uniform cubic B-spline weights (C2; node
 * indices clamped to the grid; the values are control points, not interpolated values).
 * Points outside the grid are clamped onto it.
 * eta = 1 + W (g - 1), W the box window, so rays leave the box in straight lines; the gradient
 * is the exact derivative of that expression.
 *
 * VOX_LEVELSET (with VOX_BSPLINE): the spline g is a signed distance phi (mm, negative
 * inside) and fd[VOX_NODES] the index n inside; g - 1 becomes F(phi) = (n - 1) S(1/2 -
 * phi / LS_WIDTH), S the C2 quintic smoothstep: a surface as sharp as LS_WIDTH (fp[0])
 * whatever the grid spacing, the shape of the analytic solids (fields/levelset.py).
 *
 * Trilinear and smoothstep gather scalar: field_eval spills its LANES points to private
 * arrays, interpolates each with voxel_interp1 and loads the results back; with LANES == 1 it
 * is plain scalar code. The B-spline's arithmetic (64 taps) is done on the lane vectors and
 * only its node reads are per lane. The window is applied on the vectors.
 */

#ifndef VOX_SMOOTH
#define VOX_SMOOTH 0
#endif
#ifndef VOX_BSPLINE
#define VOX_BSPLINE 0
#endif
#ifndef VOX_LEVELSET
#define VOX_LEVELSET 0
#endif
#define VOX_NODES (VOX_NX * VOX_NY * VOX_NZ)

#if VOX_LEVELSET
#define LS_WIDTH (fp[0])
/* F(phi) = (n - 1) S(1/2 - phi / w), with S, dS/dphi and d2F/dphi2. */
inline realv levelset_map(__global const REAL *restrict fp, realv phi, REAL n, realv *S,
                          realv *dS, realv *F2) {
    const REAL w = LS_WIDTH;
    realv s = RV(0.5) - phi / RV(w);
    *S = smoother(s);
    *dS = -smoother_d(s) / RV(w);
    *F2 = RV((n - (REAL)1) / (w * w)) * smoother_dd(s);
    return RV(n - (REAL)1) * *S;
}
#endif

/* PoCL may crash on helpers that take private arrays by pointer unless they are inlined */
#define VOX_INLINE inline __attribute__((always_inline))

/* The grid's low corner, node spacing (and inverse) and node counts (common.h), read from fp
 * once for all the lanes of an evaluation: read per lane, they slowed trilinear tracing. */
typedef struct {
    REAL lo[3], h[3], ih[3];
    int n[3];
} vox_geo;

VOX_INLINE vox_geo vox_geometry(__global const REAL *restrict fp) {
    vox_geo g = {{BOX_LO_X, BOX_LO_Y, BOX_LO_Z},
                 {VOX_HX, VOX_HY, VOX_HZ},
                 {VOX_IHX, VOX_IHY, VOX_IHZ},
                 {VOX_NX, VOX_NY, VOX_NZ}};
    return g;
}

/* Cell along one axis: index c in [0, n-2], weight s of the high node and ds = d s / d x
 * (ih = 1 / h). A coordinate outside the grid is clamped onto it, so there ds = 0. */
inline int voxel_axis(REAL x, REAL lo, REAL h, REAL ih, int n, REAL *s, REAL *ds) {
    REAL u = (x - lo) / h;
    REAL uc = clamp(u, (REAL)0, (REAL)(n - 1));
    int c = clamp((int)floor(uc), 0, n - 2); /* int clamp also guards against NaN */
    REAL t = uc - (REAL)c;
    REAL inside = (u == uc) ? (REAL)1 : (REAL)0;
#if VOX_SMOOTH
    *s = t * t * ((REAL)3 - (REAL)2 * t);
    *ds = inside * (REAL)6 * t * ((REAL)1 - t) * ih;
#else
    *s = t;
    *ds = inside * ih;
#endif
    return c;
}

/* The interpolant g at one point and its gradient (g[0..2]); no window. */
VOX_INLINE REAL voxel_interp1(__global const REAL *restrict fd, vox_geo G, REAL x, REAL y, REAL z,
                              REAL *g) {
    REAL sx, sy, sz, dsx, dsy, dsz;
    int i = voxel_axis(x, G.lo[0], G.h[0], G.ih[0], G.n[0], &sx, &dsx);
    int j = voxel_axis(y, G.lo[1], G.h[1], G.ih[1], G.n[1], &sy, &dsy);
    int k = voxel_axis(z, G.lo[2], G.h[2], G.ih[2], G.n[2], &sz, &dsz);
    __global const REAL *p = fd + (i * G.n[1] + j) * G.n[2] + k;
    const int di = G.n[1] * G.n[2], dj = G.n[2];
    /* the 8 corners v[a][b][c], a b c = low/high node along x y z */
    REAL v000 = p[0], v001 = p[1], v010 = p[dj], v011 = p[dj + 1];
    REAL v100 = p[di], v101 = p[di + 1], v110 = p[di + dj], v111 = p[di + dj + 1];
    /* along z first, then y, then x (each a lerp with weight s) */
    REAL v00 = mix(v000, v001, sz), v01 = mix(v010, v011, sz);
    REAL v10 = mix(v100, v101, sz), v11 = mix(v110, v111, sz);
    REAL v0 = mix(v00, v01, sy), v1 = mix(v10, v11, sy);
    /* d/dz of the z-lerps, reduced over y and x */
    REAL z00 = v001 - v000, z01 = v011 - v010, z10 = v101 - v100, z11 = v111 - v110;
    REAL z0 = mix(z00, z01, sy), z1 = mix(z10, z11, sy);
    g[0] = (v1 - v0) * dsx;
    g[1] = mix(v01 - v00, v11 - v10, sx) * dsy;
    g[2] = mix(z0, z1, sx) * dsz;
    return mix(v0, v1, sx);
}

#if VOX_BSPLINE
/* B-spline, all lanes at once (field_eval here, field_adjoint in voxel_adjoint.cl): weights,
 * derivatives and sums on the realv vectors; only the node reads are per lane. */
typedef CAT(REAL, 4) vox_real4;
#if LANES == 1
#define VOX_INT_SAT(v) convert_int_sat(v)
#else
#define VOX_INT_SAT(v) CAT(CAT(convert_int, LANES), _sat)(v)
#endif

/* One axis for all lanes: cell c in [0, n-2] (a NaN coordinate gives 0), uniform cubic
 * B-spline weights w[4] of the nodes c-1 .. c+2 at t = u - c (voxel.py's bspline_weights),
 * d w/dx and d2 w/dx2 (zero where the coordinate is clamped onto the grid). */
VOX_INLINE intv vox_axis4v(realv x, REAL lo, REAL h, REAL ih, int n, realv *w, realv *d,
                           realv *dd) {
    realv u = (x - RV(lo)) / RV(h);
    realv uc = clamp(u, RV(0), RV(n - 1));
    intv c = clamp(VOX_INT_SAT(floor(uc)), 0, n - 2);
    realv t = uc - TO_REALV(c);
    const REAL r6 = (REAL)1 / (REAL)6;
    realv s = RV(1) - t, t2 = t * t, t3 = t2 * t;
    realv d1 = SEL(RV(0), RV(ih), u == uc), d2 = d1 * RV(ih);
    w[0] = s * s * s * r6;
    w[1] = (RV(3) * t3 - RV(6) * t2 + RV(4)) * r6;
    w[2] = (RV(-3) * t3 + RV(3) * t2 + RV(3) * t + RV(1)) * r6;
    w[3] = t3 * r6;
    d[0] = (RV(-0.5) * s * s) * d1;
    d[1] = (RV(1.5) * t2 - RV(2) * t) * d1;
    d[2] = (RV(-1.5) * t2 + t + RV(0.5)) * d1;
    d[3] = (RV(0.5) * t2) * d1;
    dd[0] = s * d2;
    dd[1] = (RV(3) * t - RV(2)) * d2;
    dd[2] = (RV(1) - RV(3) * t) * d2;
    dd[3] = t * d2;
    return c;
}

/* Per-lane offsets of the 4 node planes along x and y (clamped indices times the stride). */
VOX_INLINE void vox_offsets(intv c, int n, int stride, int (*o)[LANES]) {
    for (int a = 0; a < 4; ++a)
        VSTORE_INT(clamp(c - 1 + a, 0, n - 1) * stride, 0, o[a]);
}

/* z for all lanes. The 4 nodes of a row are contiguous in fd: with 4 or more nodes along z
 * (VOX_ZVEC, from the build) a row is one vector read from kb = clamp(k - 1, 0, n - 4)
 * (oz[0][l] = kb), and the weights of taps clamped onto the same node are folded together (at
 * most one node off: (w0 + w1, w2, w3, 0) in the first cell, (0, w0, w1, w2 + w3) in the
 * last). With fewer nodes oz[c][l] are the 4 clamped taps, read one by one. Returns the cell
 * k. */
VOX_INLINE intv vox_axis4zv(__global const REAL *restrict fp, realv z, int (*oz)[LANES], realv *w,
                            realv *d, realv *dd) {
    intv k = vox_axis4v(z, BOX_LO_Z, VOX_HZ, VOX_IHZ, VOX_NZ, w, d, dd);
#if VOX_ZVEC
    intv kb = clamp(k - 1, 0, VOX_NZ - 4);
    realv sh = TO_REALV(k - 1 - kb);
    maskv lo = sh < RV(0), hi = sh > RV(0);
    realv *arrs[3] = {w, d, dd};
    for (int m = 0; m < 3; ++m) {
        realv *v = arrs[m];
        realv v0 = v[0], v1 = v[1], v2 = v[2], v3 = v[3];
        v[0] = SEL(SEL(v0, RV(0), hi), v0 + v1, lo);
        v[1] = SEL(SEL(v1, v0, hi), v2, lo);
        v[2] = SEL(SEL(v2, v1, hi), v3, lo);
        v[3] = SEL(SEL(v3, v2 + v3, hi), RV(0), lo);
    }
    VSTORE_INT(kb, 0, oz[0]);
#else
    vox_offsets(k, VOX_NZ, 1, oz);
#endif
    return k;
}

/* The 4 z-nodes of row (a, b) for every lane, as 4 vectors q[0..3]. */
VOX_INLINE void vox_row(__global const REAL *restrict fd, int *ox, int *oy, int (*oz)[LANES],
                        realv *q) {
    REAL q0[LANES], q1[LANES], q2[LANES], q3[LANES];
    for (int l = 0; l < LANES; ++l) {
        __global const REAL *p = fd + ox[l] + oy[l];
#if VOX_ZVEC
        vox_real4 r = vload4(0, p + oz[0][l]);
        q0[l] = r.s0; q1[l] = r.s1; q2[l] = r.s2; q3[l] = r.s3;
#else
        q0[l] = p[oz[0][l]]; q1[l] = p[oz[1][l]]; q2[l] = p[oz[2][l]]; q3[l] = p[oz[3][l]];
#endif
    }
    q[0] = VLOAD(0, q0); q[1] = VLOAD(0, q1); q[2] = VLOAD(0, q2); q[3] = VLOAD(0, q3);
}

/* The spline g (a level set's phi) at (x, y, z) and its gradient. */
VOX_INLINE realv vox_spline(FIELD_PARAMS, realv x, realv y, realv z, realv *gx, realv *gy,
                            realv *gz) {
    realv wx[4], dx[4], ex[4], wy[4], dy[4], ey[4], wz[4], dz[4], ez[4];
    int ox[4][LANES], oy[4][LANES], oz[4][LANES];
    vox_offsets(vox_axis4v(x, BOX_LO_X, VOX_HX, VOX_IHX, VOX_NX, wx, dx, ex), VOX_NX,
                VOX_NY * VOX_NZ, ox);
    vox_offsets(vox_axis4v(y, BOX_LO_Y, VOX_HY, VOX_IHY, VOX_NY, wy, dy, ey), VOX_NY, VOX_NZ,
                oy);
    vox_axis4zv(fp, z, oz, wz, dz, ez);
    realv g = RV(0), dgx = RV(0), dgy = RV(0), dgz = RV(0);
    for (int a = 0; a < 4; ++a) {
        realv y0 = RV(0), y1 = RV(0), y2 = RV(0);
        for (int b = 0; b < 4; ++b) {
            realv q[4];
            vox_row(fd, ox[a], oy[b], oz, q);
            realv zc = q[0] * wz[0] + q[1] * wz[1] + q[2] * wz[2] + q[3] * wz[3];
            realv zd = q[0] * dz[0] + q[1] * dz[1] + q[2] * dz[2] + q[3] * dz[3];
            y0 += wy[b] * zc;
            y1 += dy[b] * zc;
            y2 += wy[b] * zd;
        }
        g += wx[a] * y0;
        dgx += dx[a] * y0;
        dgy += wx[a] * y1;
        dgz += wx[a] * y2;
    }
    *gx = dgx;
    *gy = dgy;
    *gz = dgz;
    return g;
}

inline realv field_eval(FIELD_PARAMS, realv x, realv y, realv z, realv *gx, realv *gy,
                        realv *gz) {
    realv dgx, dgy, dgz;
    realv g = vox_spline(FIELD_ARGS, x, y, z, &dgx, &dgy, &dgz);
#if VOX_LEVELSET
    const REAL n = fd[VOX_NODES];
    realv S, dS, F2;
    realv g1 = levelset_map(fp, g, n, &S, &dS, &F2), f1 = RV(n - (REAL)1) * dS;
    dgx *= f1;
    dgy *= f1;
    dgz *= f1;
#else
    realv g1 = g - RV(1);
#endif
    realv vx, vy, vz;
    realv w = box_window(fp, x, y, z, &vx, &vy, &vz);
    *gx = vx * g1 + w * dgx;
    *gy = vy * g1 + w * dgy;
    *gz = vz * g1 + w * dgz;
    return RV(1) + w * g1;
}

#if VOX_LEVELSET && !defined(NO_INTERFACE_STEPS)
/* Interface steps (rendering only: the tracer sets NO_INTERFACE_STEPS for fits, whose
 * adjoints do not differentiate step lengths). The smoothstep's higher derivatives jump at
 * the band edges phi = -+w/2, kinks like the analytic solids'; steps land on them. */
#define FIELD_INTERFACE 1
#define INTERFACE_LO (-(REAL)0.5 * LS_WIDTH)
#define INTERFACE_HI ((REAL)0.5 * LS_WIDTH)
inline realv field_interface(FIELD_PARAMS, realv x, realv y, realv z) {
    realv gx, gy, gz;
    return vox_spline(FIELD_ARGS, x, y, z, &gx, &gy, &gz);
}
/* One region's formula continued past its edges: region -1 inside (F = n - 1), 0 the band
 * (the smoothstep's polynomial, unclamped), +1 outside (F = 0), -2 by position. */
inline realv field_eval_region(FIELD_PARAMS, realv x, realv y, realv z, realv region, realv *gx,
                               realv *gy, realv *gz) {
    realv dgx, dgy, dgz;
    realv phi = vox_spline(FIELD_ARGS, x, y, z, &dgx, &dgy, &dgz);
    const REAL w = LS_WIDTH, dn = fd[VOX_NODES] - (REAL)1;
    realv pos = SEL(SEL(RV(0), RV(1), phi > RV(0.5 * w)), RV(-1), phi < RV(-0.5 * w));
    realv reg = SEL(region, pos, region < RV(-1.5));
    realv t = RV(0.5) - phi / RV(w);
    realv band = SEL(RV(0), RV(1), reg == RV(0));
    realv p = t * t * t * (t * (t * RV(6) - RV(15)) + RV(10));
    realv dp = RV(30) * t * t * (t - RV(1)) * (t - RV(1));
    realv g1 = RV(dn) * SEL(band * p, RV(1), reg < RV(-0.5));
    realv f1 = -RV(dn) * band * dp / RV(w);
    realv vx, vy, vz;
    realv wn = box_window(fp, x, y, z, &vx, &vy, &vz);
    *gx = vx * g1 + wn * f1 * dgx;
    *gy = vy * g1 + wn * f1 * dgy;
    *gz = vz * g1 + wn * f1 * dgz;
    return RV(1) + wn * g1;
}
#endif
#else
inline realv field_eval(FIELD_PARAMS, realv x, realv y, realv z, realv *gx, realv *gy,
                        realv *gz) {
    REAL xs[LANES], ys[LANES], zs[LANES], gs[LANES], dxs[LANES], dys[LANES], dzs[LANES];
    VSTORE(x, 0, xs);
    VSTORE(y, 0, ys);
    VSTORE(z, 0, zs);
    const vox_geo G = vox_geometry(fp);
    for (int l = 0; l < LANES; ++l) {
        REAL d[3];
        gs[l] = voxel_interp1(fd, G, xs[l], ys[l], zs[l], d);
        dxs[l] = d[0];
        dys[l] = d[1];
        dzs[l] = d[2];
    }
    realv g1 = VLOAD(0, gs) - RV(1);
    realv wx, wy, wz;
    realv w = box_window(fp, x, y, z, &wx, &wy, &wz);
    *gx = wx * g1 + w * VLOAD(0, dxs);
    *gy = wy * g1 + w * VLOAD(0, dys);
    *gz = wz * g1 + w * VLOAD(0, dzs);
    return RV(1) + w * g1;
}
#endif
