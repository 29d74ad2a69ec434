/* Sharp interfaces: a solid of one index eta bounded by the zero set of phi (negative
 * inside, mm), air outside, inside the box. Rays are straight between surface events; each
 * crossing is bracketed by sphere tracing (steps |phi| / LIP, LIP a Lipschitz bound of phi
 * from the host, never below MIN_STEP) and solved by the Illinois method to TOL mm. At a
 * crossing the ray refracts by Snell's law with the normal grad phi / |grad phi|, or
 * reflects past the critical angle; at most MAX_EVENTS events (then trapped: black).
 *
 * The backward pass retraces a ray, keeping its events (a ray's memory grows with its
 * crossings, not its length), and reverses them: through Snell's law, the normal (grad phi
 * at the hit point and its Hessian), and the hit point, differentiated implicitly on
 * phi(x; theta) = 0. The phi parameters' gradient goes to `grad` by atomic adds, the index's
 * to one partial per ray.
 *
 * Providers of phi (one per build): SDF_GRID, the tricubic B-spline on the node grid of
 * fields/voxel.py (VOX_NX.. nodes over the box, fd[0..SDF_NODES-1] in C order, eta =
 * fd[SDF_NODES]); SDF_SPHERE, a sphere fd = (cx, cy, cz, R, eta), the closed-form oracle;
 * SDF_PLANES, a convex polyhedron of that many faces, whose crossings are found in closed form
 * (its sdf_cross replaces the march), or with POLY_SOFT its edges rounded (marched).
 * fp: TOL, OFFSET and MIN_STEP (clrefract/interface.py), then the box and the node counts
 * (common.h, GEO_AT 3). Needs common.h (REAL, atomic_add_real, ST_*) and snell_common.h
 * (real3, refract_or_reflect, box_exit_distance). One ray per work-item: the loops are data
 * dependent.
 */

/* PoCL may miscompile helpers that take private arrays by pointer unless they are inlined */
#define SDF_INLINE inline __attribute__((always_inline))

#ifndef MAX_EVENTS
#define MAX_EVENTS 32
#endif
#ifndef MAX_MARCH
#define MAX_MARCH 4096
#endif
#define TOL (fp[0])      /* the crossing's tolerance along the ray, mm */
#define OFFSET (fp[1])   /* the offset off the surface after an event, mm */
#define MIN_STEP (fp[2]) /* the march's shortest step, mm */

#if SDF_GRID
#define SDF_NODES (VOX_NX * VOX_NY * VOX_NZ)
#define SDF_ETA(fd) ((fd)[SDF_NODES])

/* One axis: cell c, the uniform cubic B-spline weights of nodes c-1 .. c+2 and their first
 * and second derivatives in x (zero where x is clamped onto the grid), as voxel.py's _axis4. */
SDF_INLINE int sdf_axis(REAL x, REAL lo, REAL h, REAL ih, int n, REAL *w, REAL *d, REAL *dd) {
    REAL u = (x - lo) / h;
    REAL uc = clamp(u, (REAL)0, (REAL)(n - 1));
    int c = clamp((int)floor(uc), 0, n - 2);
    REAL t = uc - (REAL)c, s = (REAL)1 - t, t2 = t * t, t3 = t2 * t;
    const REAL r6 = (REAL)1 / (REAL)6;
    REAL d1 = u == uc ? ih : (REAL)0, d2 = d1 * ih;
    w[0] = s * s * s * r6;
    w[1] = ((REAL)3 * t3 - (REAL)6 * t2 + (REAL)4) * r6;
    w[2] = ((REAL)-3 * t3 + (REAL)3 * t2 + (REAL)3 * t + (REAL)1) * r6;
    w[3] = t3 * r6;
    d[0] = (REAL)-0.5 * s * s * d1;
    d[1] = ((REAL)1.5 * t2 - (REAL)2 * t) * d1;
    d[2] = ((REAL)-1.5 * t2 + t + (REAL)0.5) * d1;
    d[3] = (REAL)0.5 * t2 * d1;
    dd[0] = s * d2;
    dd[1] = ((REAL)3 * t - (REAL)2) * d2;
    dd[2] = ((REAL)1 - (REAL)3 * t) * d2;
    dd[3] = t * d2;
    return c;
}

#define SDF_AXES(x)                                                                        \
    REAL wx[4], dx[4], ex[4], wy[4], dy[4], ey[4], wz[4], dz[4], ez[4];                    \
    int cx = sdf_axis((x).x, BOX_LO_X, VOX_HX, VOX_IHX, VOX_NX, wx, dx, ex);               \
    int cy = sdf_axis((x).y, BOX_LO_Y, VOX_HY, VOX_IHY, VOX_NY, wy, dy, ey);               \
    int cz = sdf_axis((x).z, BOX_LO_Z, VOX_HZ, VOX_IHZ, VOX_NZ, wz, dz, ez);
#define SDF_NODE(a, b, c)                                                                  \
    ((clamp(cx - 1 + (a), 0, VOX_NX - 1) * VOX_NY + clamp(cy - 1 + (b), 0, VOX_NY - 1)) *  \
         VOX_NZ +                                                                          \
     clamp(cz - 1 + (c), 0, VOX_NZ - 1))

SDF_INLINE REAL sdf_value(FIELD_PARAMS, real3 x) {
    SDF_AXES(x)
    REAL f = 0;
    for (int a = 0; a < 4; ++a) {
        REAL y0 = 0;
        for (int b = 0; b < 4; ++b) {
            REAL zc = 0;
            for (int c = 0; c < 4; ++c) zc += fd[SDF_NODE(a, b, c)] * wz[c];
            y0 += wy[b] * zc;
        }
        f += wx[a] * y0;
    }
    return f;
}

/* phi, its gradient and its Hessian h = (xx, yy, zz, xy, xz, yz). */
SDF_INLINE REAL sdf_eval(FIELD_PARAMS, real3 x, real3 *g, REAL *h) {
    SDF_AXES(x)
    REAL f = 0, gx = 0, gy = 0, gz = 0;
    for (int k = 0; k < 6; ++k) h[k] = 0;
    for (int a = 0; a < 4; ++a) {
        REAL y0 = 0, y1 = 0, y2 = 0, y11 = 0, y12 = 0, y22 = 0;
        for (int b = 0; b < 4; ++b) {
            REAL zc = 0, zd = 0, ze = 0;
            for (int c = 0; c < 4; ++c) {
                REAL q = fd[SDF_NODE(a, b, c)];
                zc += q * wz[c];
                zd += q * dz[c];
                ze += q * ez[c];
            }
            y0 += wy[b] * zc;
            y1 += dy[b] * zc;
            y2 += wy[b] * zd;
            y11 += ey[b] * zc;
            y12 += dy[b] * zd;
            y22 += wy[b] * ze;
        }
        f += wx[a] * y0;
        gx += dx[a] * y0;
        gy += wx[a] * y1;
        gz += wx[a] * y2;
        h[0] += ex[a] * y0;
        h[1] += wx[a] * y11;
        h[2] += wx[a] * y22;
        h[3] += dx[a] * y1;
        h[4] += dx[a] * y2;
        h[5] += wx[a] * y12;
    }
    *g = r3(gx, gy, gz);
    return f;
}

/* grad += af dphi/dtheta + ag . dgrad(phi)/dtheta at x. */
SDF_INLINE void sdf_splat(FIELD_PARAMS, __global REAL *grad, real3 x, REAL af, real3 ag) {
    SDF_AXES(x)
    for (int a = 0; a < 4; ++a)
        for (int b = 0; b < 4; ++b)
            for (int c = 0; c < 4; ++c) {
                REAL v = af * wx[a] * wy[b] * wz[c] + ag.x * dx[a] * wy[b] * wz[c] +
                         ag.y * wx[a] * dy[b] * wz[c] + ag.z * wx[a] * wy[b] * dz[c];
                if (v != (REAL)0) atomic_add_real(grad + SDF_NODE(a, b, c), v);
            }
}
#endif

#if SDF_SPHERE
#define SDF_ETA(fd) ((fd)[4])
SDF_INLINE REAL sdf_value(FIELD_PARAMS, real3 x) {
    real3 r = x - r3(fd[0], fd[1], fd[2]);
    return sqrt(dot(r, r)) - fd[3];
}

SDF_INLINE REAL sdf_eval(FIELD_PARAMS, real3 x, real3 *g, REAL *h) {
    real3 r = x - r3(fd[0], fd[1], fd[2]);
    REAL l = sqrt(dot(r, r));
    real3 u = r / l;
    *g = u;
    h[0] = ((REAL)1 - u.x * u.x) / l;
    h[1] = ((REAL)1 - u.y * u.y) / l;
    h[2] = ((REAL)1 - u.z * u.z) / l;
    h[3] = -u.x * u.y / l;
    h[4] = -u.x * u.z / l;
    h[5] = -u.y * u.z / l;
    return l - fd[3];
}

/* phi = |x - c| - R: dphi/dc = -u, dphi/dR = -1, dgrad/dc = -Hess, dgrad/dR = 0. */
SDF_INLINE void sdf_splat(FIELD_PARAMS, __global REAL *grad, real3 x, REAL af, real3 ag) {
    REAL h[6];
    real3 u;
    sdf_eval(FIELD_ARGS, x, &u, h);
    atomic_add_real(grad + 0, -af * u.x - (h[0] * ag.x + h[3] * ag.y + h[4] * ag.z));
    atomic_add_real(grad + 1, -af * u.y - (h[3] * ag.x + h[1] * ag.y + h[5] * ag.z));
    atomic_add_real(grad + 2, -af * u.z - (h[4] * ag.x + h[5] * ag.y + h[2] * ag.z));
    atomic_add_real(grad + 3, -af);
}
#endif

#if SDF_PLANES
/* A convex polyhedron, the intersection of SDF_PLANES half-spaces, v_j = n_j . (x - c) - d_j,
 * n_j = a_j / |a_j|, with fd[4j..4j+3] = (a_j, d_j) and c = (POLY_CX, POLY_CY, POLY_CZ).
 * Sharp: phi = max_j v_j, exact inside, a lower bound on the distance outside (a safe march
 * at LIP 1); flat faces and sharp edges, which no spline holds. With POLY_SOFT = k (mm):
 * phi = k log sum_j exp(v_j / k), the same faces with edges rounded over about k, its
 * gradient the softmax w of the normals (still 1-Lipschitz). */
#define SDF_ETA(fd) ((fd)[4 * SDF_PLANES])

SDF_INLINE real3 poly_r(real3 x) { return x - r3((REAL)POLY_CX, (REAL)POLY_CY, (REAL)POLY_CZ); }

SDF_INLINE REAL poly_v(FIELD_PARAMS, int j, real3 r, real3 *n, REAL *ia) {
    real3 a = r3(fd[4 * j], fd[4 * j + 1], fd[4 * j + 2]);
    *ia = (REAL)1 / sqrt(dot(a, a));
    *n = a * *ia;
    return dot(*n, r) - fd[4 * j + 3];
}

/* phi at x; the largest v in *vmax and, soft, the softmax's sum S of exp((v - vmax) / k) */
SDF_INLINE REAL poly_phi(FIELD_PARAMS, real3 r, REAL *vmax, REAL *sum) {
    REAL m = (REAL)-1e30, ia;
    real3 n;
    for (int j = 0; j < SDF_PLANES; ++j) m = fmax(m, poly_v(FIELD_ARGS, j, r, &n, &ia));
    *vmax = m;
    *sum = (REAL)1;
#ifdef POLY_SOFT
    const REAL k = (REAL)POLY_SOFT;
    REAL sm = 0;
    for (int j = 0; j < SDF_PLANES; ++j) sm += exp((poly_v(FIELD_ARGS, j, r, &n, &ia) - m) / k);
    *sum = sm;
    return m + k * log(sm);
#else
    return m;
#endif
}

/* the weight of face j in phi's gradient: the softmax, or 1 on the largest v */
SDF_INLINE REAL poly_w(REAL v, REAL vmax, REAL sum) {
#ifdef POLY_SOFT
    return exp((v - vmax) / (REAL)POLY_SOFT) / sum;
#else
    return v == vmax ? (REAL)1 : (REAL)0;
#endif
}

SDF_INLINE REAL sdf_value(FIELD_PARAMS, real3 x) {
    REAL m, sm;
    return poly_phi(FIELD_ARGS, poly_r(x), &m, &sm);
}

/* g = sum_j w_j n_j; soft, H = (sum_j w_j n_j n_j^T - g g^T) / k, else 0 */
SDF_INLINE REAL sdf_eval(FIELD_PARAMS, real3 x, real3 *g, REAL *h) {
    real3 r = poly_r(x), gs = r3(0, 0, 0), n;
    REAL m, sm, ia;
    REAL f = poly_phi(FIELD_ARGS, r, &m, &sm);
    for (int k = 0; k < 6; ++k) h[k] = 0;
    int taken = 0;
    for (int j = 0; j < SDF_PLANES; ++j) {
        REAL v = poly_v(FIELD_ARGS, j, r, &n, &ia);
        REAL w = poly_w(v, m, sm);
#ifndef POLY_SOFT
        if (taken) w = 0; /* a tie: one face */
#endif
        if (w == (REAL)0) continue;
        taken = 1;
        gs += w * n;
        h[0] += w * n.x * n.x;
        h[1] += w * n.y * n.y;
        h[2] += w * n.z * n.z;
        h[3] += w * n.x * n.y;
        h[4] += w * n.x * n.z;
        h[5] += w * n.y * n.z;
    }
#ifdef POLY_SOFT
    const REAL ik = (REAL)1 / (REAL)POLY_SOFT;
    h[0] = (h[0] - gs.x * gs.x) * ik;
    h[1] = (h[1] - gs.y * gs.y) * ik;
    h[2] = (h[2] - gs.z * gs.z) * ik;
    h[3] = (h[3] - gs.x * gs.y) * ik;
    h[4] = (h[4] - gs.x * gs.z) * ik;
    h[5] = (h[5] - gs.y * gs.z) * ik;
#else
    for (int k = 0; k < 6; ++k) h[k] = 0;
#endif
    *g = gs;
    return f;
}

/* Face j, weight w: dphi/dv_j = w_j; ag . dg/dv_j = c_j = w_j (n_j - g) . ag / k (soft);
 * dv_j/da_j = P_j r / |a_j|, dv_j/dd_j = -1, ag . d(w_j n_j)/da_j = w_j P_j ag / |a_j|,
 * P_j = I - n_j n_j^T. */
SDF_INLINE void sdf_splat(FIELD_PARAMS, __global REAL *grad, real3 x, REAL af, real3 ag) {
    real3 r = poly_r(x), n, g = r3(0, 0, 0);
    REAL m, sm, ia;
    poly_phi(FIELD_ARGS, r, &m, &sm);
#ifdef POLY_SOFT
    for (int j = 0; j < SDF_PLANES; ++j) {
        REAL v = poly_v(FIELD_ARGS, j, r, &n, &ia);
        g += poly_w(v, m, sm) * n;
    }
#endif
    int taken = 0;
    for (int j = 0; j < SDF_PLANES; ++j) {
        REAL v = poly_v(FIELD_ARGS, j, r, &n, &ia);
        REAL w = poly_w(v, m, sm);
#ifndef POLY_SOFT
        if (taken) w = 0;
#endif
        if (w == (REAL)0) continue;
        taken = 1;
#ifdef POLY_SOFT
        REAL dv = af * w + w * dot(n - g, ag) / (REAL)POLY_SOFT;
#else
        REAL dv = af * w;
#endif
        real3 u = dv * r + w * ag;
        real3 ga = (u - n * dot(n, u)) * ia;
        atomic_add_real(grad + 4 * j, ga.x);
        atomic_add_real(grad + 4 * j + 1, ga.y);
        atomic_add_real(grad + 4 * j + 2, ga.z);
        atomic_add_real(grad + 4 * j + 3, -dv);
    }
}

#ifndef POLY_SOFT
/* The crossing in closed form: a line meets a convex solid on one interval (t_in, t_out),
 * clipped plane by plane; from outside the crossing is t_in, from inside t_out. As the
 * march's: 1 with the root in *tc, 0 if it lies outside [t, t_hi]. */
#define SDF_CROSSES 1
SDF_INLINE int sdf_cross(FIELD_PARAMS, real3 o, real3 d, REAL t, REAL t_hi, REAL s, REAL lip,
                         int *work, REAL *tc) {
    real3 r = poly_r(o), n;
    REAL t_in = (REAL)-1e30, t_out = (REAL)1e30, ia;
    for (int j = 0; j < SDF_PLANES; ++j) {
        REAL dist = poly_v(FIELD_ARGS, j, r, &n, &ia), den = dot(n, d);
        if (den == (REAL)0) {
            if (dist > (REAL)0) t_out = (REAL)-1e30; /* parallel, outside this face */
        } else if (den < (REAL)0) {
            t_in = fmax(t_in, -dist / den);
        } else {
            t_out = fmin(t_out, -dist / den);
        }
    }
    ++*work;
    REAL tx = s > (REAL)0 ? t_in : t_out;
    if (!(t_in < t_out) || tx < t || tx > t_hi) return 0;
    *tc = tx;
    return 1;
}
#endif
#endif

/* Hessian (xx, yy, zz, xy, xz, yz) times v. */
SDF_INLINE real3 hess_mul(const REAL *h, real3 v) {
    return r3(h[0] * v.x + h[3] * v.y + h[4] * v.z, h[3] * v.x + h[1] * v.y + h[5] * v.z,
              h[4] * v.x + h[5] * v.y + h[2] * v.z);
}

/* One Illinois step on the bracket [a, b] of a root (regula falsi that halves the value of a
 * side kept twice): m, with f(m) = fm, replaces b if it lies past the root, else a. */
SDF_INLINE void illinois(REAL m, REAL fm, int past, REAL *a, REAL *b, REAL *fa, REAL *fb,
                         int *side) {
    if (past) {
        *b = m;
        *fb = fm;
        if (*side == 1) *fa *= (REAL)0.5;
        *side = 1;
    } else {
        *a = m;
        *fa = fm;
        if (*side == -1) *fb *= (REAL)0.5;
        *side = -1;
    }
}

#ifndef SDF_CROSSES
/* Where phi, seen from side s (+1 outside, -1 inside), first turns <= 0 along o + t d for t
 * in [t, t_hi]: 1 with the root in *tc, 0 if it does not, -1 past the march cap. */
SDF_INLINE int sdf_cross(FIELD_PARAMS, real3 o, real3 d, REAL t, REAL t_hi, REAL s, REAL lip,
                         int *work, REAL *tc) {
    REAL f = s * sdf_value(FIELD_ARGS, o + t * d);
    for (int k = 0; k < MAX_MARCH; ++k) {
        if (f <= (REAL)0) { /* started on the far side: within MIN_STEP of the last event */
            *tc = t;
            return 1;
        }
        REAL tn = fmin(t + fmax(f / lip, MIN_STEP), t_hi);
        REAL fn = s * sdf_value(FIELD_ARGS, o + tn * d);
        ++*work;
        if (fn <= (REAL)0) {
            REAL a = t, b = tn, fa = f, fb = fn;
            int side = 0;
            for (int it = 0; it < 200 && b - a > TOL; ++it) {
                REAL m = (a * fb - b * fa) / (fb - fa);
                if (!(m > a && m < b)) m = (REAL)0.5 * (a + b);
                REAL fm = s * sdf_value(FIELD_ARGS, o + m * d);
                ++*work;
                illinois(m, fm, fm <= (REAL)0, &a, &b, &fa, &fb, &side);
            }
            *tc = (REAL)0.5 * (a + b);
            return 1;
        }
        if (tn >= t_hi) return 0;
        t = tn;
        f = fn;
    }
    return -1;
}
#endif

/* Distance along d to the box from outside (0 inside), or -1 when the line misses it. */
SDF_INLINE REAL box_entry_distance(__global const REAL *restrict fp, real3 p, real3 d) {
    REAL lo[3] = {BOX_LO_X, BOX_LO_Y, BOX_LO_Z};
    REAL hi[3] = {BOX_HI_X, BOX_HI_Y, BOX_HI_Z};
    REAL pc[3] = {p.x, p.y, p.z}, dc[3] = {d.x, d.y, d.z};
    REAL tn = (REAL)0, tf = (REAL)1e30;
    for (int j = 0; j < 3; j++) {
        if (dc[j] == (REAL)0) {
            if (pc[j] < lo[j] || pc[j] > hi[j]) return (REAL)-1;
            continue;
        }
        REAL t1 = (lo[j] - pc[j]) / dc[j], t2 = (hi[j] - pc[j]) / dc[j];
        tn = fmax(tn, fmin(t1, t2));
        tf = fmin(tf, fmax(t1, t2));
    }
    return tn < tf ? tn : (REAL)-1;
}

/* The index inside the solid (fields/interior.py): with SDF_GRADED, eta(x) = sum_j c_j b_j(u),
 * u = (x - INT_C) INT_INVL, b = (1, u, u_x^2, u_y^2, u_z^2, u_x u_y, u_x u_z, u_y u_z), its
 * INT_N coefficients from the surface's eta on in fd; else the constant SDF_ETA. Rays inside
 * follow x' = v, v' = eta grad eta (|v| = eta) by classic RK4 steps of INT_STEP mm, and the
 * crossing out is solved on the last step's length. The backward pass integrates the ray and
 * its adjoint back from each exit (drift of one segment), Simpson's weights on the stages. */
#ifdef SDF_GRADED
#define INT_N 10
SDF_INLINE real3 int_u(real3 x) { return (x - r3(INT_CX, INT_CY, INT_CZ)) * (REAL)INT_INVL; }

/* eta, grad eta and Hess eta (xx, yy, zz, xy, xz, yz) at x */
SDF_INLINE REAL int_eval(FIELD_PARAMS, real3 x, real3 *g, REAL *hs) {
    const __global REAL *c = &SDF_ETA(fd);
    real3 u = int_u(x);
    const REAL s = (REAL)INT_INVL;
    *g = s * r3(c[1] + (REAL)2 * c[4] * u.x + c[7] * u.y + c[8] * u.z,
                c[2] + (REAL)2 * c[5] * u.y + c[7] * u.x + c[9] * u.z,
                c[3] + (REAL)2 * c[6] * u.z + c[8] * u.x + c[9] * u.y);
    hs[0] = (REAL)2 * s * s * c[4];
    hs[1] = (REAL)2 * s * s * c[5];
    hs[2] = (REAL)2 * s * s * c[6];
    hs[3] = s * s * c[7];
    hs[4] = s * s * c[8];
    hs[5] = s * s * c[9];
    return c[0] + c[1] * u.x + c[2] * u.y + c[3] * u.z + c[4] * u.x * u.x + c[5] * u.y * u.y +
           c[6] * u.z * u.z + c[7] * u.x * u.y + c[8] * u.x * u.z + c[9] * u.y * u.z;
}

/* acc_j += w b_j(x) */
SDF_INLINE void int_basis_add(real3 x, REAL w, REAL *acc) {
    real3 u = int_u(x);
    acc[0] += w;
    acc[1] += w * u.x;
    acc[2] += w * u.y;
    acc[3] += w * u.z;
    acc[4] += w * u.x * u.x;
    acc[5] += w * u.y * u.y;
    acc[6] += w * u.z * u.z;
    acc[7] += w * u.x * u.y;
    acc[8] += w * u.x * u.z;
    acc[9] += w * u.y * u.z;
}

SDF_INLINE real3 int_D(FIELD_PARAMS, real3 x) {
    real3 g;
    REAL hs[6];
    REAL e = int_eval(FIELD_ARGS, x, &g, hs);
    return e * g;
}

/* One RK4 step of length h (in sigma, ds = eta dsigma) of (x, v). */
SDF_INLINE void int_step(FIELD_PARAMS, REAL h, real3 *x, real3 *v) {
    const REAL h2 = (REAL)0.5 * h;
    real3 a1 = *v, b1 = int_D(FIELD_ARGS, *x);
    real3 a2 = *v + h2 * b1, b2 = int_D(FIELD_ARGS, *x + h2 * a1);
    real3 a3 = *v + h2 * b2, b3 = int_D(FIELD_ARGS, *x + h2 * a2);
    real3 a4 = *v + h * b3, b4 = int_D(FIELD_ARGS, *x + h * a3);
    *x += h / (REAL)6 * (a1 + (REAL)2 * (a2 + a3) + a4);
    *v += h / (REAL)6 * (b1 + (REAL)2 * (b2 + b3) + b4);
}

SDF_INLINE REAL int_h(FIELD_PARAMS) { return (REAL)INT_STEP / fmax(SDF_ETA(fd), (REAL)1); }

/* From (x, v) inside the solid, steps until phi turns > 0: 1 with the crossing's state in
 * (*x, *v), the whole steps in *nst and the last step's length in *tau; -1 past the cap. */
SDF_INLINE int int_cross(FIELD_PARAMS, real3 *x, real3 *v, int *nst, REAL *tau, int *work) {
    const REAL h = int_h(FIELD_ARGS);
    REAL f = sdf_value(FIELD_ARGS, *x);
    for (int k = 0; k < MAX_MARCH; ++k) {
        if (f > (REAL)0) { /* on the surface already: a grazing entry */
            *nst = k;
            *tau = 0;
            return 1;
        }
        real3 xn = *x, vn = *v;
        int_step(FIELD_ARGS, h, &xn, &vn);
        REAL fn = sdf_value(FIELD_ARGS, xn);
        ++*work;
        if (fn > (REAL)0) {
            REAL a = 0, b = h, fa = f, fb = fn;
            int side = 0;
            for (int it = 0; it < 200 && (b - a) * SDF_ETA(fd) > TOL; ++it) {
                REAL m = (a * fb - b * fa) / (fb - fa);
                if (!(m > a && m < b)) m = (REAL)0.5 * (a + b);
                real3 xm = *x, vm = *v;
                int_step(FIELD_ARGS, m, &xm, &vm);
                REAL fm = sdf_value(FIELD_ARGS, xm);
                ++*work;
                illinois(m, fm, fm > (REAL)0, &a, &b, &fa, &fb, &side);
            }
            *tau = b; /* the outside end: the next march starts across the surface */
            int_step(FIELD_ARGS, b, x, v);
            *nst = k;
            return 1;
        }
        *x = xn;
        *v = vn;
        f = fn;
    }
    return -1;
}

/* The backward stage: (x, v, ax, av)' in s = -sigma, and acc += w av . dD/dc. */
SDF_INLINE void int_back_rate(FIELD_PARAMS, real3 x, real3 v, real3 ax, real3 av, real3 *dx,
                              real3 *dv, real3 *dax, real3 *dav, REAL w, REAL *acc) {
    real3 g;
    REAL hs[6];
    REAL e = int_eval(FIELD_ARGS, x, &g, hs);
    REAL ga = dot(g, av);
    *dx = -v;
    *dv = -e * g;
    *dax = ga * g + e * hess_mul(hs, av); /* H_D av, D = eta grad eta */
    *dav = ax;
    /* dD/dc_j . av = b_j (grad eta . av) + eta grad b_j . av */
    real3 u = int_u(x), q = w * e * (REAL)INT_INVL * av;
    int_basis_add(x, w * ga, acc);
    acc[1] += q.x;
    acc[2] += q.y;
    acc[3] += q.z;
    acc[4] += (REAL)2 * u.x * q.x;
    acc[5] += (REAL)2 * u.y * q.y;
    acc[6] += (REAL)2 * u.z * q.z;
    acc[7] += u.y * q.x + u.x * q.y;
    acc[8] += u.z * q.x + u.x * q.z;
    acc[9] += u.z * q.y + u.y * q.z;
}

/* One RK4 step of length h > 0 backwards (in s) of the ray and its adjoint. */
SDF_INLINE void int_back_step(FIELD_PARAMS, REAL h, real3 *x, real3 *v, real3 *ax, real3 *av,
                              REAL *acc) {
    const REAL h2 = (REAL)0.5 * h, w1 = h / (REAL)6, w2 = h / (REAL)3;
    real3 x1, v1, a1, b1, x2, v2, a2, b2, x3, v3, a3, b3, x4, v4, a4, b4;
    int_back_rate(FIELD_ARGS, *x, *v, *ax, *av, &x1, &v1, &a1, &b1, w1, acc);
    int_back_rate(FIELD_ARGS, *x + h2 * x1, *v + h2 * v1, *ax + h2 * a1, *av + h2 * b1, &x2, &v2,
                  &a2, &b2, w2, acc);
    int_back_rate(FIELD_ARGS, *x + h2 * x2, *v + h2 * v2, *ax + h2 * a2, *av + h2 * b2, &x3, &v3,
                  &a3, &b3, w2, acc);
    int_back_rate(FIELD_ARGS, *x + h * x3, *v + h * v3, *ax + h * a3, *av + h * b3, &x4, &v4, &a4,
                  &b4, w1, acc);
    *x += h / (REAL)6 * (x1 + (REAL)2 * (x2 + x3) + x4);
    *v += h / (REAL)6 * (v1 + (REAL)2 * (v2 + v3) + v4);
    *ax += h / (REAL)6 * (a1 + (REAL)2 * (a2 + a3) + a4);
    *av += h / (REAL)6 * (b1 + (REAL)2 * (b2 + b3) + b4);
}
#else
#define INT_N 1
SDF_INLINE REAL int_eval(FIELD_PARAMS, real3 x, real3 *g, REAL *hs) {
    *g = r3(0, 0, 0);
    return SDF_ETA(fd);
}
SDF_INLINE void int_basis_add(real3 x, REAL w, REAL *acc) { acc[0] += w; }
#endif

/* One ray from o along unit d: its status, exit point and direction, event count and march
 * work; the events (point, incoming and outgoing direction, inside before it, and with
 * SDF_GRADED the steps and last step of the curved segment that ends there) into ex..et. */
SDF_INLINE int sdf_path(FIELD_PARAMS, REAL lip, real3 o, real3 d, real3 *pos, real3 *dir,
                        int *nev, int *work, real3 *ex, real3 *ed, real3 *eo, int *ein, int *en,
                        REAL *et) {
    *nev = 0;
    *pos = o;
    *dir = d;
    REAL t0 = box_entry_distance(fp, o, d);
    if (t0 < (REAL)0) return ST_MISSED;
    real3 p = o + t0 * d;
    int inside = 0, ev = 0;
    REAL start = 0;
    if (sdf_value(FIELD_ARGS, p) <= (REAL)0) return ST_TRAPPED; /* the solid reaches the box wall */
    for (;;) {
        *nev = ev;
        real3 x;
        int nst = 0;
        REAL tau = 0;
#ifdef SDF_GRADED
        if (inside) {
            real3 g;
            REAL hs[6];
            real3 v = int_eval(FIELD_ARGS, p, &g, hs) * d;
            if (int_cross(FIELD_ARGS, &p, &v, &nst, &tau, work) < 0) return ST_TRAPPED;
            x = p;
            d = unit3(v);
        } else
#endif
        {
            REAL t_hi = box_exit_distance(fp, p, d), tc;
            int h = sdf_cross(FIELD_ARGS, p, d, start, t_hi, inside ? (REAL)-1 : (REAL)1, lip,
                              work, &tc);
            if (h < 0) return ST_TRAPPED;
            if (h == 0) {
                *dir = d;
                *pos = p + t_hi * d;
                return inside ? ST_NONFINITE : ST_EXITED;
            }
            x = p + tc * d;
        }
        if (ev >= MAX_EVENTS) return ST_TRAPPED;
        real3 g, gi;
        REAL hs[6];
        sdf_eval(FIELD_ARGS, x, &g, hs);
        real3 nrm = unit3(g);
        REAL eta = int_eval(FIELD_ARGS, x, &gi, hs);
        if (!(eta > (REAL)0)) return ST_NONFINITE;
        real3 dn = refract_or_reflect(d, nrm, inside, eta);
        if (!finite3(x) || !finite3(dn)) return ST_NONFINITE;
        ex[ev] = x;
        ed[ev] = d;
        eo[ev] = dn;
        ein[ev] = inside;
        en[ev] = nst;
        et[ev] = tau;
        ++ev;
        inside = dot(dn, nrm) < (REAL)0;
        start = OFFSET / fmax(fabs(dot(dn, nrm)), (REAL)1e-3);
        p = x;
#ifdef SDF_GRADED
        if (inside) p = x + start * dn; /* the march starts off the surface, inside */
#endif
        d = dn;
    }
}

#define SDF_EVENTS                                                                             \
    real3 ex[MAX_EVENTS], ed[MAX_EVENTS], eo[MAX_EVENTS], pos, dir;                           \
    int ein[MAX_EVENTS], en[MAX_EVENTS], nev, w = 0;                                           \
    REAL et[MAX_EVENTS];

__kernel void interface_trace(FIELD_PARAMS, const REAL lip, const int n,
                              __global const REAL *ox, __global const REAL *oy,
                              __global const REAL *oz, __global const REAL *dx,
                              __global const REAL *dy, __global const REAL *dz,
                              __global REAL *px, __global REAL *py, __global REAL *pz,
                              __global REAL *vx, __global REAL *vy, __global REAL *vz,
                              __global int *status, __global int *events,
                              __global int *work) {
    const int i = get_global_id(0);
    if (i >= n) return;
    SDF_EVENTS
    real3 o = r3(ox[i], oy[i], oz[i]), d = unit3(r3(dx[i], dy[i], dz[i]));
    int st = sdf_path(FIELD_ARGS, lip, o, d, &pos, &dir, &nev, &w, ex, ed, eo, ein, en, et);
    px[i] = pos.x;
    py[i] = pos.y;
    pz[i] = pos.z;
    vx[i] = dir.x;
    vy[i] = dir.y;
    vz[i] = dir.z;
    status[i] = st;
    events[i] = nev;
    work[i] = w;
}

/* The adjoint of one ray's exit direction (mu = dJ/d dir) back to phi's parameters (grad,
 * atomic adds), the index's INT_N coefficients (geta[i * INT_N + j]) and the ray's origin
 * (gorig[3 i + k], dJ/do: a camera centre's share). */
__kernel void interface_adjoint(FIELD_PARAMS, const REAL lip, const int n,
                                __global const REAL *ox, __global const REAL *oy,
                                __global const REAL *oz, __global const REAL *dx,
                                __global const REAL *dy, __global const REAL *dz,
                                __global const REAL *mux, __global const REAL *muy,
                                __global const REAL *muz, __global REAL *grad,
                                __global REAL *geta, __global REAL *gorig) {
    const int i = get_global_id(0);
    if (i >= n) return;
    SDF_EVENTS
    real3 o = r3(ox[i], oy[i], oz[i]), d0 = unit3(r3(dx[i], dy[i], dz[i]));
    int st = sdf_path(FIELD_ARGS, lip, o, d0, &pos, &dir, &nev, &w, ex, ed, eo, ein, en, et);
    REAL acc[INT_N];
    for (int j = 0; j < INT_N; ++j) acc[j] = 0;
    real3 ad = r3(mux[i], muy[i], muz[i]), ax = r3(0, 0, 0);
    if (st != ST_EXITED) nev = 0;
#ifdef ADJ_MIN_COS /* grazing rays carry no gradient (interface.py, GRAZING_COS) */
    for (int k = 0; k < nev; ++k) {
        real3 g;
        REAL hs[6];
        sdf_eval(FIELD_ARGS, ex[k], &g, hs);
        if (fabs(dot(g, ed[k])) < (REAL)ADJ_MIN_COS * sqrt(dot(g, g))) nev = 0;
    }
#endif
    for (int k = nev - 1; k >= 0; --k) {
        real3 x = ex[k], d = ed[k], g, gi;
        REAL hs[6], hi[6];
        sdf_eval(FIELD_ARGS, x, &g, hs);
        const REAL eta = int_eval(FIELD_ARGS, x, &gi, hi);
        REAL gn = sqrt(dot(g, g));
        real3 nrm = g / gn;
        REAL sg = dot(d, nrm) < (REAL)0 ? (REAL)1 : (REAL)-1;
        real3 m = sg * nrm;
        REAL c = -dot(d, m);
        REAL r = ein[k] ? eta : (REAL)1 / eta;
        REAL k2 = (REAL)1 - r * r * ((REAL)1 - c * c);
        real3 a = ad, a_d, a_m;
        REAL a_c, a_eta = 0;
        if (k2 < (REAL)0) { /* reflection: d' = d + 2 c m */
            a_d = a;
            a_m = (REAL)2 * c * a;
            a_c = (REAL)2 * dot(a, m);
        } else { /* refraction: d' = r d + (r c - sqrt(k2)) m */
            REAL sk = sqrt(k2), s1 = dot(a, m);
            a_d = r * a;
            a_m = (r * c - sk) * a;
            REAL a_k = -s1 / ((REAL)2 * sk);
            REAL a_r = dot(a, d) + s1 * c - a_k * (REAL)2 * r * ((REAL)1 - c * c);
            a_c = s1 * r + a_k * (REAL)2 * r * r * c;
            a_eta = a_r * (ein[k] ? (REAL)1 : (REAL)-1 / (eta * eta));
        }
        int_basis_add(x, a_eta, acc); /* the index at the hit point */
        a_d -= a_c * m;               /* c = -d . m */
        a_m -= a_c * d;
        real3 a_n = sg * a_m;
        real3 a_g = (a_n - nrm * dot(nrm, a_n)) / gn; /* n = g / |g| */
        real3 a_x = ax + hess_mul(hs, a_g) + a_eta * gi; /* g = grad phi(x), eta(x) */
#ifdef SDF_GRADED
        if (ein[k]) {
            /* x = X(s*) on phi = 0 along the curved ray, d = V / |V|, V = eta(x) d:
             * the crossing's s* moves with X and phi, s*' = -(g . dX + dphi) / (g . V) */
            real3 v = eta * d, dd = eta * gi;
            real3 a_v = (a_d - d * dot(d, a_d)) / eta;
            REAL q = (dot(a_x, v) + dot(a_v, dd)) / dot(g, v);
            sdf_splat(FIELD_ARGS, grad, x, -q, a_g);
            real3 bx = a_x - q * g, bv = a_v;
            const REAL h = int_h(FIELD_ARGS);
            int_back_step(FIELD_ARGS, et[k], &x, &v, &bx, &bv, acc);
            for (int s = 0; s < en[k]; ++s) int_back_step(FIELD_ARGS, h, &x, &v, &bx, &bv, acc);
            /* the segment began at event k - 1 with V = eta(x') d', its outgoing direction */
            real3 xp = ex[k - 1], dp = eo[k - 1], gp;
            REAL ep = int_eval(FIELD_ARGS, xp, &gp, hi);
            REAL a_ep = dot(bv, dp);
            int_basis_add(xp, a_ep, acc);
            ad = ep * bv;
            ax = bx + a_ep * gp;
            continue;
        }
#endif
        /* x = p + t d on phi(x) = 0: dx = P (dp + t dd) - d dphi / (g . d) */
        REAL s2 = dot(d, a_x) / dot(g, d);
        real3 a_p = a_x - s2 * g;
        REAL t = k > 0 ? dot(x - ex[k - 1], d) : (REAL)0;
        sdf_splat(FIELD_ARGS, grad, x, -s2, a_g);
        ad = a_d + t * a_p;
        ax = a_p;
    }
    for (int j = 0; j < INT_N; ++j) geta[i * INT_N + j] = acc[j];
    /* the first segment is straight in air: its start moves the line, not the direction */
    gorig[3 * i] = ax.x;
    gorig[3 * i + 1] = ax.y;
    gorig[3 * i + 2] = ax.z;
}

/* phi and its gradient at points (the device check against the NumPy reference). */
__kernel void interface_eval(FIELD_PARAMS, const int n,
                             __global const REAL *x, __global const REAL *y,
                             __global const REAL *z, __global REAL *phi, __global REAL *gx,
                             __global REAL *gy, __global REAL *gz) {
    const int i = get_global_id(0);
    if (i >= n) return;
    real3 g;
    REAL hs[6];
    phi[i] = sdf_eval(FIELD_ARGS, r3(x[i], y[i], z[i]), &g, hs);
    gx[i] = g.x;
    gy[i] = g.y;
    gz[i] = g.z;
}
