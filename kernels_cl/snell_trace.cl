/* Exact Snell ray tracing through a solid: the event loop shared by the analytic solids
 * (snell.cl) and the signed-distance family (snell_sdf.cl). Built after one of them, which
 * defines hit_solid(sp, o, d, inside, &t, &n) -> 1 hit, 0 none, -1 failure (t along d, n the
 * outward unit normal, in the local frame), solid_size(sp), solid_eta(sp) and OFFSET_REL.
 * Parameters sp start with the centre (sp[0..2]) and the world -> local rotation (sp[3..11],
 * row-major), and end with the geometry from sp[GEO_AT] (common.h: the box EXITED rays leave
 * through). */

/* Status: ST_EXITED (left the object; position on the box), ST_MISSED (never hit it;
 * position = origin), ST_TRAPPED (max_events reached with another event due; position = last
 * event point), ST_NONFINITE (non-finite state, or no way out found from inside). surface:
 * the last event point (the origin for missed rays). */
__kernel void snell_trace(__global const REAL *restrict sp, const int max_events, const int n,
                          __global const REAL *ox, __global const REAL *oy,
                          __global const REAL *oz, __global const REAL *dx,
                          __global const REAL *dy, __global const REAL *dz, __global REAL *px,
                          __global REAL *py, __global REAL *pz, __global REAL *vx,
                          __global REAL *vy, __global REAL *vz, __global REAL *sx,
                          __global REAL *sy, __global REAL *sz, __global int *status,
                          __global int *events) {
    const int i = get_global_id(0);
    if (i >= n) return;
    const real3 c = r3(sp[0], sp[1], sp[2]);
    const real3 m0 = r3(sp[3], sp[4], sp[5]), m1 = r3(sp[6], sp[7], sp[8]),
                m2 = r3(sp[9], sp[10], sp[11]);
    const REAL eta = solid_eta(sp);
    const REAL eps = OFFSET_REL * solid_size(sp);

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
        int h = hit_solid(sp, o, d, inside, &t, &nrm);
        if (h < 0) { /* the shape's root finding failed */
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
        /* step off the surface to the new side along the new ray (the line is unchanged):
         * a distance eps from the surface, at most 1000 eps along the ray */
        o = p + (eps / fmax(fabs(cn), (REAL)1e-3)) * dn;
        surf = p;
        d = dn;
        ev++;
    }
    /* back to the world frame: x = c + M^T l */
    real3 dwo = d.x * m0 + d.y * m1 + d.z * m2;
    real3 sw = c + surf.x * m0 + surf.y * m1 + surf.z * m2;
    real3 pos = sw;
    if (st == ST_MISSED) {
        dwo = dw;
        sw = pos = ow;
    } else if (st == ST_EXITED) {
        pos = sw + box_exit_distance(sp, sw, dwo) * dwo;
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
