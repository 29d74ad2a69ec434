/* The hash grid's distillation on the device (clrefract/fields/hashgrid_device.py): a
 * least-squares fit of the MLP's output o to targets at points, as HashGridField._distil
 * does in NumPy (_forward2 and _reverse2 are the float64 reference).
 *
 * hg_points_o: o and grad o at points (LANES per work-item).
 * hg_points_reverse: the parameter gradient sum_n ob_n do/dtheta + omb_n d(mu_n . grad o)/dtheta
 * of the host's residuals (ob, omb, mu) at the same points, through hg_point_adjoint
 * (hashgrid_adjoint.cl): table entries by atomic adds into grad, the MLP's weights summed by
 * each work-item over its `per` vectors of points into its slot of `partial`. Padding lanes
 * carry ob = omb = 0 and add nothing. */

__kernel void hg_points_o(FIELD_PARAMS, __global const REAL *restrict px,
                          __global const REAL *restrict py, __global const REAL *restrict pz,
                          __global REAL *restrict o, __global REAL *restrict ox,
                          __global REAL *restrict oy, __global REAL *restrict oz) {
    const int i = get_global_id(0);
    realv feat[HG_NF], fx[HG_NF], fy[HG_NF], fz[HG_NF];
    hg_encode(FIELD_ARGS, VLOAD(i, px), VLOAD(i, py), VLOAD(i, pz), feat, fx, fy, fz);
    realv gx, gy, gz;
    VSTORE(hg_mlp(fd, feat, fx, fy, fz, &gx, &gy, &gz), i, o);
    VSTORE(gx, i, ox);
    VSTORE(gy, i, oy);
    VSTORE(gz, i, oz);
}

__kernel void hg_points_reverse(FIELD_PARAMS, const int n_vec, const int per,
                                __global const REAL *restrict px,
                                __global const REAL *restrict py,
                                __global const REAL *restrict pz,
                                __global const REAL *restrict ob,
                                __global const REAL *restrict omb,
                                __global const REAL *restrict mx,
                                __global const REAL *restrict my,
                                __global const REAL *restrict mz, __global REAL *grad,
                                __global REAL *restrict partial) {
    FIELD_ACC_DECL
    const int first = (int)get_global_id(0) * per, last = min(n_vec, first + per);
    for (int i = first; i < last; ++i) {
        realv gx, gy, gz, hx, hy, hz;
        hg_point_adjoint(FIELD_ARGS, VLOAD(i, px), VLOAD(i, py), VLOAD(i, pz), VLOAD(i, mx),
                         VLOAD(i, my), VLOAD(i, mz), RV(1), 1, VLOAD(i, ob), VLOAD(i, omb), &gx,
                         &gy, &gz, &hx, &hy, &hz, grad FIELD_ACC_ARG);
    }
}
