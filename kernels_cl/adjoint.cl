/* Adjoint-state backward pass (SPEC section 3), constant memory per ray.
 *
 * From the last in-box state (x_K, v_K) and the terminal adjoint mu(T) = dJ/dv, lambda(T) = 0,
 * integrate backwards in sigma the ray and its adjoint:
 *     x'' = D(x),  mu'' = -lambda' = H_D(x) mu,  D = eta grad eta,
 *     H_D mu = grad eta (grad eta . mu) + eta Hess(eta) mu,
 * a second-order system in y = (x, mu) with y' = (v, -lambda), so the same Runge-Kutta-Nystrom
 * step as the forward pass applies (3 field evaluations per step, 4th order). The parameter
 * gradient dJ/dtheta = int mu . dD/dtheta dsigma is integrated by Simpson's rule on the
 * step's stages (sigma, sigma - h/2, sigma - h): each stage splats its integrand with weight
 * h/6, 4h/6, h/6. The field gives field_adjoint(): eta, grad eta, Hess(eta) mu, and the
 * splat (see voxel_adjoint.cl).
 *
 * The re-integrated ray drifts from the forward one (RK steps are not time-reversible), and
 * through sharp interfaces the drift grows fast. With ckpt_every = C > 0 the ray's (x, v) is
 * reset to the forward pass's checkpoint every C steps: drift stays that of C steps, for
 * memory O(max_steps / C) per ray. Lanes are aligned on the forward step index (a lane with
 * fewer steps starts later), so that every lane meets its checkpoints together.
 *
 * A ray that wanders inside an object (repeated reflection off a smooth interface) has an
 * adjoint that grows exponentially backwards: its derivative is exact only for perturbations
 * far below any useful step, and one such ray outweighs thousands of others. With
 * growth_max = G > 0 a ray's backward pass stops once |mu| exceeds G |mu(T)| (a truncated
 * adjoint); its contributions nearer the exit are kept. growth returns max |mu| / |mu(T)|
 * along the integrated part of each ray. */

/* Fields accumulate in private memory what they can (a voxel grid: the cell a ray is
 * in; shared MLP weights: the whole ray) and reach global memory when that changes or at
 * the end (FIELD_ACC_FLUSH). */
#ifndef FIELD_ACC_DECL
#define FIELD_ACC_DECL
#define FIELD_ACC_PARAM
#define FIELD_ACC_ARG
#define FIELD_ACC_FLUSH(grad, partial, gid)
#endif

/* f(y) = (D(x), H_D(x) mu); splats w * (mu . dD/dtheta) on the way. */
inline void adjoint_f(FIELD_PARAMS, __global REAL *grad FIELD_ACC_PARAM, realv w, realv x,
                      realv y, realv z, realv mx, realv my, realv mz, realv *fx, realv *fy,
                      realv *fz, realv *fmx, realv *fmy, realv *fmz) {
    realv gx, gy, gz, hx, hy, hz;
    realv eta = field_adjoint(FIELD_ARGS, x, y, z, mx, my, mz, w, &gx, &gy, &gz, &hx, &hy, &hz,
                              grad FIELD_ACC_ARG);
    *fx = eta * gx;
    *fy = eta * gy;
    *fz = eta * gz;
    realv gm = gx * mx + gy * my + gz * mz;
    *fmx = gx * gm + eta * hx;
    *fmy = gy * gm + eta * hy;
    *fmz = gz * gm + eta * hz;
}

/* One backward RKN step k = -h of y = (x, mu), y' = (v, nu), in the lanes of `active`;
 * the stages splat w * (mu . dD/dtheta) with Simpson's weights (w is 0 in other lanes). */
#define ADJ_STATE realv *x, realv *y, realv *z, realv *vx, realv *vy, realv *vz, realv *mx, \
                  realv *my, realv *mz, realv *nx, realv *ny, realv *nz
inline void adjoint_step(FIELD_PARAMS, __global REAL *grad FIELD_ACC_PARAM, const REAL h,
                         maskv active, ADJ_STATE) {
    const REAL k = -h, k2 = (REAL)0.5 * k, k8 = (REAL)0.125 * k, s6 = (REAL)1 / (REAL)6;
    realv w = SEL(RV(0), RV(h * s6), active);
    realv ax, ay, az, amx, amy, amz, bx_, by_, bz_, bmx, bmy, bmz;
    realv cx, cy, cz, cmx, cmy, cmz;
    adjoint_f(FIELD_ARGS, grad FIELD_ACC_ARG, w, *x, *y, *z, *mx, *my, *mz, &ax, &ay, &az, &amx,
              &amy, &amz);
    ax *= k; ay *= k; az *= k; amx *= k; amy *= k; amz *= k;
    adjoint_f(FIELD_ARGS, grad FIELD_ACC_ARG, RV(4) * w, *x + k2 * *vx + k8 * ax,
              *y + k2 * *vy + k8 * ay, *z + k2 * *vz + k8 * az, *mx + k2 * *nx + k8 * amx,
              *my + k2 * *ny + k8 * amy, *mz + k2 * *nz + k8 * amz, &bx_, &by_, &bz_, &bmx,
              &bmy, &bmz);
    bx_ *= k; by_ *= k; bz_ *= k; bmx *= k; bmy *= k; bmz *= k;
    adjoint_f(FIELD_ARGS, grad FIELD_ACC_ARG, w, *x + k * *vx + k2 * bx_,
              *y + k * *vy + k2 * by_, *z + k * *vz + k2 * bz_, *mx + k * *nx + k2 * bmx,
              *my + k * *ny + k2 * bmy, *mz + k * *nz + k2 * bmz, &cx, &cy, &cz, &cmx, &cmy,
              &cmz);
    cx *= k; cy *= k; cz *= k; cmx *= k; cmy *= k; cmz *= k;
#define ADV(P, V, A, B, C)                                                                   \
    *P = SEL(*P, *P + k * (*V + s6 * (A + RV(2) * B)), active);                              \
    *V = SEL(*V, *V + s6 * (A + RV(4) * B + C), active)
    ADV(x, vx, ax, bx_, cx); ADV(y, vy, ay, by_, cy); ADV(z, vz, az, bz_, cz);
    ADV(mx, nx, amx, bmx, cmx); ADV(my, ny, amy, bmy, cmy); ADV(mz, nz, amz, bmz, cmz);
#undef ADV
}

/* Both variants of the backward pass below share their signature, their start and end, and
 * the adjoint-growth cap. y = (x, mu), y' = (v, nu) with nu = -lambda; the step k = -h runs
 * backwards. */
#define ADJOINT_RAYS_KERNEL                                                                    \
    __kernel void adjoint_rays(                                                                \
        FIELD_PARAMS, const REAL h, __global const REAL *pxk, __global const REAL *pyk,        \
        __global const REAL *pzk, __global const REAL *qxk, __global const REAL *qyk,          \
        __global const REAL *qzk, __global const int *steps, __global const REAL *mux,         \
        __global const REAL *muy, __global const REAL *muz, __global REAL *grad,               \
        __global REAL *partial, __global REAL *bx, __global REAL *by, __global REAL *bz,       \
        const int max_steps, const int ckpt_every, __global const REAL *ckpt,                  \
        __global REAL *snap, const REAL growth_max, __global REAL *growth, __global REAL *oax,  \
        __global REAL *oay, __global REAL *oaz SKIP_ARG)

/* worst: largest distance from a checkpoint when the ray reached it */
#define ADJOINT_RAY_BEGIN                                                                      \
    const size_t i = get_global_id(0);                                                         \
    const size_t col = get_global_size(0) * LANES;                                             \
    realv x = VLOAD(i, pxk), y = VLOAD(i, pyk), z = VLOAD(i, pzk);                             \
    realv vx = VLOAD(i, qxk), vy = VLOAD(i, qyk), vz = VLOAD(i, qzk);                          \
    realv mx = VLOAD(i, mux), my = VLOAD(i, muy), mz = VLOAD(i, muz);                          \
    realv nx = RV(0), ny = RV(0), nz = RV(0);                                                  \
    FIELD_ACC_DECL                                                                             \
    realv worst = RV(0);                                                                       \
    const realv inv_m0 = RV(1) / fmax(mx * mx + my * my + mz * mz, RV(1e-30));                 \
    const realv g2 = RV(growth_max * growth_max);                                              \
    realv grown = RV(1), alive = RV(1)

/* a ray stops once its adjoint grew past growth_max (0: never) */
#define ADJOINT_GROWTH(active)                                                                 \
    {                                                                                          \
        realv m2 = (mx * mx + my * my + mz * mz) * inv_m0;                                     \
        grown = SEL(grown, fmax(grown, m2), active);                                           \
        if (growth_max > (REAL)0)                                                              \
            alive = SEL(alive, RV(0), (active) && m2 > g2);                                    \
    }

/* oa: dJ/dx at the entry, lambda = -nu (0 where the cap cut the ray: not its origin's) */
#define ADJOINT_RAY_END                                                                        \
    VSTORE(x, i, bx); VSTORE(y, i, by); VSTORE(z, i, bz); VSTORE(worst, i, snap);              \
    VSTORE(sqrt(grown), i, growth);                                                            \
    VSTORE(SEL(RV(0), -nx, alive > RV(0)), i, oax);                                            \
    VSTORE(SEL(RV(0), -ny, alive > RV(0)), i, oay);                                            \
    VSTORE(SEL(RV(0), -nz, alive > RV(0)), i, oaz);                                            \
    FIELD_ACC_FLUSH(grad, partial, i)

#ifndef SKIP_EMPTY
ADJOINT_RAYS_KERNEL {
    ADJOINT_RAY_BEGIN;
    realv n = TO_REALV(VLOAD(i, steps));
    /* s: forward index of the state the step starts from */
    for (int s = max_steps; s > 0; --s) {
        maskv active = RV(s) <= n && alive > RV(0);
        if (!ANY(active))
            continue;
        adjoint_step(FIELD_ARGS, grad FIELD_ACC_ARG, h, active, &x, &y, &z, &vx, &vy, &vz, &mx,
                     &my, &mz, &nx, &ny, &nz);
        ADJOINT_GROWTH(active);
        if (ckpt_every > 0 && (s - 1) % ckpt_every == 0 && s > 1) {
            __global const REAL *c = ckpt + (size_t)((s - 1) / ckpt_every - 1) * 6 * col;
            realv cx_ = VLOAD(i, c), cy_ = VLOAD(i, c + col), cz_ = VLOAD(i, c + 2 * col);
            realv ex = x - cx_, ey = y - cy_, ez = z - cz_;
            worst = SEL(worst, fmax(worst, sqrt(ex * ex + ey * ey + ez * ez)), active);
            x = SEL(x, cx_, active);
            y = SEL(y, cy_, active);
            z = SEL(z, cz_, active);
            vx = SEL(vx, VLOAD(i, c + 3 * col), active);
            vy = SEL(vy, VLOAD(i, c + 4 * col), active);
            vz = SEL(vz, VLOAD(i, c + 5 * col), active);
        }
    }
    ADJOINT_RAY_END;
}
#else
/* With empty-space skipping: `steps` holds each ray's lattice index (trace_rays), and the
 * ray goes back along the same lattice, flying straight through empty cells as the forward
 * pass did: there D = 0 and H_D = 0, so x and mu move linearly, exactly. What is dropped is
 * the splat of mu . dD/dtheta along the flights: zero for a level set (eta is flat there
 * whatever phi's nodes do, off the band), and for other fields zero for every parameter
 * whose support lies in occupied cells (the fit's occupancy covers every trainable one).
 * Lanes keep their own lattice index and meet their checkpoints (indexed by it) apart. */
inline realv ckpt_gather(__global const REAL *ckpt, size_t col, size_t i, int every,
                         int slots, maskv mask, realv s, int comp, realv keep) {
    REAL a[3][LANES];
    VSTORE(SEL(RV(0), RV(1), mask), 0, a[0]); VSTORE(s, 0, a[1]); VSTORE(keep, 0, a[2]);
    for (int l = 0; l < LANES; ++l) {
        int j = (int)a[1][l];
        if (a[0][l] != (REAL)0 && j >= every && j % every == 0 && j / every <= slots)
            a[2][l] = ckpt[(size_t)(j / every - 1) * 6 * col + comp * col + i * LANES + l];
    }
    return VLOAD(0, a[2]);
}

ADJOINT_RAYS_KERNEL {
    ADJOINT_RAY_BEGIN;
    realv s = TO_REALV(VLOAD(i, steps)); /* lattice index of the state */
    const int slots = ckpt_every > 0 ? max(max_steps / ckpt_every, 1) : 0;
    /* each iteration flies or steps at least one lattice index: the loop ends */
    for (int it = 0; it < 2 * max_steps + 2; ++it) {
        maskv active = s > RV(0) && alive > RV(0);
        if (!ANY(active))
            break;
        realv sp = sqrt(vx * vx + vy * vy + vz * vz);
        realv L = empty_jump(fp, occ, x, y, z, -vx / sp, -vy / sp, -vz / sp);
        realv nj = fmin(floor(L / (sp * h)), s);
        maskv fly = active && nj > RV(0);
        realv back = -nj * h;
        x = SEL(x, x + back * vx, fly); y = SEL(y, y + back * vy, fly);
        z = SEL(z, z + back * vz, fly);
        mx = SEL(mx, mx + back * nx, fly); my = SEL(my, my + back * ny, fly);
        mz = SEL(mz, mz + back * nz, fly);
        maskv stepping = active && !fly;
        if (ANY(stepping))
            adjoint_step(FIELD_ARGS, grad FIELD_ACC_ARG, h, stepping, &x, &y, &z, &vx, &vy, &vz,
                         &mx, &my, &mz, &nx, &ny, &nz);
        s -= SEL(RV(0), SEL(RV(1), nj, fly), active);
        ADJOINT_GROWTH(active);
        if (ckpt_every > 0) {
            realv sc = s - floor(s / RV(ckpt_every)) * RV(ckpt_every);
            maskv at = active && sc == RV(0) && s >= RV(ckpt_every) &&
                       s <= RV((REAL)slots * ckpt_every);
            if (ANY(at)) {
                realv cx_ = ckpt_gather(ckpt, col, i, ckpt_every, slots, at, s, 0, x);
                realv cy_ = ckpt_gather(ckpt, col, i, ckpt_every, slots, at, s, 1, y);
                realv cz_ = ckpt_gather(ckpt, col, i, ckpt_every, slots, at, s, 2, z);
                realv ex = x - cx_, ey = y - cy_, ez = z - cz_;
                worst = SEL(worst, fmax(worst, sqrt(ex * ex + ey * ey + ez * ez)), at);
                x = cx_; y = cy_; z = cz_;
                vx = ckpt_gather(ckpt, col, i, ckpt_every, slots, at, s, 3, vx);
                vy = ckpt_gather(ckpt, col, i, ckpt_every, slots, at, s, 4, vy);
                vz = ckpt_gather(ckpt, col, i, ckpt_every, slots, at, s, 5, vz);
            }
        }
    }
    ADJOINT_RAY_END;
}
#endif
