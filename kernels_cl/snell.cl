/* Ground truth for the solid objects: exact Snell refraction at analytic surfaces.
 *
 * Rays are straight lines between surface events. At each event the ray refracts by Snell's
 * law or, past the critical angle, reflects (total internal reflection); no Fresnel split.
 * This kernel never touches the eikonal tracer. One ray per work-item, scalar REAL: the event
 * loop has data-dependent branches (root isolation, bisection) that do not vectorise.
 *
 * Build defines: exactly one of SOLID_SPHERE, SOLID_PRISM, SOLID_DROP, and GEO_AT. Parameters
 * sp (layout of clrefract/snell.py):
 *   sp[0..2]  centre           sp[3..11] world -> local rotation, row-major
 *   sp[12] a  sp[13] b         sp[14] eta      sp[15..] the box (common.h, GEO_AT 15)
 *   sphere: a = radius;  prism: a = side, b = length;  drop: a = R, b = H.
 * Everything below works in the solid's local frame: l = M (x - centre).
 */

#ifdef REAL_IS_DOUBLE
#define OFFSET_REL 1e-9  /* origin offset off the surface after an event, times the size */
#define TOL_REL 1e-12    /* bisection tolerance on the ray parameter, times the size */
#else
#define OFFSET_REL 1e-5f
#define TOL_REL 1e-6f
#endif
#define MAX_BISECT 100
#define BIG ((REAL)1e30)

/* ---------------------------------------------------------------- sphere (centre 0) */
inline int hit_sphere(real3 o, real3 d, int inside, REAL R, REAL *t, real3 *n) {
    REAL b = dot(o, d);
    real3 l = o - b * d;                 /* foot of the perpendicular from the centre */
    REAL disc = R * R - dot(l, l);       /* robust form (no b^2 - c cancellation) */
    REAL c = dot(o, o) - R * R;
    REAL tt;
    if (!inside) {
        if (b >= (REAL)0 || disc <= (REAL)0) return 0;
        tt = fmax(c / (-b + sqrt(disc)), (REAL)0);
    } else {
        REAL sq = sqrt(fmax(disc, (REAL)0));
        tt = (b <= (REAL)0) ? -b + sq : -c / (b + sq);
        tt = fmax(tt, (REAL)0);
    }
    *t = tt;
    *n = unit3(o + tt * d);
    return 1;
}

/* ------------------------------------------------- prism: convex polyhedron of 5 planes */
inline int hit_prism(real3 o, real3 d, int inside, REAL side, REAL len, REAL *t, real3 *n) {
    const REAL s3 = (REAL)0.86602540378443864676;
    const REAL hs = side / ((REAL)2 * sqrt((REAL)3)), hl = (REAL)0.5 * len;
    const REAL nx[5] = {(REAL)0, -s3, s3, (REAL)0, (REAL)0};
    const REAL ny[5] = {(REAL)1, (REAL)-0.5, (REAL)-0.5, (REAL)0, (REAL)0};
    const REAL nz[5] = {(REAL)0, (REAL)0, (REAL)0, (REAL)1, (REAL)-1};
    const REAL hh[5] = {hs, hs, hs, hl, hl};
    int k = -1;
    if (inside) { /* nearest plane the ray leaves through */
        REAL tmin = BIG;
        for (int j = 0; j < 5; j++) {
            REAL dn = nx[j] * d.x + ny[j] * d.y + nz[j] * d.z;
            if (dn > (REAL)0) {
                REAL tj = (hh[j] - (nx[j] * o.x + ny[j] * o.y + nz[j] * o.z)) / dn;
                if (tj < tmin) {
                    tmin = tj;
                    k = j;
                }
            }
        }
        if (k < 0) return 0;
        *t = fmax(tmin, (REAL)0);
    } else { /* slab (Kay-Kajiya) clipping against the 5 half-spaces */
        REAL tn = -BIG, tf = BIG;
        for (int j = 0; j < 5; j++) {
            REAL dn = nx[j] * d.x + ny[j] * d.y + nz[j] * d.z;
            REAL num = hh[j] - (nx[j] * o.x + ny[j] * o.y + nz[j] * o.z);
            if (dn < (REAL)0) {
                REAL tj = num / dn;
                if (tj > tn) {
                    tn = tj;
                    k = j;
                }
            } else if (dn > (REAL)0) {
                tf = fmin(tf, num / dn);
            } else if (num < (REAL)0) {
                return 0; /* parallel to the plane, on its outer side */
            }
        }
        if (k < 0 || tn <= (REAL)0 || tn >= tf) return 0;
        *t = tn;
    }
    *n = r3(nx[k], ny[k], nz[k]);
    return 1;
}

/* ------------------------------------------------------------- drop (body of revolution)
 * Inside function F = A u w^3 - x^2 - y^2 with u = 1 + z/H, w = 1 - z/H, A = R^2/4: the
 * square of r(t) = (R/2) sin t (1 - cos t) at cos t = z/H, minus rho^2. F > 0 exactly inside
 * (it is negative for |z| > H). Along a ray F is a quartic in the parameter: its inflection
 * points (a quadratic) split the segment into pieces where F' is monotone, bisection on F'
 * gives the critical points, and F is monotone between them, so the first crossing is
 * bracketed exactly and found by bisection -- no step size, no missed thin features. */
inline REAL drop_F(real3 p, REAL A, REAL H) {
    REAL u = (H + p.z) / H, w = (H - p.z) / H;
    return A * u * w * w * w - p.x * p.x - p.y * p.y;
}

inline REAL poly_d1(const REAL *a, REAL s) {
    return a[1] + s * ((REAL)2 * a[2] + s * ((REAL)3 * a[3] + s * (REAL)4 * a[4]));
}

/* Real roots of qa s^2 + qb s + qc in (lo, hi), ascending; returns how many (0..2). */
inline int quad_roots_in(REAL qa, REAL qb, REAL qc, REAL lo, REAL hi, REAL *r) {
    REAL x0, x1;
    int m = 0;
    if (qa == (REAL)0) {
        if (qb == (REAL)0) return 0;
        x0 = x1 = -qc / qb;
        m = 1;
    } else {
        REAL disc = qb * qb - (REAL)4 * qa * qc;
        if (disc < (REAL)0) return 0;
        REAL q = (REAL)-0.5 * (qb + copysign(sqrt(disc), qb));
        x0 = q / qa;
        x1 = (q != (REAL)0) ? qc / q : x0;
        if (x1 < x0) {
            REAL tmp = x0;
            x0 = x1;
            x1 = tmp;
        }
        m = 2;
    }
    int k = 0;
    if (x0 > lo && x0 < hi) r[k++] = x0;
    if (m == 2 && x1 > lo && x1 < hi && x1 != x0) r[k++] = x1;
    return k;
}

/* Clip o + s d to the box |x|, |y| <= rb, |z| <= zb (s >= 0); false when empty. */
inline int clip_box(real3 o, real3 d, REAL rb, REAL zb, REAL *s0, REAL *s1) {
    REAL lo = (REAL)0, hi = BIG;
    REAL oc[3] = {o.x, o.y, o.z}, dc[3] = {d.x, d.y, d.z}, hb[3] = {rb, rb, zb};
    for (int j = 0; j < 3; j++) {
        if (dc[j] != (REAL)0) {
            REAL ta = (-hb[j] - oc[j]) / dc[j], tb = (hb[j] - oc[j]) / dc[j];
            lo = fmax(lo, fmin(ta, tb));
            hi = fmin(hi, fmax(ta, tb));
        } else if (fabs(oc[j]) > hb[j]) {
            return 0;
        }
    }
    *s0 = lo;
    *s1 = hi;
    return lo < hi;
}

/* Outward unit normal from the profile at t = acos(z/H): in the (rho, z) half-plane
 * (H sin t, R/2 (cos t - cos 2t)) = (H sqrt(u w), R/2 w (2u - 1)). */
inline real3 drop_normal(real3 p, REAL R, REAL H) {
    REAL u = clamp((H + p.z) / H, (REAL)0, (REAL)2), w = clamp((H - p.z) / H, (REAL)0, (REAL)2);
    REAL nr = H * sqrt(u * w), nz = (REAL)0.5 * R * w * ((REAL)2 * u - (REAL)1);
    REAL rho = sqrt(p.x * p.x + p.y * p.y);
    REAL ex = rho > (REAL)0 ? p.x / rho : (REAL)0, ey = rho > (REAL)0 ? p.y / rho : (REAL)0;
    real3 n = r3(nr * ex, nr * ey, nz);
    REAL nn = dot(n, n);
    return nn > (REAL)0 ? n / sqrt(nn) : r3((REAL)0, (REAL)0, (REAL)1);
}

inline int hit_drop(real3 o, real3 d, int inside, REAL R, REAL H, REAL *t, real3 *n) {
    const REAL A = (REAL)0.25 * R * R;
    const REAL tol = TOL_REL * fmax(R, H);
    REAL s0, s1;
    /* max r(t) = (3 sqrt 3 / 8) R = 0.6495 R */
    if (!clip_box(o, d, (REAL)0.6505 * R, H * ((REAL)1 + (REAL)1e-6), &s0, &s1)) return 0;
    real3 q = o + s0 * d;
    REAL L = s1 - s0;
    /* F(q + s d) = sum a_i s^i: u = u0 + k s, w = w0 - k s */
    REAL k = d.z / H, u0 = (H + q.z) / H, w0 = (H - q.z) / H;
    REAL W0 = w0 * w0 * w0, W1 = (REAL)-3 * w0 * w0 * k, W2 = (REAL)3 * w0 * k * k,
         W3 = -k * k * k;
    REAL a[5];
    a[0] = A * u0 * W0 - (q.x * q.x + q.y * q.y);
    a[1] = A * (u0 * W1 + k * W0) - (REAL)2 * (q.x * d.x + q.y * d.y);
    a[2] = A * (u0 * W2 + k * W1) - (d.x * d.x + d.y * d.y);
    a[3] = A * (u0 * W3 + k * W2);
    a[4] = A * k * W3;
    /* F'' = 12 a4 s^2 + 6 a3 s + 2 a2: its roots split [0, L] into pieces with F' monotone */
    REAL br[4];
    br[0] = (REAL)0;
    int nb = 1 + quad_roots_in((REAL)6 * a[4], (REAL)3 * a[3], a[2], (REAL)0, L, br + 1);
    br[nb++] = L;
    REAL cp[5];
    int nc = 0;
    cp[nc++] = (REAL)0;
    for (int i = 0; i + 1 < nb; i++) {
        REAL lo = br[i], hi = br[i + 1];
        int plo = poly_d1(a, lo) > (REAL)0;
        if (plo == (poly_d1(a, hi) > (REAL)0)) continue;
        for (int it = 0; it < MAX_BISECT && hi - lo > tol; it++) {
            REAL mid = (REAL)0.5 * (lo + hi);
            if ((poly_d1(a, mid) > (REAL)0) == plo) lo = mid;
            else hi = mid;
        }
        cp[nc++] = (REAL)0.5 * (lo + hi);
    }
    cp[nc++] = L;
    /* F is monotone on each [cp_i, cp_i+1]: the first piece whose end lies on the other side
     * brackets the first crossing */
    for (int i = 0; i + 1 < nc; i++) {
        REAL fe = drop_F(q + cp[i + 1] * d, A, H);
        int other = inside ? (fe <= (REAL)0) : (fe > (REAL)0);
        if (!other) continue;
        REAL lo = cp[i], hi = cp[i + 1];
        for (int it = 0; it < MAX_BISECT && hi - lo > tol; it++) {
            REAL mid = (REAL)0.5 * (lo + hi);
            REAL fm = drop_F(q + mid * d, A, H);
            int om = inside ? (fm <= (REAL)0) : (fm > (REAL)0);
            if (om) hi = mid;
            else lo = mid;
        }
        REAL s = (REAL)0.5 * (lo + hi);
        *t = s0 + s;
        *n = drop_normal(q + s * d, R, H);
        return 1;
    }
    return 0;
}

/* ------------------------------------------------------------------------- the event */
inline int hit_solid(__global const REAL *sp, real3 o, real3 d, int inside, REAL *t, real3 *n) {
#if defined(SOLID_SPHERE)
    return hit_sphere(o, d, inside, sp[12], t, n);
#elif defined(SOLID_PRISM)
    return hit_prism(o, d, inside, sp[12], sp[13], t, n);
#elif defined(SOLID_DROP)
    return hit_drop(o, d, inside, sp[12], sp[13], t, n);
#else
#error "snell.cl needs SOLID_SPHERE, SOLID_PRISM or SOLID_DROP"
#endif
}

inline REAL solid_size(__global const REAL *sp) {
#if defined(SOLID_DROP)
    return fmax(sp[12], sp[13]);
#else
    return sp[12];
#endif
}

inline REAL solid_eta(__global const REAL *sp) { return sp[14]; }
