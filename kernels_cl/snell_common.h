/* Helpers of the exact Snell renderers (snell.cl, snell_sdf.cl, snell_trace.cl). */

typedef CAT(REAL, 3) real3;

inline real3 r3(REAL x, REAL y, REAL z) {
    real3 v;
    v.x = x;
    v.y = y;
    v.z = z;
    return v;
}

inline real3 unit3(real3 v) { return v / sqrt(dot(v, v)); }

/* Snell refraction with relative index eta_i / eta_t, or mirror reflection past the critical
 * angle. n is the outward normal; inside says which medium the ray travels in. */
inline real3 refract_or_reflect(real3 d, real3 n, int inside, REAL eta) {
    REAL cd = dot(d, n);
    real3 m = cd < (REAL)0 ? n : -n; /* faces the incoming ray */
    REAL ci = fabs(cd);
    REAL r = inside ? eta : (REAL)1 / eta;
    REAL k = (REAL)1 - r * r * ((REAL)1 - ci * ci);
    if (k < (REAL)0) return unit3(d + (REAL)2 * ci * m);
    return unit3(r * d + (r * ci - sqrt(k)) * m);
}

inline int finite3(real3 v) { return isfinite(v.x) && isfinite(v.y) && isfinite(v.z); }

/* Distance along d from p to the box wall it leaves through (0 when p is outside); the box
 * from the parameters fp (common.h). */
inline REAL box_exit_distance(__global const REAL *restrict fp, real3 p, real3 d) {
    REAL lo[3] = {BOX_LO_X, BOX_LO_Y, BOX_LO_Z};
    REAL hi[3] = {BOX_HI_X, BOX_HI_Y, BOX_HI_Z};
    REAL pc[3] = {p.x, p.y, p.z}, dc[3] = {d.x, d.y, d.z};
    REAL t = (REAL)1e30;
    for (int j = 0; j < 3; j++) {
        if (dc[j] > (REAL)0) t = fmin(t, (hi[j] - pc[j]) / dc[j]);
        else if (dc[j] < (REAL)0) t = fmin(t, (lo[j] - pc[j]) / dc[j]);
    }
    return fmax(t, (REAL)0);
}
