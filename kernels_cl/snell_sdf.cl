/* Exact Snell refraction through a solid bounded by the zero set of a signed distance
 * (the family shapes of clrefract/family.py, whose NumPy SDFs these mirror: keep in step).
 *
 * Rays are straight between surface events. Along each segment the crossing is bracketed by
 * sphere tracing (steps |f| / L, safe for an L-Lipschitz f, never below a small floor so that
 * grazing rays progress) and then bisected to TOL_REL of the object's size; the normal is the
 * central-difference gradient of f. At each event the ray refracts by Snell's law or, past the
 * critical angle, reflects; no Fresnel split, no absorption. One ray per work-item, scalar
 * REAL: the marching loop is data dependent and does not vectorise.
 *
 * Build defines: one SHAPE_* (SHAPE_RANDOM also NPRIM), the box BOX_LO_X .. BOX_HI_Z.
 * Parameters sp (SdfSolid.kernel_params): sp[0..2] centre, sp[3..11] world -> local rotation
 * (row-major), sp[12] eta, sp[13] Lipschitz bound L, sp[14] bounding radius Rb about the
 * centre, sp[15..] the shape's own parameters (q below). Work is in the local frame.
 */

typedef CAT(REAL, 3) real3;

#ifdef REAL_IS_DOUBLE
#define OFFSET_REL 1e-9   /* origin offset off the surface after an event, times Rb */
#define TOL_REL 1e-12     /* bisection tolerance on the ray parameter, times Rb */
#define MIN_STEP_REL 1e-5 /* smallest marching step, times Rb */
#define GRAD_REL 1e-6     /* central-difference step of the normal, times Rb (family.py) */
#else
#define OFFSET_REL 1e-5f
#define TOL_REL 1e-6f
#define MIN_STEP_REL 1e-4f
#define GRAD_REL 1e-3f
#endif
#define CLIP_REL 1.01     /* radius of the marching sphere, times Rb (snell_sdf.py) */
#define MAX_MARCH 20000
#define MAX_BISECT 200

inline real3 r3(REAL x, REAL y, REAL z) {
    real3 v;
    v.x = x;
    v.y = y;
    v.z = z;
    return v;
}

inline real3 unit3(real3 v) { return v / sqrt(dot(v, v)); }

inline REAL norm3(real3 v) { return sqrt(dot(v, v)); }

inline REAL rounded_box(real3 p, REAL b, REAL r) {
    real3 q = fabs(p) - b;
    real3 qp = fmax(q, (REAL)0);
    return norm3(qp) + fmin(fmax(q.x, fmax(q.y, q.z)), (REAL)0) - r;
}

inline REAL smin(REAL a, REAL b, REAL k) {
    REAL h = fmax(k - fabs(a - b), (REAL)0) / k;
    return fmin(a, b) - (REAL)0.25 * k * h * h;
}

/* The signed distance at local point p; q = sp + 15. */
inline REAL shape_sdf(__global const REAL *q, real3 p) {
#if defined(SHAPE_SDF_SPHERE)
    return norm3(p) - q[0];
#elif defined(SHAPE_ROUNDED_CUBE)
    return rounded_box(p, q[0], q[1]);
#elif defined(SHAPE_CYLINDER)
    REAL dr = hypot(p.x, p.y) - q[0], dz = fabs(p.z) - q[1];
    return fmin(fmax(dr, dz), (REAL)0) + hypot(fmax(dr, (REAL)0), fmax(dz, (REAL)0)) - q[2];
#elif defined(SHAPE_BOWL)
    /* q: mid-wall radius r, half thickness t, cut height h, rim radius w */
    REAL rho = hypot(p.x, p.y);
    REAL d = (q[2] * rho < q[3] * p.z) ? hypot(rho - q[3], p.z - q[2])
                                        : fabs(hypot(rho, p.z) - q[0]);
    return d - q[1];
#elif defined(SHAPE_TWO_BODIES)
    /* q: ball x, ball radius, box x, box inner half size, box rounding */
    real3 ps = p, pb = p;
    ps.x -= q[0];
    pb.x -= q[2];
    return fmin(norm3(ps) - q[1], rounded_box(pb, q[3], q[4]));
#elif defined(SHAPE_VASE)
    /* q: half height, waist radius, waist z, k of r(z) = waist + k (z - waist_z)^2 */
    REAL u = p.z - q[2];
    REAL rp = (REAL)2 * q[3] * u;
    REAL side = (hypot(p.x, p.y) - (q[1] + q[3] * u * u)) / sqrt((REAL)1 + rp * rp);
    return fmax(side, fabs(p.z) - q[0]);
#elif defined(SHAPE_RANDOM)
    /* q: blend k, then NPRIM capsules (a, b, radius) */
    REAL d = (REAL)0;
    for (int i = 0; i < NPRIM; i++) {
        __global const REAL *c = q + 1 + 7 * i;
        real3 a = r3(c[0], c[1], c[2]);
        real3 ba = r3(c[3], c[4], c[5]) - a, pa = p - a;
        REAL t = clamp(dot(pa, ba) / fmax(dot(ba, ba), (REAL)1e-30), (REAL)0, (REAL)1);
        REAL di = norm3(pa - t * ba) - c[6];
        d = i == 0 ? di : smin(d, di, q[0]);
    }
    return d;
#else
#error "snell_sdf.cl needs one SHAPE_* define"
#endif
}

inline real3 sdf_normal(__global const REAL *q, real3 p, REAL h) {
    real3 ex = r3(h, (REAL)0, (REAL)0), ey = r3((REAL)0, h, (REAL)0), ez = r3((REAL)0, (REAL)0, h);
    real3 g = r3(shape_sdf(q, p + ex) - shape_sdf(q, p - ex),
                 shape_sdf(q, p + ey) - shape_sdf(q, p - ey),
                 shape_sdf(q, p + ez) - shape_sdf(q, p - ez));
    return unit3(g);
}

/* First crossing of the surface along o + t d (t >= 0) inside the bounding sphere, from the
 * side `inside` says. Returns 1 (t, n set), 0 (none), -1 (marching cap: lost). */
inline int hit_sdf(__global const REAL *sp, real3 o, real3 d, int inside, REAL *t, real3 *n) {
    __global const REAL *q = sp + 15;
    const REAL L = sp[13], rb = sp[14];
    /* clip to a sphere a little larger than the bound, so that a surface touching the bound
     * (a ball) is crossed before the segment ends */
    const REAL rc = CLIP_REL * rb;
    REAL b = dot(o, d), c = dot(o, o) - rc * rc;
    REAL disc = b * b - c;
    if (disc <= (REAL)0) return 0;
    REAL sq = sqrt(disc);
    REAL t0 = fmax(-b - sq, (REAL)0), t1 = -b + sq;
    if (t1 <= t0) return 0;
    const REAL dmin = MIN_STEP_REL * rb, tol = TOL_REL * rb;
    REAL lo = t0, hi = t0;
    REAL f = shape_sdf(q, o + t0 * d);
    int found = inside ? (f > (REAL)0) : (f < (REAL)0);
    for (int k = 0; !found; k++) {
        if (lo >= t1) return 0;
        if (k >= MAX_MARCH) return -1;
        /* |f| / L is a safe step: no crossing can lie closer */
        hi = fmin(lo + fmax(fabs(f) / L, dmin), t1);
        REAL fh = shape_sdf(q, o + hi * d);
        found = inside ? (fh > (REAL)0) : (fh < (REAL)0);
        if (!found) {
            lo = hi;
            f = fh;
        }
    }
    for (int it = 0; it < MAX_BISECT && hi - lo > tol; it++) {
        REAL mid = (REAL)0.5 * (lo + hi);
        REAL fm = shape_sdf(q, o + mid * d);
        if (inside ? (fm > (REAL)0) : (fm < (REAL)0)) hi = mid;
        else lo = mid;
    }
    *t = (REAL)0.5 * (lo + hi);
    *n = sdf_normal(q, o + *t * d, GRAD_REL * rb);
    return 1;
}

/* As in snell.cl: Snell refraction with relative index eta_i / eta_t, or mirror reflection
 * past the critical angle; n the outward normal, inside the medium of the incoming ray. */
inline real3 refract_or_reflect(real3 d, real3 n, int inside, REAL eta) {
    REAL cd = dot(d, n);
    real3 m = cd < (REAL)0 ? n : -n;
    REAL ci = fabs(cd);
    REAL r = inside ? eta : (REAL)1 / eta;
    REAL k = (REAL)1 - r * r * ((REAL)1 - ci * ci);
    if (k < (REAL)0) return unit3(d + (REAL)2 * ci * m);
    return unit3(r * d + (r * ci - sqrt(k)) * m);
}

inline int finite3(real3 v) { return isfinite(v.x) && isfinite(v.y) && isfinite(v.z); }

inline REAL box_exit_distance(real3 p, real3 d) {
    REAL lo[3] = {(REAL)BOX_LO_X, (REAL)BOX_LO_Y, (REAL)BOX_LO_Z};
    REAL hi[3] = {(REAL)BOX_HI_X, (REAL)BOX_HI_Y, (REAL)BOX_HI_Z};
    REAL pc[3] = {p.x, p.y, p.z}, dc[3] = {d.x, d.y, d.z};
    REAL t = (REAL)1e30;
    for (int j = 0; j < 3; j++) {
        if (dc[j] > (REAL)0) t = fmin(t, (hi[j] - pc[j]) / dc[j]);
        else if (dc[j] < (REAL)0) t = fmin(t, (lo[j] - pc[j]) / dc[j]);
    }
    return fmax(t, (REAL)0);
}

/* Outputs and status codes as snell_trace (snell.cl): ST_EXITED, ST_MISSED, ST_TRAPPED (event
 * cap reached with another event due), ST_NONFINITE (non-finite state, no way out found from
 * inside, or the marching cap). */
__kernel void snell_sdf_trace(__global const REAL *restrict sp, const int max_events,
                              const int n, __global const REAL *ox, __global const REAL *oy,
                              __global const REAL *oz, __global const REAL *dx,
                              __global const REAL *dy, __global const REAL *dz,
                              __global REAL *px, __global REAL *py, __global REAL *pz,
                              __global REAL *vx, __global REAL *vy, __global REAL *vz,
                              __global REAL *sx, __global REAL *sy, __global REAL *sz,
                              __global int *status, __global int *events) {
    const int i = get_global_id(0);
    if (i >= n) return;
    const real3 c = r3(sp[0], sp[1], sp[2]);
    const real3 m0 = r3(sp[3], sp[4], sp[5]), m1 = r3(sp[6], sp[7], sp[8]),
                m2 = r3(sp[9], sp[10], sp[11]);
    const REAL eta = sp[12];
    const REAL eps = OFFSET_REL * sp[14];

    const real3 ow = r3(ox[i], oy[i], oz[i]);
    const real3 dw = unit3(r3(dx[i], dy[i], dz[i]));
    real3 rel = ow - c;
    real3 o = r3(dot(m0, rel), dot(m1, rel), dot(m2, rel));
    real3 d = r3(dot(m0, dw), dot(m1, dw), dot(m2, dw));
    real3 surf = o;
    int inside = 0, ev = 0, st;
    for (;;) {
        REAL t;
        real3 nrm;
        int h = hit_sdf(sp, o, d, inside, &t, &nrm);
        if (h < 0) {
            st = ST_NONFINITE;
            break;
        }
        if (h == 0) {
            st = inside ? ST_NONFINITE : (ev == 0 ? ST_MISSED : ST_EXITED);
            break;
        }
        if (ev >= max_events) {
            st = ST_TRAPPED;
            break;
        }
        real3 p = o + t * d;
        real3 dn = refract_or_reflect(d, nrm, inside, eta);
        if (!finite3(p) || !finite3(dn) || !finite3(nrm)) {
            st = ST_NONFINITE;
            break;
        }
        REAL cn = dot(dn, nrm);
        inside = cn < (REAL)0;
        /* a distance eps off the surface on the new side, at most 1000 eps along the ray */
        o = p + (eps / fmax(fabs(cn), (REAL)1e-3)) * dn;
        surf = p;
        d = dn;
        ev++;
    }
    real3 dwo = d.x * m0 + d.y * m1 + d.z * m2;
    real3 sw = c + surf.x * m0 + surf.y * m1 + surf.z * m2;
    real3 pos = sw;
    if (st == ST_MISSED) {
        dwo = dw;
        sw = pos = ow;
    } else if (st == ST_EXITED) {
        pos = sw + box_exit_distance(sw, dwo) * dwo;
    }
    px[i] = pos.x;
    py[i] = pos.y;
    pz[i] = pos.z;
    vx[i] = dwo.x;
    vy[i] = dwo.y;
    vz[i] = dwo.z;
    sx[i] = sw.x;
    sy[i] = sw.y;
    sz[i] = sw.z;
    status[i] = st;
    events[i] = ev;
}
