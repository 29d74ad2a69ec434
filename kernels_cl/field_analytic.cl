/* Analytic index fields: eta and grad eta, vectorised over LANES points.
 * Exactly one FIELD_* define selects the field; its parameters are in fp
 * (layouts mirror clrefract/fields/analytic.py). */

/* Tilted fields: fp[0..2] the centre, fp[3..11] M (world -> local, row-major). */
inline void tilted_local(__global const REAL *restrict fp, realv x, realv y, realv z,
                         realv *lx, realv *ly, realv *lz) {
    realv px = x - fp[0], py = y - fp[1], pz = z - fp[2];
    *lx = fp[3] * px + fp[4] * py + fp[5] * pz;
    *ly = fp[6] * px + fp[7] * py + fp[8] * pz;
    *lz = fp[9] * px + fp[10] * py + fp[11] * pz;
}
/* a local vector back to world: M^T v */
inline void tilted_world(__global const REAL *restrict fp, realv vx, realv vy, realv vz,
                         realv *wx, realv *wy, realv *wz) {
    *wx = fp[3] * vx + fp[6] * vy + fp[9] * vz;
    *wy = fp[4] * vx + fp[7] * vy + fp[10] * vz;
    *wz = fp[5] * vx + fp[8] * vy + fp[11] * vz;
}

#if defined(FIELD_LUNEBURG)
/* fp: cx cy cz R.  eta = sqrt(2 - r^2/R^2) inside, 1 outside. */
inline realv field_eval(FIELD_PARAMS, realv x, realv y, realv z, realv *gx, realv *gy,
                        realv *gz) {
    realv px = x - fp[0], py = y - fp[1], pz = z - fp[2];
    REAL R2 = fp[3] * fp[3];
    realv r2 = px * px + py * py + pz * pz;
    realv inside = SEL(RV(0), RV(1), r2 < RV(R2));
    realv eta = sqrt(RV(1) + inside * (RV(1) - r2 / R2));
    realv k = -inside / (R2 * eta);
    *gx = k * px;
    *gy = k * py;
    *gz = k * pz;
    return eta;
}

/* grad eta jumps at the surface: (r^2 - R^2) / 2R, about r - R there */
#ifndef NO_INTERFACE_STEPS
#define FIELD_INTERFACE 1
#define INTERFACE_LO (REAL)0
#define INTERFACE_HI (REAL)0
inline realv field_interface(FIELD_PARAMS, realv x, realv y, realv z) {
    realv px = x - fp[0], py = y - fp[1], pz = z - fp[2];
    return (px * px + py * py + pz * pz - fp[3] * fp[3]) / (RV(2) * fp[3]);
}
/* One side's formula continued a little past the surface: region -1 inside, +1 outside,
 * -2 by position (see interface_step in trace.cl). */
inline realv field_eval_region(FIELD_PARAMS, realv x, realv y, realv z, realv region, realv *gx,
                               realv *gy, realv *gz) {
    realv px = x - fp[0], py = y - fp[1], pz = z - fp[2];
    REAL R2 = fp[3] * fp[3];
    realv r2 = px * px + py * py + pz * pz;
    maskv in = SEL(region < RV(0), r2 < RV(R2), region < RV(-1.5));
    realv inside = SEL(RV(0), RV(1), in);
    realv eta = sqrt(fmax(RV(1) + inside * (RV(1) - r2 / R2), RV(REAL_EPS)));
    realv k = -inside / (R2 * eta);
    *gx = k * px;
    *gy = k * py;
    *gz = k * pz;
    return eta;
}
#endif

#elif defined(FIELD_MAXWELL)
/* fp: cx cy cz R n0.  eta = n0 / (1 + r^2/R^2). */
inline realv field_eval(FIELD_PARAMS, realv x, realv y, realv z, realv *gx, realv *gy,
                        realv *gz) {
    realv px = x - fp[0], py = y - fp[1], pz = z - fp[2];
    REAL R2 = fp[3] * fp[3];
    realv q = RV(1) + (px * px + py * py + pz * pz) / R2;
    realv eta = fp[4] / q;
    realv k = RV(-2) * eta / (q * R2);
    *gx = k * px;
    *gy = k * py;
    *gz = k * pz;
    return eta;
}

#elif defined(FIELD_FIBRE)
/* fp: cx cy n0 a.  eta^2 = n0^2 (1 - a^2 rho^2), rho measured from the axis (cx, cy, z). */
inline realv field_eval(FIELD_PARAMS, realv x, realv y, realv z, realv *gx, realv *gy,
                        realv *gz) {
    realv px = x - fp[0], py = y - fp[1];
    REAL n0 = fp[2], a2 = fp[3] * fp[3];
    realv q = fmax(RV(1) - a2 * (px * px + py * py), RV(REAL_EPS));
    realv eta = n0 * sqrt(q);
    realv k = -n0 * n0 * a2 / eta;
    *gx = k * px;
    *gy = k * py;
    *gz = RV(0);
    return eta;
}

#elif defined(FIELD_BLOBS)
/* 2^q for q <= 0 (the blobs' exponents): q = n + f, |f| <= 1/2, 2^f by Cephes' exp2f
 * polynomial (relative error about 1e-7) in Estrin's order (a shorter chain: a step is three
 * dependent evaluations, so latency, not throughput, sets its pace), n added to the exponent
 * bits, rint by adding 1.5 2^23. q is clamped at -100, where a term is far below float32's
 * resolution of eta, but the gradient's products stay normal: at -125 they were denormal far
 * from a blob, and x86 takes a slow path on each. PoCL's exp and rint took about twice the
 * instructions (their range checks). */
#ifdef REAL_IS_DOUBLE
#define blob_exp2 exp2
#else
inline __attribute__((always_inline)) realv blob_exp2(realv q) {
    q = fmax(q, RV(-100.0f));
    realv t = q + RV(12582912.0f);
    realv f = q - (t - RV(12582912.0f));
    realv f2 = f * f;
    realv a = RV(6.931472028550421e-1f) * f + RV(1.0f);
    realv b = RV(5.550332471162809e-2f) * f + RV(2.402264791363012e-1f);
    realv c = RV(1.535336188319500e-4f) * f + RV(1.339887440266574e-3f);
    c = c * f + RV(9.618437357674640e-3f);
    realv y = (c * f2 + b) * f2 + a;
#if LANES == 1
    return as_float(as_int(y) + ((as_int(t) - 0x4B400000) << 23));
#else
    return CAT(as_float, LANES)(CAT(as_int, LANES)(y) +
                                ((CAT(as_int, LANES)(t) - 0x4B400000) << 23));
#endif
}
#endif

/* fp: NBLOBS x (cx cy cz a q inv), q = -log2(e) / 2 s^2 and inv = 1 / s^2 computed on the
 * host (Blobs.params).  eta = 1 + sum a exp(-|x - c|^2 / 2 s^2) = 1 + sum a 2^(q |x - c|^2).
 * Inlined by force: PoCL builds with -Dinline= and left it a call, its vectors through memory. */
inline __attribute__((always_inline)) realv field_eval(FIELD_PARAMS, realv x, realv y,
                                                       realv z, realv *gx, realv *gy,
                                                       realv *gz) {
    realv eta = RV(1), ax = RV(0), ay = RV(0), az = RV(0);
#pragma unroll
    for (int k = 0; k < NBLOBS; ++k) {
        __global const REAL *b = fp + 6 * k;
        realv px = x - b[0], py = y - b[1], pz = z - b[2];
        realv g = b[3] * blob_exp2(b[4] * (px * px + py * py + pz * pz));
        realv gi = g * b[5];
        eta += g;
        ax -= gi * px;
        ay -= gi * py;
        az -= gi * pz;
    }
    *gx = ax;
    *gy = ay;
    *gz = az;
    return eta;
}

#elif defined(FIELD_GRIN_ROD)
/* fp: cx cy cz, M (world -> local), n0 a L/2 cap.  Along local z:
 * eta = 1 + (eta_p - 1) S((L/2 - |z|) / cap), eta_p = n0 sqrt(max(1 - a^2 rho^2, 1/n0^2)). */
inline realv field_eval(FIELD_PARAMS, realv x, realv y, realv z, realv *gx, realv *gy,
                        realv *gz) {
    realv lx, ly, lz;
    tilted_local(fp, x, y, z, &lx, &ly, &lz);
    REAL n0 = fp[12], a2 = fp[13] * fp[13], cap = fp[15], floor_q = (REAL)1 / (n0 * n0);
    realv q = RV(1) - a2 * (lx * lx + ly * ly);
    realv eta_p = n0 * sqrt(fmax(q, RV(floor_q)));
    realv k = SEL(RV(0), -n0 * n0 * a2 / eta_p, q > RV(floor_q));
    realv u = (RV(fp[14]) - fabs(lz)) / cap;
    realv w = smoother(u);
    realv glz = -(eta_p - RV(1)) * sign(lz) * smoother_d(u) / cap;
    tilted_world(fp, w * k * lx, w * k * ly, glz, gx, gy, gz);
    return RV(1) + (eta_p - RV(1)) * w;
}

#elif defined(FIELD_GRIN_LENS)
/* fp: cx cy cz, M (world -> local), dn R T rim.  Disc about local z:
 * eta = 1 + dn (1 - u^2)^3 S((R - rho) / rim), u = 2z / T, |u| < 1. */
inline realv field_eval(FIELD_PARAMS, realv x, realv y, realv z, realv *gx, realv *gy,
                        realv *gz) {
    realv lx, ly, lz;
    tilted_local(fp, x, y, z, &lx, &ly, &lz);
    REAL dn = fp[12], R = fp[13], T = fp[14], rim = fp[15];
    realv u = RV(2) * lz / T;
    realv t = fmax(RV(1) - u * u, RV(0));
    realv b = t * t * t, db = RV(-12) * u * t * t / T;
    realv rho = sqrt(lx * lx + ly * ly);
    realv v = (RV(R) - rho) / rim;
    realv w = smoother(v);
    realv dw = -dn * b * smoother_d(v) / (rim * fmax(rho, RV(REAL_EPS)));
    tilted_world(fp, dw * lx, dw * ly, dn * db * w, gx, gy, gz);
    return RV(1) + dn * b * w;
}

#elif defined(FIELD_PLUME)
/* fp: cx cy cz h A0 s0 k p rise fade m w.  Height above the source zeta = z - (cz - h),
 * zc = clamp(zeta, 0, 2h), t = zc / 2h; s = s0 + k zc, A = A0 (s0 / s)^p; axis at
 * (cx + m t sin(w zc), cy + m t sin(0.6 w zc));
 * eta = 1 + A W exp(-r^2 / 2 s^2), W = S(zeta / rise) S((2h - zeta) / fade). */
inline realv field_eval(FIELD_PARAMS, realv x, realv y, realv z, realv *gx, realv *gy,
                        realv *gz) {
    REAL h2 = 2 * fp[3], s0 = fp[5], k = fp[6], p = fp[7], m = fp[10], w = fp[11];
    realv zeta = z - (fp[2] - fp[3]);
    realv zc = clamp(zeta, RV(0), RV(h2));
    realv t = zc / h2;
    realv s = s0 + k * zc;
    realv amp = fp[4] * exp(-p * log(s / s0));
    realv sx = sin(w * zc), sy = sin((REAL)0.6 * w * zc);
    realv px = x - fp[0] - m * t * sx, py = y - fp[1] - m * t * sy;
    realv dxm = m * (sx / h2 + t * w * cos(w * zc));
    realv dym = m * (sy / h2 + (REAL)0.6 * t * w * cos((REAL)0.6 * w * zc));
    realv r2 = px * px + py * py, is2 = RV(1) / (s * s);
    realv g = amp * exp((REAL)-0.5 * r2 * is2);
    realv lo = zeta / fp[8], hi = (RV(h2) - zeta) / fp[9];
    realv slo = smoother(lo), shi = smoother(hi);
    realv win = slo * shi;
    realv dwin = smoother_d(lo) * shi / fp[8] - slo * smoother_d(hi) / fp[9];
    realv f = g * win;
    realv dz = (px * dxm + py * dym) * is2 + (r2 * is2 - p) * k / s;
    *gx = -f * px * is2;
    *gy = -f * py * is2;
    *gz = g * dwin + f * dz;
    return RV(1) + f;
}

#else /* smoothed solids: eta = 1 + (n - 1) S(1/2 - sd / w), sd the signed distance */

#if defined(FIELD_SPHERE)
/* fp: cx cy cz R n w */
#define SOLID_N fp[4]
#define SOLID_W fp[5]
inline realv solid_sdf(FIELD_PARAMS, realv x, realv y, realv z, realv *nx, realv *ny,
                       realv *nz) {
    realv px = x - fp[0], py = y - fp[1], pz = z - fp[2];
    realv r = sqrt(px * px + py * py + pz * pz);
    realv ir = RV(1) / fmax(r, RV(REAL_EPS));
    *nx = px * ir;
    *ny = py * ir;
    *nz = pz * ir;
    return r - fp[3];
}

#elif defined(FIELD_PRISM)
/* fp: cx cy cz, M (3x3 world->local, row-major), side, length, n, w.
 * Equilateral triangle in local xy around the centroid, axis along local z. */
#define SOLID_N fp[14]
#define SOLID_W fp[15]
inline realv solid_sdf(FIELD_PARAMS, realv x, realv y, realv z, realv *nx, realv *ny,
                       realv *nz) {
    realv lx, ly, lz;
    tilted_local(fp, x, y, z, &lx, &ly, &lz);
    REAL rin = fp[12] * (REAL)0.28867513459481287; /* side / (2 sqrt 3) */
    REAL c30 = (REAL)0.8660254037844386;
    /* plane normals (0,1), (-c30,-1/2), (c30,-1/2), and the caps (0,0,+-1) */
    realv d = ly - rin, mx = RV(0), my = RV(1), mz = RV(0);
    realv dk = -c30 * lx - (REAL)0.5 * ly - rin;
    maskv m = dk > d;
    d = SEL(d, dk, m); mx = SEL(mx, RV(-c30), m); my = SEL(my, RV(-0.5), m);
    dk = c30 * lx - (REAL)0.5 * ly - rin;
    m = dk > d;
    d = SEL(d, dk, m); mx = SEL(mx, RV(c30), m); my = SEL(my, RV(-0.5), m);
    dk = fabs(lz) - (REAL)0.5 * fp[13];
    m = dk > d;
    d = SEL(d, dk, m); mx = SEL(mx, RV(0), m); my = SEL(my, RV(0), m);
    mz = SEL(mz, sign(lz), m);
    tilted_world(fp, mx, my, mz, nx, ny, nz);
    return d;
}

#elif defined(FIELD_DROP)
/* fp: cx cy cz R H n w.  Body of revolution about z: r(t) = R sin t sin^2(t/2),
 * z(t) = H cos t, t in [0, pi]. Distance to the profile: the nearest of DROP_SAMPLES + 1
 * samples t_k, then Newton on u = t - t_k within the sample interval the descent points
 * into (bisection where Newton would leave it), the point (cos t, sin t) turned by each step
 * with sin and cos as series: no trigonometric calls, which made the drop 70x slower than
 * the sphere. A lane stops once its step is below DROP_TOL. Drop.foot in
 * clrefract/fields/analytic.py is the same arithmetic. */
#define SOLID_N fp[5]
#define SOLID_W fp[6]
#define DROP_SAMPLES 24
#define DROP_NEWTON 8
#ifdef REAL_IS_DOUBLE
#define DROP_TOL 1e-9
#else
#define DROP_TOL 1e-5f
#endif
/* (cos, sin) of t_k = k pi / DROP_SAMPLES */
__constant REAL DROP_CS[DROP_SAMPLES + 1][2] = {
    {(REAL)1.0, (REAL)0.0},
    {(REAL)0.9914448613738104, (REAL)0.13052619222005157},
    {(REAL)0.9659258262890683, (REAL)0.25881904510252074},
    {(REAL)0.9238795325112867, (REAL)0.3826834323650898},
    {(REAL)0.8660254037844387, (REAL)0.49999999999999994},
    {(REAL)0.7933533402912352, (REAL)0.6087614290087207},
    {(REAL)0.7071067811865476, (REAL)0.7071067811865475},
    {(REAL)0.6087614290087207, (REAL)0.7933533402912352},
    {(REAL)0.5000000000000001, (REAL)0.8660254037844386},
    {(REAL)0.38268343236508984, (REAL)0.9238795325112867},
    {(REAL)0.25881904510252074, (REAL)0.9659258262890683},
    {(REAL)0.1305261922200517, (REAL)0.9914448613738104},
    {(REAL)6.123233995736766e-17, (REAL)1.0},
    {(REAL)-0.1305261922200516, (REAL)0.9914448613738104},
    {(REAL)-0.25881904510252063, (REAL)0.9659258262890683},
    {(REAL)-0.3826834323650895, (REAL)0.9238795325112868},
    {(REAL)-0.4999999999999998, (REAL)0.8660254037844387},
    {(REAL)-0.6087614290087207, (REAL)0.7933533402912352},
    {(REAL)-0.7071067811865475, (REAL)0.7071067811865476},
    {(REAL)-0.793353340291235, (REAL)0.6087614290087209},
    {(REAL)-0.8660254037844387, (REAL)0.49999999999999994},
    {(REAL)-0.9238795325112867, (REAL)0.3826834323650899},
    {(REAL)-0.9659258262890682, (REAL)0.258819045102521},
    {(REAL)-0.9914448613738104, (REAL)0.130526192220052},
    {(REAL)-1.0, (REAL)1.2246467991473532e-16}};
inline realv solid_sdf(FIELD_PARAMS, realv x, realv y, realv z, realv *nx, realv *ny,
                       realv *nz) {
    realv px = x - fp[0], py = y - fp[1], pz = z - fp[2];
    const REAL hR = (REAL)0.5 * fp[3], H = fp[4];
    const REAL dt = (REAL)M_PI / (REAL)DROP_SAMPLES;
    realv rho = sqrt(px * px + py * py);
    /* a lower bound: the distance to the drop's cylinder (radius 3 sqrt 3 R / 8, |z| < H).
     * Lanes more than a band width w beyond it are outside the band (eta 1, no gradient):
     * they return the bound, and where all lanes do the search is skipped. */
    realv er0 = fmax(rho - RV(fp[3] * (REAL)0.649519052838329), RV(0));
    realv ez0 = fmax(fabs(pz) - RV(H), RV(0));
    realv bound = sqrt(er0 * er0 + ez0 * ez0);
    maskv far = bound > RV(SOLID_W), near = bound <= RV(SOLID_W);
    *nx = RV(0);
    *ny = RV(0);
    *nz = RV(0);
    if (!ANY(near))
        return bound;
    realv c = RV(1), s = RV(0), kb = RV(0), best_d2 = RV(INFINITY);
    for (int k = 0; k <= DROP_SAMPLES; ++k) {
        const REAL ck = DROP_CS[k][0], sk = DROP_CS[k][1];
        realv dr = RV(hR * sk * (1 - ck)) - rho, dz = RV(H * ck) - pz;
        realv d2 = dr * dr + dz * dz;
        maskv m = d2 < best_d2;
        best_d2 = SEL(best_d2, d2, m);
        c = SEL(c, RV(ck), m);
        s = SEL(s, RV(sk), m);
        kb = SEL(kb, RV((REAL)k), m);
    }
    realv u = RV(0), lo = RV(0), hi = RV(0);
    maskv open = near;
    for (int it = 0; it < DROP_NEWTON; ++it) {
        realv c2t = c * c - s * s;
        realv r = hR * s * (RV(1) - c), zc = H * c;
        realv r1 = hR * (c - c2t), z1 = -H * s;
        realv r2 = hR * (RV(4) * s * c - s), z2 = -H * c;
        realv g = (r - rho) * r1 + (zc - pz) * z1;
        realv dg = r1 * r1 + z1 * z1 + (r - rho) * r2 + (zc - pz) * z2;
        if (it == 0) { /* the interval the descent points into (the inner one at the ends) */
            maskv up = (g < RV(0) || kb == RV(0)) && kb < RV(DROP_SAMPLES);
            lo = SEL(RV(-dt), RV(0), up || kb == RV(0));
            hi = SEL(RV(0), RV(dt), up);
        } else {
            lo = SEL(lo, u, g < RV(0));
            hi = SEL(u, hi, g < RV(0));
        }
        realv un = u - g / SEL(RV(1), dg, dg > RV(0));
        maskv ok = dg > RV(0) && un >= lo && un <= hi;
        realv step = SEL(RV(0), SEL(RV(0.5) * (lo + hi), un, ok) - u, open);
        realv q = step * step;
        realv sn_ = RV(1) - q * RV(1.0 / 42);
        sn_ = step * (RV(1) - q * RV(1.0 / 6) * (RV(1) - q * RV(1.0 / 20) * sn_));
        realv cs_ = RV(1) - q * RV(0.5) * (RV(1) - q * RV(1.0 / 12) * (RV(1) - q * RV(1.0 / 30)));
        realv cn = c * cs_ - s * sn_, sn = s * cs_ + c * sn_;
        realv inv = rsqrt(cn * cn + sn * sn);
        c = cn * inv;
        s = fmax(sn * inv, RV(0));
        u += step;
        open = open && fabs(step) > RV(DROP_TOL);
        if (!ANY(open))
            break;
    }
    realv er = rho - hR * s * (RV(1) - c), ez = pz - H * c;
    realv dist = sqrt(er * er + ez * ez);
    /* inside: |z| < H and rho below the profile radius at that height (cos t = z / H) */
    realv uz = clamp(pz / H, RV(-1), RV(1));
    realv rz = hR * sqrt(RV(1) - uz * uz) * (RV(1) - uz);
    realv sgn = SEL(RV(1), RV(-1), fabs(pz) < RV(H) && rho < rz);
    /* gradient: away from the curve, or the curve's outward normal when on it */
    realv c2t = c * c - s * s;
    realv onx = H * s, onz = hR * (c - c2t);
    realv on = fmax(sqrt(onx * onx + onz * onz), RV(REAL_EPS));
    maskv away = dist > RV(1e-4) * (RV(2) * hR + H);
    realv inv = RV(1) / fmax(dist, RV(REAL_EPS));
    realv gr = SEL(onx / on, sgn * er * inv, away);
    realv gz_ = SEL(onz / on, sgn * ez * inv, away);
    realv irho = SEL(RV(0), RV(1) / fmax(rho, RV(REAL_EPS)), rho > RV(REAL_EPS));
    *nx = SEL(gr * px * irho, RV(0), far);
    *ny = SEL(gr * py * irho, RV(0), far);
    *nz = SEL(gz_, RV(0), far);
    return SEL(sgn * dist, bound, far);
}
#else
#error "no FIELD_* kind defined"
#endif

inline realv field_eval(FIELD_PARAMS, realv x, realv y, realv z, realv *gx, realv *gy,
                        realv *gz) {
    realv nx, ny, nz;
    realv sd = solid_sdf(FIELD_ARGS, x, y, z, &nx, &ny, &nz);
    REAL w = SOLID_W, dn = SOLID_N - (REAL)1;
    realv s = RV(0.5) - sd / w;
    realv k = -dn * smoother_d(s) / w;
    *gx = k * nx;
    *gy = k * ny;
    *gz = k * nz;
    return RV(1) + dn * smoother(s);
}

/* The smoothstep's higher derivatives jump at the band edges sd = +-w/2. */
#ifndef NO_INTERFACE_STEPS
#define FIELD_INTERFACE 1
#define INTERFACE_LO (-(REAL)0.5 * SOLID_W)
#define INTERFACE_HI ((REAL)0.5 * SOLID_W)
inline realv field_interface(FIELD_PARAMS, realv x, realv y, realv z) {
    realv nx, ny, nz;
    return solid_sdf(FIELD_ARGS, x, y, z, &nx, &ny, &nz);
}
/* One region's formula continued a little past its edges: region -1 inside (eta = n), 0 the
 * band (the smoothstep's polynomial, unclamped), +1 outside (eta = 1), -2 by position. */
inline realv field_eval_region(FIELD_PARAMS, realv x, realv y, realv z, realv region, realv *gx,
                               realv *gy, realv *gz) {
    realv nx, ny, nz;
    realv sd = solid_sdf(FIELD_ARGS, x, y, z, &nx, &ny, &nz);
    REAL w = SOLID_W, dn = SOLID_N - (REAL)1;
    realv pos = SEL(SEL(RV(0), RV(1), sd > RV(0.5 * w)), RV(-1), sd < RV(-0.5 * w));
    realv reg = SEL(region, pos, region < RV(-1.5));
    realv t = RV(0.5) - sd / w;
    realv band = SEL(RV(0), RV(1), reg == RV(0));
    realv p = t * t * t * (t * (t * RV(6) - RV(15)) + RV(10));
    realv dp = RV(30) * t * t * (t - RV(1)) * (t - RV(1));
    realv frac = SEL(band * p, RV(1), reg < RV(-0.5));
    realv k = -dn * band * dp / w;
    *gx = k * nx;
    *gy = k * ny;
    *gz = k * nz;
    return RV(1) + dn * frac;
}
#endif
#endif
