/* The neural field of the Meridian-style baseline (clrefract/baselines/neural.py): density and
 * colour at points from field_hashgrid.cl's multi-resolution hash encoding (its hg_axis,
 * hg_indices, hg_gather and HG_NORMALISE, built with HG_SMOOTH 0: trilinear, no spatial
 * derivatives needed) and an MLP with a 4-unit head:
 *     o = MLP(features(x)),  sigma = softplus(o_0) per mm,  rgb = sigmoid(o_1..3).
 * fd: the tables, then the hidden layers as in field_hashgrid.cl (HG_W0 .. HG_B1), then the
 * head W (4 x HG_HIDDEN, row-major) and b (4). Points and outputs are structure of arrays,
 * padded to a multiple of LANES; compositing along the rays is the host's.
 * The backward pass takes dLoss/d(sigma, rgb) per point: table entries by atomic adds, the
 * MLP summed per work-item into its own slot of `partial` (as hashgrid_adjoint.cl).
 * Needs common.h and field_hashgrid.cl.
 */

#define NF_BO (HG_WO + 4 * HG_HIDDEN)
#define NF_NSHARED (NF_BO + 4 - HG_MLP_OFFSET)
#define NF_A(off) ((off) - HG_MLP_OFFSET)

/* Corner weights of level l at normalised points (cx cy cz) and their table indices. */
HG_INLINE void nf_corners(FIELD_PARAMS, const int l, realv cx, realv cy, realv cz, uint *idx,
                          realv *w) {
    const REAL n = fp[1 + l];
    realv s[3], unused, unused2;
    hg_uintv i = hg_axis(cx, RV(0), n, (REAL)0, &s[0], &unused, &unused2);
    hg_uintv j = hg_axis(cy, RV(0), n, (REAL)0, &s[1], &unused, &unused2);
    hg_uintv k = hg_axis(cz, RV(0), n, (REAL)0, &s[2], &unused, &unused2);
    hg_indices(fp, l, n, i, j, k, idx);
    realv ax[2] = {RV(1) - s[0], s[0]}, ay[2] = {RV(1) - s[1], s[1]},
          az[2] = {RV(1) - s[2], s[2]};
    for (int c = 0; c < 8; ++c) w[c] = ax[c >> 2] * ay[(c >> 1) & 1] * az[c & 1];
}

/* The L*F features of the LANES points. */
HG_INLINE void nf_encode(FIELD_PARAMS, realv x, realv y, realv z, realv *feat) {
    HG_NORMALISE
    for (int l = 0; l < HG_LEVELS; ++l) {
        uint idx[8 * LANES];
        REAL vals[8 * HG_FEATURES * LANES];
        realv w[8];
        nf_corners(FIELD_ARGS, l, cx, cy, cz, idx, w);
        hg_gather(fd, l, idx, vals);
        for (int f = 0; f < HG_FEATURES; ++f) {
            realv v = RV(0);
            for (int c = 0; c < 8; ++c) v += w[c] * VLOAD(c * HG_FEATURES + f, vals);
            feat[l * HG_FEATURES + f] = v;
        }
    }
}

/* Feature adjoints fb to the table entries: atomic adds of fb w per corner. */
HG_INLINE void nf_encode_reverse(FIELD_PARAMS, __global REAL *grad, realv x, realv y, realv z,
                                 const realv *fb) {
    HG_NORMALISE
    for (int l = 0; l < HG_LEVELS; ++l) {
        uint idx[8 * LANES];
        REAL tv[8 * HG_FEATURES * LANES];
        realv w[8];
        nf_corners(FIELD_ARGS, l, cx, cy, cz, idx, w);
        for (int c = 0; c < 8; ++c)
            for (int f = 0; f < HG_FEATURES; ++f)
                VSTORE(fb[l * HG_FEATURES + f] * w[c], c * HG_FEATURES + f, tv);
        hg_scatter(grad, l, idx, tv);
    }
}

/* A hidden layer: act = softplus(W a + b) and s = sigmoid(W a + b) (its derivative). */
HG_INLINE void nf_hidden(__global const REAL *W, __global const REAL *B, const int n_in,
                         const realv *a, realv *act, realv *s) {
    for (int j = 0; j < HG_HIDDEN; ++j) {
        __global const REAL *w = W + j * n_in;
        realv v = RV(B[j]);
        for (int i = 0; i < n_in; ++i) v += w[i] * a[i];
        act[j] = hg_softplus(v, &s[j]);
    }
}

/* Forward pass: features, hidden activations (with their sigmoids) and the head's o[4]. */
#if HG_LAYERS == 2
#define NF_TAPE                                                                              \
    realv feat[HG_NF], a1[HG_HIDDEN], s1[HG_HIDDEN], a2[HG_HIDDEN], s2[HG_HIDDEN], o[4];    \
    nf_encode(FIELD_ARGS, x, y, z, feat);                                                    \
    nf_hidden(fd + HG_W0, fd + HG_B0, HG_NF, feat, a1, s1);                                  \
    nf_hidden(fd + HG_W1, fd + HG_B1, HG_HIDDEN, a1, a2, s2);                                \
    realv *aL = a2, *sL = s2;                                                                \
    nf_head(fd, aL, o);
#else
#define NF_TAPE                                                                              \
    realv feat[HG_NF], a1[HG_HIDDEN], s1[HG_HIDDEN], o[4];                                   \
    nf_encode(FIELD_ARGS, x, y, z, feat);                                                    \
    nf_hidden(fd + HG_W0, fd + HG_B0, HG_NF, feat, a1, s1);                                  \
    realv *aL = a1, *sL = s1;                                                                \
    nf_head(fd, aL, o);
#endif

HG_INLINE void nf_head(__global const REAL *restrict fd, const realv *a, realv *o) {
    for (int k = 0; k < 4; ++k) {
        __global const REAL *w = fd + HG_WO + k * HG_HIDDEN;
        realv v = RV(fd[NF_BO + k]);
        for (int j = 0; j < HG_HIDDEN; ++j) v += w[j] * a[j];
        o[k] = v;
    }
}

/* Reverse of a dense layer h = W a + b given hb: dW += hb a^T, db += hb into acc (the
 * layer's place in the work-item's slot), ab = W^T hb. */
HG_INLINE void nf_layer_reverse(__global const REAL *W, const int n_out, const int n_in,
                                __global REAL *accw, __global REAL *accb, const realv *hb,
                                const realv *a, realv *ab) {
    for (int i = 0; i < n_in; ++i) ab[i] = RV(0);
    for (int j = 0; j < n_out; ++j) {
        const realv b = hb[j];
        __global const REAL *w = W + j * n_in;
        __global REAL *g = accw + j * n_in;
        accb[j] += HG_HSUM(b);
        for (int i = 0; i < n_in; ++i) {
            g[i] += HG_HSUM(b * a[i]);
            ab[i] += w[i] * b;
        }
    }
}

#define NF_LOAD_POINTS                                                                       \
    realv x = VLOAD(g, px), y = VLOAD(g, py), z = VLOAD(g, pz);

/* On CPUs (LANES > 1) PoCL runs a work-group as a loop over its work-items with a copy of
 * the kernel's private arrays for each on one thread's stack (a crash with large groups);
 * the per-point work in functions that are never inlined keeps one copy per call. */
#if LANES > 1
#define NF_FN __attribute__((noinline))
#else
#define NF_FN inline
#endif

NF_FN void nf_eval_group(FIELD_PARAMS, __global const REAL *px, __global const REAL *py,
                         __global const REAL *pz, const int g, const int n_pad,
                         __global REAL *out) {
    NF_LOAD_POINTS
    NF_TAPE
    realv unused;
    VSTORE(hg_softplus(o[0], &unused), g, out);
    for (int k = 1; k < 4; ++k) VSTORE(hg_sigmoid(o[k]), g, out + k * n_pad);
}

__kernel void nf_eval(FIELD_PARAMS, __global const REAL *px, __global const REAL *py,
                      __global const REAL *pz, const int groups, const int n_pad,
                      __global REAL *out) {
    const int g = get_global_id(0);
    if (g < groups) nf_eval_group(FIELD_ARGS, px, py, pz, g, n_pad, out);
}

/* Adds one point group's gradient: tables to grad (atomics), the MLP to acc. */
NF_FN void nf_backward_group(FIELD_PARAMS, __global const REAL *px, __global const REAL *py,
                             __global const REAL *pz, const int g, const int n_pad,
                             __global const REAL *adj, __global REAL *grad,
                             __global REAL *acc) {
    realv ob[4];
    for (int k = 0; k < 4; ++k) ob[k] = VLOAD(g, adj + k * n_pad);
    if (!ANY(ob[0] != RV(0) || ob[1] != RV(0) || ob[2] != RV(0) || ob[3] != RV(0))) return;
    NF_LOAD_POINTS
    NF_TAPE
    /* through the output maps: softplus' = sigmoid, sigmoid' = c (1 - c) */
    ob[0] *= hg_sigmoid(o[0]);
    for (int k = 1; k < 4; ++k) {
        realv c = hg_sigmoid(o[k]);
        ob[k] *= c * (RV(1) - c);
    }
    realv hb[HG_HIDDEN], ab[HG_HIDDEN > HG_NF ? HG_HIDDEN : HG_NF];
    nf_layer_reverse(fd + HG_WO, 4, HG_HIDDEN, acc + NF_A(HG_WO), acc + NF_A(NF_BO), ob, aL,
                     hb);
    for (int j = 0; j < HG_HIDDEN; ++j) hb[j] *= sL[j];
#if HG_LAYERS == 2
    nf_layer_reverse(fd + HG_W1, HG_HIDDEN, HG_HIDDEN, acc + NF_A(HG_W1), acc + NF_A(HG_B1), hb,
                     a1, ab);
    for (int j = 0; j < HG_HIDDEN; ++j) hb[j] = ab[j] * s1[j];
#endif
    nf_layer_reverse(fd + HG_W0, HG_HIDDEN, HG_NF, acc + NF_A(HG_W0), acc + NF_A(HG_B0), hb,
                     feat, ab);
    nf_encode_reverse(FIELD_ARGS, grad, x, y, z, ab);
}

/* adj: dLoss/d(sigma, r, g, b) per point (4 x n_pad); grad: the tables' gradient (fd's
 * layout); partial: NF_NSHARED numbers per work-item, the MLP's gradient, for the host to
 * sum. Each work-item takes point groups gid, gid + size, ... */
__kernel void nf_backward(FIELD_PARAMS, __global const REAL *px, __global const REAL *py,
                          __global const REAL *pz, const int groups, const int n_pad,
                          __global const REAL *adj, __global REAL *grad,
                          __global REAL *partial) {
    const int gid = get_global_id(0), size = get_global_size(0);
    __global REAL *acc = partial + (size_t)gid * NF_NSHARED;
    for (int p = 0; p < NF_NSHARED; ++p) acc[p] = 0;
    for (int g = gid; g < groups; g += size)
        nf_backward_group(FIELD_ARGS, px, py, pz, g, n_pad, adj, grad, acc);
}
