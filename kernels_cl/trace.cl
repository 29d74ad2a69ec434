/* Curved-ray tracing in the optical-path form: x' = v, v' = D(x) = eta grad eta, |v| = eta.
 * INTEGRATOR_RKN4 (Sharma's Runge-Kutta-Nystrom, 3 evaluations, 4th order),
 * INTEGRATOR_RK4 (classic 4-stage on (x, v)) or INTEGRATOR_EULER, chosen at build time. */

inline void field_D(FIELD_PARAMS, realv x, realv y, realv z, realv *dx, realv *dy, realv *dz) {
    realv gx, gy, gz;
    realv eta = field_eval(FIELD_ARGS, x, y, z, &gx, &gy, &gz);
    *dx = eta * gx;
    *dy = eta * gy;
    *dz = eta * gz;
}

inline void ode_step(FIELD_PARAMS, REAL h, realv *x, realv *y, realv *z, realv *vx, realv *vy,
                     realv *vz) {
#if defined(INTEGRATOR_RKN4)
    realv ax, ay, az, bx, by, bz, cx, cy, cz;
    field_D(FIELD_ARGS, *x, *y, *z, &ax, &ay, &az);
    ax *= h; ay *= h; az *= h;
    REAL h2 = (REAL)0.5 * h, h8 = (REAL)0.125 * h;
    field_D(FIELD_ARGS, *x + h2 * *vx + h8 * ax, *y + h2 * *vy + h8 * ay,
            *z + h2 * *vz + h8 * az, &bx, &by, &bz);
    bx *= h; by *= h; bz *= h;
    field_D(FIELD_ARGS, *x + h * *vx + h2 * bx, *y + h * *vy + h2 * by, *z + h * *vz + h2 * bz,
            &cx, &cy, &cz);
    cx *= h; cy *= h; cz *= h;
    const REAL s = (REAL)1 / (REAL)6;
    *x += h * (*vx + s * (ax + RV(2) * bx));
    *y += h * (*vy + s * (ay + RV(2) * by));
    *z += h * (*vz + s * (az + RV(2) * bz));
    *vx += s * (ax + RV(4) * bx + cx);
    *vy += s * (ay + RV(4) * by + cy);
    *vz += s * (az + RV(4) * bz + cz);
#elif defined(INTEGRATOR_RK4)
    REAL h2 = (REAL)0.5 * h;
    realv k1x, k1y, k1z, k2x, k2y, k2z, k3x, k3y, k3z, k4x, k4y, k4z;
    field_D(FIELD_ARGS, *x, *y, *z, &k1x, &k1y, &k1z);
    realv u2x = *vx + h2 * k1x, u2y = *vy + h2 * k1y, u2z = *vz + h2 * k1z;
    field_D(FIELD_ARGS, *x + h2 * *vx, *y + h2 * *vy, *z + h2 * *vz, &k2x, &k2y, &k2z);
    realv u3x = *vx + h2 * k2x, u3y = *vy + h2 * k2y, u3z = *vz + h2 * k2z;
    field_D(FIELD_ARGS, *x + h2 * u2x, *y + h2 * u2y, *z + h2 * u2z, &k3x, &k3y, &k3z);
    realv u4x = *vx + h * k3x, u4y = *vy + h * k3y, u4z = *vz + h * k3z;
    field_D(FIELD_ARGS, *x + h * u3x, *y + h * u3y, *z + h * u3z, &k4x, &k4y, &k4z);
    const REAL s = h / (REAL)6;
    *x += s * (*vx + RV(2) * (u2x + u3x) + u4x);
    *y += s * (*vy + RV(2) * (u2y + u3y) + u4y);
    *z += s * (*vz + RV(2) * (u2z + u3z) + u4z);
    *vx += s * (k1x + RV(2) * (k2x + k3x) + k4x);
    *vy += s * (k1y + RV(2) * (k2y + k3y) + k4y);
    *vz += s * (k1z + RV(2) * (k2z + k3z) + k4z);
#elif defined(INTEGRATOR_EULER)
    realv ax, ay, az;
    field_D(FIELD_ARGS, *x, *y, *z, &ax, &ay, &az);
    *x += h * *vx;
    *y += h * *vy;
    *z += h * *vz;
    *vx += h * ax;
    *vy += h * ay;
    *vz += h * az;
#else
#error "no INTEGRATOR_* defined"
#endif
}

inline maskv outside_box(realv x, realv y, realv z) {
    return x < RV(BOX_LO_X) || x > RV(BOX_HI_X) || y < RV(BOX_LO_Y) || y > RV(BOX_HI_Y) ||
           z < RV(BOX_LO_Z) || z > RV(BOX_HI_Z);
}

/* Distance along the unit direction d from a point inside the box to its boundary. */
inline realv box_exit_t(realv x, realv y, realv z, realv dx, realv dy, realv dz) {
    realv tx = (SEL(RV(BOX_LO_X), RV(BOX_HI_X), dx > RV(0)) - x) / dx;
    realv ty = (SEL(RV(BOX_LO_Y), RV(BOX_HI_Y), dy > RV(0)) - y) / dy;
    realv tz = (SEL(RV(BOX_LO_Z), RV(BOX_HI_Z), dz > RV(0)) - z) / dz;
    tx = SEL(tx, RV(INFINITY), dx == RV(0));
    ty = SEL(ty, RV(INFINITY), dy == RV(0));
    tz = SEL(tz, RV(INFINITY), dz == RV(0));
    return fmax(fmin(fmin(tx, ty), tz), RV(0));
}

/* Trace rays: straight to the box, integrate inside, straight out of the exit face.
 * Outputs the exit point, the exit v (direction times |v|), a status, the step count and
 * the last state inside the box (where the backward pass starts). With ckpt_every = C > 0,
 * the state after every C-th step goes to slot (k / C - 1) of ckpt (6 columns of the padded
 * ray count per slot, max_steps / C slots): the backward pass restarts from them.
 * A step that leaves the box is undone and replaced by a straight flight from its start:
 * exact because fields are 1 with zero gradient within MARGIN (> step) of the walls. */
__kernel void trace_rays(FIELD_PARAMS, const REAL h, const int max_steps,
                         __global const REAL *ox, __global const REAL *oy,
                         __global const REAL *oz, __global const REAL *dx,
                         __global const REAL *dy, __global const REAL *dz, __global REAL *px,
                         __global REAL *py, __global REAL *pz, __global REAL *qx,
                         __global REAL *qy, __global REAL *qz, __global int *status,
                         __global int *steps, __global REAL *lx, __global REAL *ly,
                         __global REAL *lz, const int ckpt_every, __global REAL *ckpt) {
    const size_t i = get_global_id(0);
    const size_t col = get_global_size(0) * LANES;
    realv x = VLOAD(i, ox), y = VLOAD(i, oy), z = VLOAD(i, oz);
    realv ux = VLOAD(i, dx), uy = VLOAD(i, dy), uz = VLOAD(i, dz);
    realv un = rsqrt(ux * ux + uy * uy + uz * uz);
    ux *= un; uy *= un; uz *= un;

    /* slab test against the box */
    realv t1 = (RV(BOX_LO_X) - x) / ux, t2 = (RV(BOX_HI_X) - x) / ux;
    realv tmin = fmin(t1, t2), tmax = fmax(t1, t2);
    t1 = (RV(BOX_LO_Y) - y) / uy; t2 = (RV(BOX_HI_Y) - y) / uy;
    tmin = fmax(tmin, fmin(t1, t2)); tmax = fmin(tmax, fmax(t1, t2));
    t1 = (RV(BOX_LO_Z) - z) / uz; t2 = (RV(BOX_HI_Z) - z) / uz;
    tmin = fmax(tmin, fmin(t1, t2)); tmax = fmin(tmax, fmax(t1, t2));
    tmin = fmax(tmin, RV(0));
    maskv hit = tmax >= tmin;

    realv sx = x, sy = y, sz = z; /* kept for missed rays */
    realv t0 = SEL(RV(0), tmin, hit);
    x += t0 * ux; y += t0 * uy; z += t0 * uz;
    realv g0x, g0y, g0z;
    realv eta0 = field_eval(FIELD_ARGS, x, y, z, &g0x, &g0y, &g0z);
    realv vx = eta0 * ux, vy = eta0 * uy, vz = eta0 * uz;

    maskv active = hit;
    realv st = SEL(RV(ST_MISSED), RV(ST_EXITED), hit);
    realv n = RV(0);
    for (int k = 0; k < max_steps && ANY(active); ++k) {
        realv nx = x, ny = y, nz = z, nvx = vx, nvy = vy, nvz = vz;
        ode_step(FIELD_ARGS, h, &nx, &ny, &nz, &nvx, &nvy, &nvz);
        maskv bad = !isfinite(nx + ny + nz + nvx + nvy + nvz);
        maskv go = active && !outside_box(nx, ny, nz) && !bad;
        x = SEL(x, nx, go); y = SEL(y, ny, go); z = SEL(z, nz, go);
        vx = SEL(vx, nvx, go); vy = SEL(vy, nvy, go); vz = SEL(vz, nvz, go);
        st = SEL(st, RV(ST_NONFINITE), active && bad);
        n += SEL(RV(0), RV(1), go);
        active = go;
        if (ckpt_every > 0 && (k + 1) % ckpt_every == 0) {
            __global REAL *c = ckpt + (size_t)((k + 1) / ckpt_every - 1) * 6 * col;
            VSTORE(x, i, c); VSTORE(y, i, c + col); VSTORE(z, i, c + 2 * col);
            VSTORE(vx, i, c + 3 * col); VSTORE(vy, i, c + 4 * col); VSTORE(vz, i, c + 5 * col);
        }
    }
    st = SEL(st, RV(ST_TRAPPED), active);

    realv speed = sqrt(vx * vx + vy * vy + vz * vz);
    realv iv = RV(1) / speed;
    realv ex = vx * iv, ey = vy * iv, ez = vz * iv;
    VSTORE(x, i, lx); VSTORE(y, i, ly); VSTORE(z, i, lz);
    maskv out = st == RV(ST_EXITED);
    realv te = SEL(RV(0), box_exit_t(x, y, z, ex, ey, ez), out);
    x += te * ex; y += te * ey; z += te * ez;
    maskv missed = st == RV(ST_MISSED);
    x = SEL(x, sx, missed); y = SEL(y, sy, missed); z = SEL(z, sz, missed);
    vx = SEL(vx, ux, missed); vy = SEL(vy, uy, missed); vz = SEL(vz, uz, missed);

    VSTORE(x, i, px); VSTORE(y, i, py); VSTORE(z, i, pz);
    VSTORE(vx, i, qx); VSTORE(vy, i, qy); VSTORE(vz, i, qz);
    VSTORE_INT(TO_INTV(st), i, status);
    VSTORE_INT(TO_INTV(n), i, steps);
}

/* Fixed number of steps from given (x, v), no box: for trajectories and oracles. */
__kernel void propagate_rays(FIELD_PARAMS, const REAL h, const int n_steps, __global REAL *px,
                             __global REAL *py, __global REAL *pz, __global REAL *qx,
                             __global REAL *qy, __global REAL *qz) {
    const size_t i = get_global_id(0);
    realv x = VLOAD(i, px), y = VLOAD(i, py), z = VLOAD(i, pz);
    realv vx = VLOAD(i, qx), vy = VLOAD(i, qy), vz = VLOAD(i, qz);
    for (int k = 0; k < n_steps; ++k)
        ode_step(FIELD_ARGS, h, &x, &y, &z, &vx, &vy, &vz);
    VSTORE(x, i, px); VSTORE(y, i, py); VSTORE(z, i, pz);
    VSTORE(vx, i, qx); VSTORE(vy, i, qy); VSTORE(vz, i, qz);
}

__kernel void eval_field(FIELD_PARAMS, __global const REAL *x, __global const REAL *y,
                         __global const REAL *z, __global REAL *eta, __global REAL *gx,
                         __global REAL *gy, __global REAL *gz) {
    const size_t i = get_global_id(0);
    realv ax, ay, az;
    realv e = field_eval(FIELD_ARGS, VLOAD(i, x), VLOAD(i, y), VLOAD(i, z), &ax, &ay, &az);
    VSTORE(e, i, eta); VSTORE(ax, i, gx); VSTORE(ay, i, gy); VSTORE(az, i, gz);
}
