/* Voxel-grid index field (clrefract/fields/voxel.py holds the float64 NumPy reference).
 *
 * Node-centred samples: VOX_NX x VOX_NY x VOX_NZ nodes, node (0,0,0) on the box's low corner
 * and node (n-1) on its high corner along each axis (spacing = size / (n - 1)). The value of
 * node (i, j, k) is fd[(i * VOX_NY + j) * VOX_NZ + k] (NumPy C order of values[i, j, k]).
 * fp is unused.
 *
 * g(x) interpolates the nodes of the cell holding x with weights w0 = 1 - s(t), w1 = s(t) per
 * axis, t in [0, 1] the position inside the cell: s(t) = t (trilinear, C0) or, with
 * VOX_SMOOTH, s(t) = 3t^2 - 2t^3 (C1, so grad eta is continuous and the diagonal of
 * Hess(eta) is not zero inside a cell). Points outside the grid are clamped onto it.
 * eta = 1 + W (g - 1), W the box window, so rays leave the box in straight lines; the gradient
 * is the exact derivative of that expression.
 *
 * The gather is scalar: field_eval spills its LANES points to private arrays, interpolates
 * each with voxel_interp1 and loads the results back; with LANES == 1 it is plain scalar
 * code. The window is applied on the vectors.
 */

#ifndef VOX_SMOOTH
#define VOX_SMOOTH 0
#endif

#define VOX_HX (((REAL)BOX_HI_X - (REAL)BOX_LO_X) / (REAL)(VOX_NX - 1))
#define VOX_HY (((REAL)BOX_HI_Y - (REAL)BOX_LO_Y) / (REAL)(VOX_NY - 1))
#define VOX_HZ (((REAL)BOX_HI_Z - (REAL)BOX_LO_Z) / (REAL)(VOX_NZ - 1))

/* Cell along one axis: index c in [0, n-2], weight s of the high node and ds = d s / d x.
 * A coordinate outside the grid is clamped onto it, so there ds = 0. */
inline int voxel_axis(REAL x, REAL lo, REAL h, int n, REAL *s, REAL *ds) {
    REAL u = (x - lo) / h;
    REAL uc = clamp(u, (REAL)0, (REAL)(n - 1));
    int c = clamp((int)floor(uc), 0, n - 2); /* int clamp also guards against NaN */
    REAL t = uc - (REAL)c;
    REAL inside = (u == uc) ? (REAL)1 : (REAL)0;
#if VOX_SMOOTH
    *s = t * t * ((REAL)3 - (REAL)2 * t);
    *ds = inside * (REAL)6 * t * ((REAL)1 - t) / h;
#else
    *s = t;
    *ds = inside / h;
#endif
    return c;
}

/* The interpolant g at one point and its gradient (g[0..2]); no window. */
inline REAL voxel_interp1(__global const REAL *restrict fd, REAL x, REAL y, REAL z, REAL *g) {
    REAL sx, sy, sz, dsx, dsy, dsz;
    int i = voxel_axis(x, (REAL)BOX_LO_X, VOX_HX, VOX_NX, &sx, &dsx);
    int j = voxel_axis(y, (REAL)BOX_LO_Y, VOX_HY, VOX_NY, &sy, &dsy);
    int k = voxel_axis(z, (REAL)BOX_LO_Z, VOX_HZ, VOX_NZ, &sz, &dsz);
    __global const REAL *p = fd + (i * VOX_NY + j) * VOX_NZ + k;
    const int di = VOX_NY * VOX_NZ, dj = VOX_NZ;
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

inline realv field_eval(FIELD_PARAMS, realv x, realv y, realv z, realv *gx, realv *gy,
                        realv *gz) {
    REAL xs[LANES], ys[LANES], zs[LANES], gs[LANES], dxs[LANES], dys[LANES], dzs[LANES];
    VSTORE(x, 0, xs);
    VSTORE(y, 0, ys);
    VSTORE(z, 0, zs);
    for (int l = 0; l < LANES; ++l) {
        REAL d[3];
        gs[l] = voxel_interp1(fd, xs[l], ys[l], zs[l], d);
        dxs[l] = d[0];
        dys[l] = d[1];
        dzs[l] = d[2];
    }
    realv g1 = VLOAD(0, gs) - RV(1);
    realv wx, wy, wz;
    realv w = box_window(x, y, z, &wx, &wy, &wz);
    *gx = wx * g1 + w * VLOAD(0, dxs);
    *gy = wy * g1 + w * VLOAD(0, dys);
    *gz = wz * g1 + w * VLOAD(0, dzs);
    return RV(1) + w * g1;
}
