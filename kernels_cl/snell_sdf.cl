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
 * Build defines: one SHAPE_* (SHAPE_RANDOM also NPRIM), GEO_AT. Parameters sp
 * (SdfSolid.kernel_params): sp[0..2] centre, sp[3..11] world -> local rotation (row-major),
 * sp[12] eta, sp[13] Lipschitz bound L, sp[14] bounding radius Rb about the centre, sp[15..]
 * the shape's own parameters (q below), then from sp[GEO_AT] the box (common.h). Work is in
 * the local frame.
 */

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

inline REAL rounded_box(real3 p, REAL b, REAL r) {
    real3 q = fabs(p) - b;
    real3 qp = fmax(q, (REAL)0);
    return length(qp) + fmin(fmax(q.x, fmax(q.y, q.z)), (REAL)0) - r;
}

inline REAL smin(REAL a, REAL b, REAL k) {
    REAL h = fmax(k - fabs(a - b), (REAL)0) / k;
    return fmin(a, b) - (REAL)0.25 * k * h * h;
}

/* The signed distance at local point p; q = sp + 15. */
inline REAL shape_sdf(__global const REAL *q, real3 p) {
#if defined(SHAPE_SDF_SPHERE)
    return length(p) - q[0];
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
    return fmin(length(ps) - q[1], rounded_box(pb, q[3], q[4]));
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
        REAL di = length(pa - t * ba) - c[6];
        d = i == 0 ? di : smin(d, di, q[0]);
    }
    return d;
#elif defined(SHAPE_FACETED)
    /* q: NPRIM faces (unit normal, offset): the largest n . p - d */
    REAL d = (REAL)-1e30;
    for (int i = 0; i < NPRIM; i++) {
        __global const REAL *c = q + 4 * i;
        d = fmax(d, c[0] * p.x + c[1] * p.y + c[2] * p.z - c[3]);
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

inline int hit_solid(__global const REAL *sp, real3 o, real3 d, int inside, REAL *t, real3 *n) {
    return hit_sdf(sp, o, d, inside, t, n);
}
inline REAL solid_size(__global const REAL *sp) { return sp[14]; }
inline REAL solid_eta(__global const REAL *sp) { return sp[12]; }
