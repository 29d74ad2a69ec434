/* Backward-pass pieces of the voxel grid (field_voxel.cl): eta, grad eta, Hess(eta) mu, and
 * the splat of w * d/dtheta [eta (mu . grad eta)] onto the nodes that weigh in at the point:
 * the 8 nodes of the cell (trilinear, smoothstep) or the 4 x 4 x 4 nodes c-1 .. c+2 around
 * it (VOX_BSPLINE, node indices clamped to the grid).
 * Layout as field_voxel.cl: node-centred, node (0,0,0) at the box's low corner, values at
 * fd[(i * VOX_NY + j) * VOX_NZ + k]; eta = 1 + W (g - 1) with W the box window. */

#if VOX_BSPLINE
/* B-spline: lane-parallel like its field_eval. Each lane keeps the 64 splats of its current
 * cell in private memory, tap-major (vacc[tap][lane]) so that a step adds them as vectors,
 * and adds them to the global gradient when it moves to another cell or at the end. The key
 * is the cell (i * VOX_NY + j) * VOX_NZ + k; the taps are its 4 x 4 x 4 nodes as the gather
 * reads them (x, y clamped; z folded from kb, see vox_axis4zv). */
#if VOX_LEVELSET
/* the index n is shared by every ray: each lane sums its gradient along the ray in a private
 * vector, and the work-item writes the sum of its lanes to its own slot of `partial` */
#define LS_ACC_DECL realv ls_acc[1] = {RV(0)};
#define LS_ACC_FLUSH(partial, gid)                                                           \
    {                                                                                        \
        REAL s_[LANES], t_ = 0;                                                              \
        VSTORE(ls_acc[0], 0, s_);                                                            \
        for (int l_ = 0; l_ < LANES; ++l_)                                                   \
            t_ += s_[l_];                                                                    \
        partial[gid] = t_;                                                                   \
    }
#define FIELD_ACC_PARAM , int *vcell, REAL(*vacc)[LANES], realv *ls_acc
#define FIELD_ACC_ARG , vcell, vacc, ls_acc
#else
#define LS_ACC_DECL
#define LS_ACC_FLUSH(partial, gid)
#define FIELD_ACC_PARAM , int *vcell, REAL(*vacc)[LANES]
#define FIELD_ACC_ARG , vcell, vacc
#endif
#define FIELD_ACC_DECL                                                                       \
    LS_ACC_DECL                                                                              \
    int vcell[LANES];                                                                        \
    REAL vacc[64][LANES];                                                                    \
    for (int l_ = 0; l_ < LANES; ++l_) {                                                     \
        vcell[l_] = -1;                                                                      \
        for (int c_ = 0; c_ < 64; ++c_)                                                      \
            vacc[c_][l_] = 0;                                                                \
    }
#define FIELD_ACC_FLUSH(grad, partial, gid)                                                  \
    for (int l_ = 0; l_ < LANES; ++l_)                                                       \
        voxel_flush_lane(fp, grad, vcell[l_], vacc, l_);                                     \
    LS_ACC_FLUSH(partial, gid)

/* Add lane l's splats of `cell` to grad and zero them. */
VOX_INLINE void voxel_flush_lane(__global const REAL *restrict fp, __global REAL *grad, int cell,
                                 REAL (*acc)[LANES], int l) {
    if (cell < 0)
        return;
    const int i = cell / (VOX_NY * VOX_NZ), j = (cell / VOX_NZ) % VOX_NY, k = cell % VOX_NZ;
    for (int a = 0; a < 4; ++a) {
        const int oa = clamp(i - 1 + a, 0, VOX_NX - 1) * VOX_NY;
        for (int b = 0; b < 4; ++b) {
            __global REAL *row = grad + (oa + clamp(j - 1 + b, 0, VOX_NY - 1)) * VOX_NZ;
            for (int c = 0; c < 4; ++c) {
                REAL *v = &acc[16 * a + 4 * b + c][l];
#if VOX_ZVEC
                const int kc = clamp(k - 1, 0, VOX_NZ - 4) + c;
#else
                const int kc = clamp(k - 1 + c, 0, VOX_NZ - 1);
#endif
                if (*v != 0)
                    atomic_add_real(row + kc, *v);
                *v = 0;
            }
        }
    }
}

inline realv field_adjoint(FIELD_PARAMS, realv x, realv y, realv z, realv mx, realv my,
                           realv mz, realv w, realv *gx, realv *gy, realv *gz, realv *hx,
                           realv *hy, realv *hz, __global REAL *grad FIELD_ACC_PARAM) {
    realv wx[4], dx[4], sx[4], wy[4], dy[4], sy[4], wz[4], dz[4], sz[4];
    int ox[4][LANES], oy[4][LANES], oz[4][LANES];
    intv i = vox_axis4v(x, BOX_LO_X, VOX_HX, VOX_IHX, VOX_NX, wx, dx, sx);
    intv j = vox_axis4v(y, BOX_LO_Y, VOX_HY, VOX_IHY, VOX_NY, wy, dy, sy);
    intv k = vox_axis4zv(fp, z, oz, wz, dz, sz);
    vox_offsets(i, VOX_NX, VOX_NY * VOX_NZ, ox);
    vox_offsets(j, VOX_NY, VOX_NZ, oy);
    /* interpolant g, its gradient and Hessian (xx yy zz xy xz yz): separable sums over z,
     * then y, then x */
    realv g = RV(0), gg[3] = {RV(0), RV(0), RV(0)};
    realv gh[6] = {RV(0), RV(0), RV(0), RV(0), RV(0), RV(0)};
    for (int a = 0; a < 4; ++a) {
        realv y0 = RV(0), y1 = RV(0), y2 = RV(0), y3 = RV(0), y4 = RV(0), y5 = RV(0);
        for (int b = 0; b < 4; ++b) {
            realv q[4];
            vox_row(fd, ox[a], oy[b], oz, q);
            realv zc = q[0] * wz[0] + q[1] * wz[1] + q[2] * wz[2] + q[3] * wz[3];
            realv zd = q[0] * dz[0] + q[1] * dz[1] + q[2] * dz[2] + q[3] * dz[3];
            realv zs = q[0] * sz[0] + q[1] * sz[1] + q[2] * sz[2] + q[3] * sz[3];
            y0 += wy[b] * zc; /* g, gx, gxx */
            y1 += dy[b] * zc; /* gy, gxy */
            y2 += sy[b] * zc; /* gyy */
            y3 += wy[b] * zd; /* gz, gxz */
            y4 += dy[b] * zd; /* gyz */
            y5 += wy[b] * zs; /* gzz */
        }
        g += wx[a] * y0;
        gg[0] += dx[a] * y0;
        gg[1] += wx[a] * y1;
        gg[2] += wx[a] * y3;
        gh[0] += sx[a] * y0;
        gh[1] += wx[a] * y2;
        gh[2] += wx[a] * y5;
        gh[3] += dx[a] * y1;
        gh[4] += dx[a] * y3;
        gh[5] += wx[a] * y4;
    }
#if VOX_LEVELSET
    /* g is phi: g - 1 becomes F(phi), grad F = F' grad phi, Hess F = F'' grad phi grad
     * phi^T + F' Hess phi */
    const REAL n = fd[VOX_NODES];
    realv S, dS, f2;
    realv g1 = levelset_map(fp, g, n, &S, &dS, &f2), f1 = RV(n - (REAL)1) * dS;
    realv pg[3] = {gg[0], gg[1], gg[2]};
    gh[0] = f2 * pg[0] * pg[0] + f1 * gh[0];
    gh[1] = f2 * pg[1] * pg[1] + f1 * gh[1];
    gh[2] = f2 * pg[2] * pg[2] + f1 * gh[2];
    gh[3] = f2 * pg[0] * pg[1] + f1 * gh[3];
    gh[4] = f2 * pg[0] * pg[2] + f1 * gh[4];
    gh[5] = f2 * pg[1] * pg[2] + f1 * gh[5];
    for (int a = 0; a < 3; ++a)
        gg[a] *= f1;
#endif
    realv gw[3], hw[6];
    realv W = window_hess_v(fp, x, y, z, gw, hw);
#if !VOX_LEVELSET
    realv g1 = g - RV(1);
#endif
    realv eta = RV(1) + W * g1;
    realv ge0 = gw[0] * g1 + W * gg[0], ge1 = gw[1] * g1 + W * gg[1];
    realv ge2 = gw[2] * g1 + W * gg[2];
    *gx = ge0; *gy = ge1; *gz = ge2;
    /* Hess eta = HW (g-1) + gW gg^T + gg gW^T + W Hg, applied to mu */
    realv H[6];
    for (int a = 0; a < 6; ++a)
        H[a] = hw[a] * g1 + W * gh[a];
    H[0] += RV(2) * gw[0] * gg[0]; H[1] += RV(2) * gw[1] * gg[1];
    H[2] += RV(2) * gw[2] * gg[2];
    H[3] += gw[0] * gg[1] + gg[0] * gw[1];
    H[4] += gw[0] * gg[2] + gg[0] * gw[2];
    H[5] += gw[1] * gg[2] + gg[1] * gw[2];
    *hx = H[0] * mx + H[3] * my + H[4] * mz;
    *hy = H[3] * mx + H[1] * my + H[5] * mz;
    *hz = H[4] * mx + H[5] * my + H[2] * mz;
    maskv act = w != RV(0) && W != RV(0);
#if VOX_LEVELSET
    /* only the interface band depends on the parameters */
    act = act && dS != RV(0);
    if (!ANY(act))
        return eta;
    /* d eta / dn = W S, d grad eta / dn = gW S + W dS grad phi */
    realv mp = mx * pg[0] + my * pg[1] + mz * pg[2];
    realv dn = w * ((mx * ge0 + my * ge1 + mz * ge2) * W * S +
                    eta * (S * (mx * gw[0] + my * gw[1] + mz * gw[2]) + W * dS * mp));
    *ls_acc += SEL(RV(0), dn, act);
#else
    if (!ANY(act))
        return eta;
#endif
    /* a lane that splats into another cell than its accumulator's flushes it first */
    REAL acts[LANES];
    int keys[LANES];
    VSTORE(SEL(RV(0), RV(1), act), 0, acts);
    VSTORE_INT((i * VOX_NY + j) * VOX_NZ + k, 0, keys);
    for (int l = 0; l < LANES; ++l)
        if (acts[l] != 0 && keys[l] != vcell[l]) {
            voxel_flush_lane(fp, grad, vcell[l], vacc, l);
            vcell[l] = keys[l];
        }
    /* node weight c = wx wy wz: d eta / d theta = W c, d (mu . grad eta) / d theta =
     * c (mu . gW) + W mu . grad c; the splat w [(mu . grad eta) W c + eta (c (mu . gW) +
     * W mu . grad c)] = A c + B mu . grad c, separable in the three axes */
    realv A = w * ((mx * ge0 + my * ge1 + mz * ge2) * W +
                   eta * (mx * gw[0] + my * gw[1] + mz * gw[2]));
    realv B = w * eta * W;
#if VOX_LEVELSET
    /* d g1 / d theta = F' c, d grad g1 / d theta = F'' c grad phi + F' grad c */
    A = f1 * A + w * eta * W * f2 * mp;
    B = f1 * B;
#endif
    A = SEL(RV(0), A, act);
    B = SEL(RV(0), B, act);
    realv bz[4];
    for (int c = 0; c < 4; ++c)
        bz[c] = B * mz * dz[c];
    for (int a = 0; a < 4; ++a) {
        realv xa = A * wx[a] + B * mx * dx[a], xb = B * my * wx[a];
        for (int b = 0; b < 4; ++b) {
            realv pc = xa * wy[b] + xb * dy[b], pd = wx[a] * wy[b];
            for (int c = 0; c < 4; ++c) {
                REAL *r = vacc[16 * a + 4 * b + c];
                VSTORE(VLOAD(0, r) + pc * wz[c] + pd * bz[c], 0, r);
            }
        }
    }
    return eta;
}
#else
/* Each lane keeps the splats of its current cell in private memory and adds them to the
 * global gradient when it moves to another cell: a ray takes several steps per cell, so
 * this saves most of the atomic additions. */
#define FIELD_ACC_DECL                                                                       \
    int vcell[LANES];                                                                        \
    REAL vacc[LANES][8];                                                                     \
    for (int l_ = 0; l_ < LANES; ++l_) {                                                     \
        vcell[l_] = -1;                                                                      \
        for (int c_ = 0; c_ < 8; ++c_)                                                       \
            vacc[l_][c_] = 0;                                                                \
    }
#define FIELD_ACC_PARAM , int *vcell, REAL(*vacc)[8]
#define FIELD_ACC_ARG , vcell, vacc
#define FIELD_ACC_FLUSH(grad, partial, gid)                                                  \
    for (int l_ = 0; l_ < LANES; ++l_)                                                       \
        voxel_flush(fp, grad, vcell[l_], vacc[l_])

VOX_INLINE void voxel_flush(__global const REAL *restrict fp, __global REAL *grad, int cell,
                            REAL *acc) {
    if (cell < 0)
        return;
    for (int a = 0; a < 2; ++a)
        for (int b = 0; b < 2; ++b)
            for (int c = 0; c < 2; ++c) {
                REAL *v = acc + 4 * a + 2 * b + c;
                if (*v != 0)
                    atomic_add_real(grad + cell + (a * VOX_NY + b) * VOX_NZ + c, *v);
                *v = 0;
            }
}

/* weights of the low/high node along one axis: value, first and second derivative in t */
VOX_INLINE void vox_axis(REAL t, REAL *w, REAL *d, REAL *s) {
#if VOX_SMOOTH
    REAL st = t * t * (3 - 2 * t), dt = 6 * t * (1 - t), sst = 6 - 12 * t;
#else
    REAL st = t, dt = 1, sst = 0;
#endif
    w[0] = 1 - st; w[1] = st;
    d[0] = -dt; d[1] = dt;
    s[0] = -sst; s[1] = sst;
}

/* One lane; the box window W, its gradient gw and Hessian hw come from the lane vectors, the
 * grid's geometry G from vox_geometry. */
VOX_INLINE REAL voxel_adjoint1(FIELD_PARAMS, vox_geo G, __global REAL *grad, REAL x, REAL y,
                               REAL z, REAL mx, REAL my, REAL mz, REAL w, REAL W,
                               const REAL *gw, const REAL *hw, REAL *ge, REAL *hm, int *cell,
                               REAL *acc) {
    const REAL hx = G.h[0], hy = G.h[1], hz = G.h[2];
    const int ny = G.n[1], nz = G.n[2];
    REAL ux = clamp((x - G.lo[0]) / hx, (REAL)0, (REAL)(G.n[0] - 1));
    REAL uy = clamp((y - G.lo[1]) / hy, (REAL)0, (REAL)(ny - 1));
    REAL uz = clamp((z - G.lo[2]) / hz, (REAL)0, (REAL)(nz - 1));
    int i = min((int)floor(ux), G.n[0] - 2);
    int j = min((int)floor(uy), ny - 2);
    int k = min((int)floor(uz), nz - 2);
    REAL wx[2], dx[2], sx[2], wy[2], dy[2], sy[2], wz[2], dz[2], sz[2];
    vox_axis(ux - i, wx, dx, sx);
    vox_axis(uy - j, wy, dy, sy);
    vox_axis(uz - k, wz, dz, sz);
    for (int a = 0; a < 2; ++a) {
        dx[a] /= hx; sx[a] /= hx * hx;
        dy[a] /= hy; sy[a] /= hy * hy;
        dz[a] /= hz; sz[a] /= hz * hz;
    }
    /* interpolant g, its gradient and Hessian (xx yy zz xy xz yz) */
    REAL g = 0, gg[3] = {0, 0, 0}, gh[6] = {0, 0, 0, 0, 0, 0};
    for (int a = 0; a < 2; ++a)
        for (int b = 0; b < 2; ++b)
            for (int c = 0; c < 2; ++c) {
                REAL t = fd[((i + a) * ny + (j + b)) * nz + (k + c)];
                g += wx[a] * wy[b] * wz[c] * t;
                gg[0] += dx[a] * wy[b] * wz[c] * t;
                gg[1] += wx[a] * dy[b] * wz[c] * t;
                gg[2] += wx[a] * wy[b] * dz[c] * t;
                gh[0] += sx[a] * wy[b] * wz[c] * t;
                gh[1] += wx[a] * sy[b] * wz[c] * t;
                gh[2] += wx[a] * wy[b] * sz[c] * t;
                gh[3] += dx[a] * dy[b] * wz[c] * t;
                gh[4] += dx[a] * wy[b] * dz[c] * t;
                gh[5] += wx[a] * dy[b] * dz[c] * t;
            }
    REAL g1 = g - 1;
    REAL eta = 1 + W * g1;
    for (int a = 0; a < 3; ++a)
        ge[a] = gw[a] * g1 + W * gg[a];
    /* Hess eta = HW (g-1) + gW gg^T + gg gW^T + W Hg, applied to mu */
    REAL m[3] = {mx, my, mz};
    REAL H[6];
    for (int a = 0; a < 6; ++a)
        H[a] = hw[a] * g1 + W * gh[a];
    H[0] += 2 * gw[0] * gg[0]; H[1] += 2 * gw[1] * gg[1]; H[2] += 2 * gw[2] * gg[2];
    H[3] += gw[0] * gg[1] + gg[0] * gw[1];
    H[4] += gw[0] * gg[2] + gg[0] * gw[2];
    H[5] += gw[1] * gg[2] + gg[1] * gw[2];
    hm[0] = H[0] * m[0] + H[3] * m[1] + H[4] * m[2];
    hm[1] = H[3] * m[0] + H[1] * m[1] + H[5] * m[2];
    hm[2] = H[4] * m[0] + H[5] * m[1] + H[2] * m[2];
    if (w != 0 && W != 0) {
        /* d eta / d theta_c = W c;  d (mu . grad eta) / d theta_c = c (mu . gW) + W mu . grad c */
        int base = (i * ny + j) * nz + k;
        if (base != *cell) {
            voxel_flush(fp, grad, *cell, acc);
            *cell = base;
        }
        REAL am = w * (mx * ge[0] + my * ge[1] + mz * ge[2]);
        REAL mw = mx * gw[0] + my * gw[1] + mz * gw[2];
        for (int a = 0; a < 2; ++a)
            for (int b = 0; b < 2; ++b)
                for (int c = 0; c < 2; ++c) {
                    REAL cv = wx[a] * wy[b] * wz[c];
                    REAL cm = mx * dx[a] * wy[b] * wz[c] + my * wx[a] * dy[b] * wz[c] +
                              mz * wx[a] * wy[b] * dz[c];
                    REAL v = am * W * cv + w * eta * (cv * mw + W * cm);
                    acc[4 * a + 2 * b + c] += v;
                }
    }
    return eta;
}

inline realv field_adjoint(FIELD_PARAMS, realv x, realv y, realv z, realv mx, realv my,
                           realv mz, realv w, realv *gx, realv *gy, realv *gz, realv *hx,
                           realv *hy, realv *hz, __global REAL *grad FIELD_ACC_PARAM) {
    REAL xs[LANES], ys[LANES], zs[LANES], ms[3][LANES], ws[LANES];
    REAL eo[LANES], go[3][LANES], ho[3][LANES], Ws[LANES], gws[3][LANES], hws[6][LANES];
    VSTORE(x, 0, xs); VSTORE(y, 0, ys); VSTORE(z, 0, zs);
    VSTORE(mx, 0, ms[0]); VSTORE(my, 0, ms[1]); VSTORE(mz, 0, ms[2]);
    VSTORE(w, 0, ws);
    realv gwv[3], hwv[6];
    VSTORE(window_hess_v(fp, x, y, z, gwv, hwv), 0, Ws);
    for (int a = 0; a < 3; ++a)
        VSTORE(gwv[a], 0, gws[a]);
    for (int a = 0; a < 6; ++a)
        VSTORE(hwv[a], 0, hws[a]);
    const vox_geo G = vox_geometry(fp);
    for (int l = 0; l < LANES; ++l) {
        REAL ge[3], hm[3];
        REAL gw[3] = {gws[0][l], gws[1][l], gws[2][l]};
        REAL hw[6] = {hws[0][l], hws[1][l], hws[2][l], hws[3][l], hws[4][l], hws[5][l]};
        eo[l] = voxel_adjoint1(FIELD_ARGS, G, grad, xs[l], ys[l], zs[l], ms[0][l], ms[1][l],
                               ms[2][l], ws[l], Ws[l], gw, hw, ge, hm, &vcell[l], vacc[l]);
        for (int a = 0; a < 3; ++a) {
            go[a][l] = ge[a];
            ho[a][l] = hm[a];
        }
    }
    *gx = VLOAD(0, go[0]); *gy = VLOAD(0, go[1]); *gz = VLOAD(0, go[2]);
    *hx = VLOAD(0, ho[0]); *hy = VLOAD(0, ho[1]); *hz = VLOAD(0, ho[2]);
    return VLOAD(0, eo);
}
#endif
