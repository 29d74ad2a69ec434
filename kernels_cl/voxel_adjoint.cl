/* Backward-pass pieces of the voxel grid (field_voxel.cl): eta, grad eta, Hess(eta) mu, and
 * the splat of w * d/dtheta [eta (mu . grad eta)] onto the 8 nodes of the cell.
 * Layout as field_voxel.cl: node-centred, node (0,0,0) at the box's low corner, values at
 * fd[(i * VOX_NY + j) * VOX_NZ + k]; eta = 1 + W (g - 1) with W the box window. */

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
        voxel_flush(grad, vcell[l_], vacc[l_])

inline void voxel_flush(__global REAL *grad, int cell, REAL *acc) {
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
inline void vox_axis(REAL t, REAL *w, REAL *d, REAL *s) {
#if VOX_SMOOTH
    REAL st = t * t * (3 - 2 * t), dt = 6 * t * (1 - t), sst = 6 - 12 * t;
#else
    REAL st = t, dt = 1, sst = 0;
#endif
    w[0] = 1 - st; w[1] = st;
    d[0] = -dt; d[1] = dt;
    s[0] = -sst; s[1] = sst;
}

inline REAL voxel_adjoint1(__global const REAL *restrict fd, __global REAL *grad, REAL x,
                           REAL y, REAL z, REAL mx, REAL my, REAL mz, REAL w, REAL *ge,
                           REAL *hm, int *cell, REAL *acc) {
    const REAL hx = ((REAL)BOX_HI_X - (REAL)BOX_LO_X) / (VOX_NX - 1);
    const REAL hy = ((REAL)BOX_HI_Y - (REAL)BOX_LO_Y) / (VOX_NY - 1);
    const REAL hz = ((REAL)BOX_HI_Z - (REAL)BOX_LO_Z) / (VOX_NZ - 1);
    REAL ux = clamp((x - (REAL)BOX_LO_X) / hx, (REAL)0, (REAL)(VOX_NX - 1));
    REAL uy = clamp((y - (REAL)BOX_LO_Y) / hy, (REAL)0, (REAL)(VOX_NY - 1));
    REAL uz = clamp((z - (REAL)BOX_LO_Z) / hz, (REAL)0, (REAL)(VOX_NZ - 1));
    int i = min((int)floor(ux), VOX_NX - 2);
    int j = min((int)floor(uy), VOX_NY - 2);
    int k = min((int)floor(uz), VOX_NZ - 2);
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
                REAL t = fd[((i + a) * VOX_NY + (j + b)) * VOX_NZ + (k + c)];
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
    REAL gw[3], hw[6];
    REAL W = window_hess(x, y, z, gw, hw);
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
        int base = (i * VOX_NY + j) * VOX_NZ + k;
        if (base != *cell) {
            voxel_flush(grad, *cell, acc);
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
    REAL eo[LANES], go[3][LANES], ho[3][LANES];
    VSTORE(x, 0, xs); VSTORE(y, 0, ys); VSTORE(z, 0, zs);
    VSTORE(mx, 0, ms[0]); VSTORE(my, 0, ms[1]); VSTORE(mz, 0, ms[2]);
    VSTORE(w, 0, ws);
    for (int l = 0; l < LANES; ++l) {
        REAL ge[3], hm[3];
        eo[l] = voxel_adjoint1(fd, grad, xs[l], ys[l], zs[l], ms[0][l], ms[1][l], ms[2][l],
                               ws[l], ge, hm, &vcell[l], vacc[l]);
        for (int a = 0; a < 3; ++a) {
            go[a][l] = ge[a];
            ho[a][l] = hm[a];
        }
    }
    *gx = VLOAD(0, go[0]); *gy = VLOAD(0, go[1]); *gz = VLOAD(0, go[2]);
    *hx = VLOAD(0, ho[0]); *hy = VLOAD(0, ho[1]); *hz = VLOAD(0, ho[2]);
    return VLOAD(0, eo);
}
