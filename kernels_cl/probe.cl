/* Lane-width probe: every vector built-in the kernels use, at the build's LANES and precision.
 * Some drivers fail instruction selection for a built-in at one width only (pip PoCL 3.0:
 * rsqrt on float16 for znver3), so clrefract builds and runs this before choosing LANES. */
__kernel void probe_builtins(__global const REAL *restrict a, __global REAL *restrict out,
                             __global int *restrict flags) {
    const int i = get_global_id(0);
    realv x = VLOAD(i, a); /* in [0.5, 2) */
    realv r = sqrt(x) + rsqrt(x) + exp(-x) + log1p(x) + sin(x) + cos(x);
    r += acos(clamp(x - RV(1), RV(-1), RV(1))) + fabs(RV(1) - x) + floor(x * RV(3));
    r += mix(x, RV(2) * x, RV(0.25)) + fmin(x, RV(1)) + fmax(x, RV(1.5));
    r += copysign(x, RV(1) - x) + sign(x - RV(1)) + smoother(x - RV(0.5));
    maskv big = x > RV(1);
    r += SEL(RV(0), RV(1), big && isfinite(x));
    intv k = TO_INTV(floor(x * RV(4)));
    r += TO_REALV(min(k, (intv)(5)));
    VSTORE(r, i, out);
    if (ANY(big)) atomic_add(flags, 1);
}
