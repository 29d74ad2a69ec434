/* Adam over one group [start, start + n) of a flat parameter vector held on the device
 * (clrefract/adam.py: Adam.step is the reference). A sparse group's entries whose gradient
 * is exactly zero keep their moments and their own step count, as instant-ngp's tables. */

__kernel void adam_step(__global REAL *restrict p, __global REAL *restrict m,
                        __global REAL *restrict v, __global int *restrict t,
                        __global const REAL *restrict g, const int start, const REAL lr,
                        const REAL b1, const REAL b2, const REAL eps, const int sparse) {
    const int j = start + (int)get_global_id(0);
    const REAL gj = g[j];
    if (sparse && gj == (REAL)0)
        return;
    const int tj = t[j] + 1;
    const REAL mj = b1 * m[j] + ((REAL)1 - b1) * gj;
    const REAL vj = b2 * v[j] + ((REAL)1 - b2) * gj * gj;
    t[j] = tj;
    m[j] = mj;
    v[j] = vj;
    const REAL mhat = mj / ((REAL)1 - pown(b1, tj));
    const REAL vhat = vj / ((REAL)1 - pown(b2, tj));
    p[j] -= lr * mhat / (sqrt(vhat) + eps);
}
