/* Adjoint-state backward pass (SPEC section 3), constant memory per ray.
 *
 * From the last in-box state (x_K, v_K) and the terminal adjoint mu(T) = dJ/dv, integrate
 * backwards in sigma, with classic RK4, the augmented system
 *     x' = v,  v' = D(x),  lambda' = -H_D(x) mu,  mu' = -lambda,   D = eta grad eta,
 *     H_D mu = grad eta (grad eta . mu) + eta Hess(eta) mu,
 * and the parameter gradient dJ/dtheta = int mu . dD/dtheta dsigma as one more component of
 * that state, so each RK4 stage splats its integrand with the stage weight. The field gives
 * field_adjoint(): eta, grad eta, Hess(eta) mu, and the splat (see field_voxel.cl). */

/* Fields accumulate in private memory what they can (a voxel grid: the cell a ray is
 * in; shared MLP weights: the whole ray) and reach global memory when that changes or at
 * the end (FIELD_ACC_FLUSH). */
#ifndef FIELD_ACC_DECL
#define FIELD_ACC_DECL
#define FIELD_ACC_PARAM
#define FIELD_ACC_ARG
#define FIELD_ACC_FLUSH(grad, partial, gid)
#endif

/* Time derivative of the augmented state; splats w * (mu . dD/dtheta) on the way. */
inline void adjoint_rhs(FIELD_PARAMS, __global REAL *grad FIELD_ACC_PARAM, realv w, realv x,
                        realv y, realv z, realv mx, realv my, realv mz, realv lx, realv ly,
                        realv lz, realv *dvx, realv *dvy, realv *dvz, realv *dlx, realv *dly,
                        realv *dlz) {
    realv gx, gy, gz, hx, hy, hz;
    realv eta = field_adjoint(FIELD_ARGS, x, y, z, mx, my, mz, w, &gx, &gy, &gz, &hx, &hy, &hz,
                              grad FIELD_ACC_ARG);
    *dvx = eta * gx;
    *dvy = eta * gy;
    *dvz = eta * gz;
    realv gm = gx * mx + gy * my + gz * mz;
    *dlx = -(gx * gm + eta * hx);
    *dly = -(gy * gm + eta * hy);
    *dlz = -(gz * gm + eta * hz);
}

#define STAGE(W, X, Y, Z, VX, VY, VZ, LX, LY, LZ, MX, MY, MZ, K)                              \
    realv K##xx = VX, K##xy = VY, K##xz = VZ, K##vx, K##vy, K##vz, K##lx, K##ly, K##lz;        \
    realv K##mx = -(LX), K##my = -(LY), K##mz = -(LZ);                                        \
    adjoint_rhs(FIELD_ARGS, grad FIELD_ACC_ARG, W, X, Y, Z, MX, MY, MZ, LX, LY, LZ, &K##vx,     \
                &K##vy, &K##vz, &K##lx, &K##ly, &K##lz)

__kernel void adjoint_rays(FIELD_PARAMS, const REAL h, __global const REAL *pxk,
                           __global const REAL *pyk, __global const REAL *pzk,
                           __global const REAL *qxk, __global const REAL *qyk,
                           __global const REAL *qzk, __global const int *steps,
                           __global const REAL *mux, __global const REAL *muy,
                           __global const REAL *muz, __global REAL *grad,
                           __global REAL *partial, __global REAL *bx, __global REAL *by,
                           __global REAL *bz) {
    const size_t i = get_global_id(0);
    realv x = VLOAD(i, pxk), y = VLOAD(i, pyk), z = VLOAD(i, pzk);
    realv vx = VLOAD(i, qxk), vy = VLOAD(i, qyk), vz = VLOAD(i, qzk);
    realv mx = VLOAD(i, mux), my = VLOAD(i, muy), mz = VLOAD(i, muz);
    realv lx = RV(0), ly = RV(0), lz = RV(0);
    realv n = TO_REALV(VLOAD(i, steps));
    FIELD_ACC_DECL
    const REAL hh = (REAL)0.5 * h, h6 = h / (REAL)6;
    for (int k = 0; ANY(RV(k) < n); ++k) {
        maskv active = RV(k) < n;
        realv w = SEL(RV(0), RV(h6), active);
        STAGE(w, x, y, z, vx, vy, vz, lx, ly, lz, mx, my, mz, a);
        STAGE(RV(2) * w, x - hh * axx, y - hh * axy, z - hh * axz, vx - hh * avx,
              vy - hh * avy, vz - hh * avz, lx - hh * alx, ly - hh * aly, lz - hh * alz,
              mx - hh * amx, my - hh * amy, mz - hh * amz, b);
        STAGE(RV(2) * w, x - hh * bxx, y - hh * bxy, z - hh * bxz, vx - hh * bvx,
              vy - hh * bvy, vz - hh * bvz, lx - hh * blx, ly - hh * bly, lz - hh * blz,
              mx - hh * bmx, my - hh * bmy, mz - hh * bmz, c);
        STAGE(w, x - h * cxx, y - h * cxy, z - h * cxz, vx - h * cvx, vy - h * cvy,
              vz - h * cvz, lx - h * clx, ly - h * cly, lz - h * clz, mx - h * cmx,
              my - h * cmy, mz - h * cmz, d);
#define ADV(S, C) S = SEL(S, S - h6 * (a##C + RV(2) * (b##C + c##C) + d##C), active)
        ADV(x, xx); ADV(y, xy); ADV(z, xz);
        ADV(vx, vx); ADV(vy, vy); ADV(vz, vz);
        ADV(lx, lx); ADV(ly, ly); ADV(lz, lz);
        ADV(mx, mx); ADV(my, my); ADV(mz, mz);
#undef ADV
    }
    VSTORE(x, i, bx); VSTORE(y, i, by); VSTORE(z, i, bz);
    FIELD_ACC_FLUSH(grad, partial, i);
}
