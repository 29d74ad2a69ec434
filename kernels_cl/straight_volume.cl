/* Straight-ray emission-absorption volume rendering (the paper's Meridian- and Synapse-style
 * baselines): no bending, density sigma (per mm) and linear RGB colour c on a node grid of
 * RES^3 values per channel over the box, trilinear, channel-major (vol[ch * N + node]).
 *
 * A ray is cut where it crosses the box into M equal segments of length dt (the sample at
 * each segment's middle), composited front to back over the environment behind:
 *     alpha_i = 1 - exp(-sigma_i dt),  T_{i+1} = T_i (1 - alpha_i),
 *     C = sum_i T_i alpha_i c_i + T_M bg.
 * Its exact reverse needs no stored samples: with R_{i+1} = C - sum_{j<=i} T_j alpha_j c_j
 * (the light that reaches the camera from behind sample i),
 *     dC/dc_i = T_i alpha_i,   dC/dsigma_i = dt (T_{i+1} c_i - R_{i+1}),
 * so the backward kernel marches forward again from the front with C known.
 * Values are used as stored (the host keeps them >= 0 after each step), so the gradient is
 * that of the identity: a projected gradient, with no dead zone at 0 where training starts.
 * Needs common.h (REAL, atomic_add_real) and RES from the build.
 */

#define N_NODES (RES * RES * RES)
#define T_STOP ((REAL)1e-5) /* light left below this: the rest of the ray is invisible */

typedef struct {
    REAL lo[3], h[3];
} Grid;

/* Entry and exit distances of a ray through the box; 0 when it misses. */
inline int ray_box(const REAL *o, const REAL *d, const Grid *g, REAL *t0, REAL *t1) {
    REAL a = 0, b = (REAL)1e30;
    for (int k = 0; k < 3; ++k) {
        REAL hi = g->lo[k] + g->h[k] * (RES - 1);
        REAL inv = (REAL)1 / (fabs(d[k]) > (REAL)1e-12 ? d[k] : (REAL)1e-12);
        REAL ta = (g->lo[k] - o[k]) * inv, tb = (hi - o[k]) * inv;
        a = fmax(a, fmin(ta, tb));
        b = fmin(b, fmax(ta, tb));
    }
    *t0 = a;
    *t1 = b;
    return b > a;
}

/* The 8 node indices and trilinear weights around point p. */
inline void corners(const REAL *p, const Grid *g, int *idx, REAL *w) {
    int i[3];
    REAL f[3];
    for (int k = 0; k < 3; ++k) {
        REAL u = clamp((p[k] - g->lo[k]) / g->h[k], (REAL)0, (REAL)(RES - 1));
        i[k] = min((int)floor(u), RES - 2);
        f[k] = u - (REAL)i[k];
    }
    for (int c = 0; c < 8; ++c) {
        int cx = c & 1, cy = (c >> 1) & 1, cz = (c >> 2) & 1;
        idx[c] = ((i[0] + cx) * RES + (i[1] + cy)) * RES + (i[2] + cz);
        w[c] = (cx ? f[0] : 1 - f[0]) * (cy ? f[1] : 1 - f[1]) * (cz ? f[2] : 1 - f[2]);
    }
}

/* One pass along ray `r`: returns the composited colour in rgb (and the light left in *trans).
 * With grad != 0 it is the backward pass: dl_dc is dLoss/dC of the ray, c_total its C. */
inline void march(int r, __global const REAL *orig, __global const REAL *dirs,
                  __global const REAL *bg, __global const REAL *vol, const Grid *g, REAL ds,
                  REAL *rgb, REAL *trans, __global REAL *grad, const REAL *dl_dc,
                  const REAL *c_total) {
    REAL o[3] = {orig[3 * r], orig[3 * r + 1], orig[3 * r + 2]};
    REAL d[3] = {dirs[3 * r], dirs[3 * r + 1], dirs[3 * r + 2]};
    REAL acc[3] = {0, 0, 0}, T = 1, t0, t1;
    if (ray_box(o, d, g, &t0, &t1)) {
        int m = max(1, (int)ceil((t1 - t0) / ds));
        REAL dt = (t1 - t0) / (REAL)m;
        for (int s = 0; s < m && T > T_STOP; ++s) {
            REAL t = t0 + ((REAL)s + (REAL)0.5) * dt;
            REAL p[3] = {o[0] + t * d[0], o[1] + t * d[1], o[2] + t * d[2]};
            int idx[8];
            REAL w[8], v[4] = {0, 0, 0, 0};
            corners(p, g, idx, w);
            for (int c = 0; c < 8; ++c)
                for (int ch = 0; ch < 4; ++ch) v[ch] += w[c] * vol[ch * N_NODES + idx[c]];
            REAL sigma = fmax(v[0], (REAL)0);
            REAL alpha = 1 - exp(-sigma * dt);
            REAL Tn = T * (1 - alpha);
            for (int ch = 0; ch < 3; ++ch) acc[ch] += T * alpha * fmax(v[1 + ch], (REAL)0);
            if (grad) {
                REAL g_sigma = 0, g_col[3];
                for (int ch = 0; ch < 3; ++ch) {
                    REAL behind = c_total[ch] - acc[ch];
                    g_sigma += dl_dc[ch] * dt * (Tn * fmax(v[1 + ch], (REAL)0) - behind);
                    g_col[ch] = dl_dc[ch] * T * alpha;
                }
                for (int c = 0; c < 8; ++c) {
                    atomic_add_real(grad + idx[c], w[c] * g_sigma);
                    for (int ch = 0; ch < 3; ++ch)
                        atomic_add_real(grad + (1 + ch) * N_NODES + idx[c], w[c] * g_col[ch]);
                }
            }
            T = Tn;
        }
    }
    for (int ch = 0; ch < 3; ++ch) rgb[ch] = acc[ch] + T * bg[3 * r + ch];
    *trans = T;
}

inline Grid make_grid(REAL lx, REAL ly, REAL lz, REAL hx, REAL hy, REAL hz) {
    Grid g = {{lx, ly, lz}, {hx, hy, hz}};
    return g;
}

__kernel void straight_render(__global const REAL *orig, __global const REAL *dirs,
                              __global const REAL *bg, __global const REAL *vol, REAL lx,
                              REAL ly, REAL lz, REAL hx, REAL hy, REAL hz, REAL ds, int n,
                              __global REAL *out, __global REAL *trans) {
    int r = get_global_id(0);
    if (r >= n) return;
    Grid g = make_grid(lx, ly, lz, hx, hy, hz);
    REAL rgb[3], T;
    march(r, orig, dirs, bg, vol, &g, ds, rgb, &T, 0, 0, 0);
    for (int ch = 0; ch < 3; ++ch) out[3 * r + ch] = rgb[ch];
    trans[r] = T;
}

__kernel void straight_backward(__global const REAL *orig, __global const REAL *dirs,
                                __global const REAL *bg, __global const REAL *vol, REAL lx,
                                REAL ly, REAL lz, REAL hx, REAL hy, REAL hz, REAL ds, int n,
                                __global const REAL *colour, __global const REAL *dl_dc,
                                __global REAL *grad) {
    int r = get_global_id(0);
    if (r >= n) return;
    Grid g = make_grid(lx, ly, lz, hx, hy, hz);
    REAL c[3] = {colour[3 * r], colour[3 * r + 1], colour[3 * r + 2]};
    REAL gl[3] = {dl_dc[3 * r], dl_dc[3 * r + 1], dl_dc[3 * r + 2]};
    if (gl[0] == 0 && gl[1] == 0 && gl[2] == 0) return;
    REAL rgb[3], T;
    march(r, orig, dirs, bg, vol, &g, ds, rgb, &T, grad, gl, c);
}
