/* The voxel finite-element operator f = K u over solid voxels (issue 14), and the product of a
 * coarse level of the multigrid preconditioner.
 *
 * All gather: one work item per node of a periodic node grid (n1, n2, n3) (a box sample is
 * padded with one void layer by the host, so it never wraps). A node is corner b of the eight
 * voxels (elements) around it; for each one it adds row block b of that element's matrix times
 * the element's 24 corner displacements. No atomics, and the sum's order is fixed, so the
 * result does not depend on the work-group size.
 *
 * NCASE load cases are done together (one read of the flags and the matrices for all of them),
 * from case `first` of u and f. REAL is float unless the host asks for double (-DUSE_DOUBLE=1)
 * on a device that has cl_khr_fp64: the solver's CG runs in double, and a float operator limits
 * its residual to about 1e-6.
 */
#ifndef NCASE
#define NCASE 1
#endif
/* VOTE=1 (the host passes it where the device has cl_intel_subgroups, whose sub-group is the
 * vector a CPU runtime packs work items into): the 3-D kernels' rows decide whether to skip the
 * products once per vector, by a sub-group vote, instead of per work item. Left per work item, the
 * Intel CPU runtime ran the products under a mask in every vector, touched or not: on the 128^3
 * benchmark scaffold stiffness_rows took 21.8 ms a case, and an all-void grid still 15.9 ms; with
 * the vote 13.3 and 4.4 ms, the results bitwise the same (an untouched node's sum is its 0/1
 * weights times the products, 0 either way). In the benchmark's solve, the fine product fell from
 * 24.9 to 15.5 ms a case and pattern_rows' six cases from 66.9 to 31.2 ms. The ends kernels (two
 * work items a row) keep the per-item test: there the vote made them 4.6 times slower. */
#ifndef VOTE
#define VOTE 0
#endif
#if VOTE
#define VECTOR_ANY(x) sub_group_any(x)
#else
#define VECTOR_ANY(x) (x)
#endif
#if defined(USE_DOUBLE) && USE_DOUBLE
#pragma OPENCL EXTENSION cl_khr_fp64 : enable
typedef double real;
#else
typedef float real;
#endif

/* A coarse level: each element has its own 24 x 24 matrix; `owner` holds its row in `mats`
 * (-1: no solid under it). One work item per node of a 1-D range. With -DADD=1 the product is
 * added to f, and a node no element of `owner` touches is left as it is (the first coarse level's
 * elements that pattern_rows does not cover: see there).
 * Reference: implicit_scaffold.multigrid.Level.apply (numba). */
__kernel void stiffness_apply(__global const int *owner, __global const real *mats, __global const real *u,
                              __global real *f, const int n1, const int n2, const int n3, const int first)
{
    const int node = (int)get_global_id(0);
    const int n = n1 * n2 * n3;
    if (node >= n) return;
    /* the NCASE cases from case `first` of the vectors */
    u += (size_t)first * 3 * n;
    f += (size_t)first * 3 * n;
    const int i = node / (n2 * n3), j = (node / n3) % n2, k = node % n3;
    /* the three planes around this node along each axis, wrapped once here (no % in the loops) */
    const int I[3] = {(i == 0 ? n1 : i) - 1, i, i + 1 == n1 ? 0 : i + 1};
    const int J[3] = {(j == 0 ? n2 : j) - 1, j, j + 1 == n2 ? 0 : j + 1};
    const int K[3] = {(k == 0 ? n3 : k) - 1, k, k + 1 == n3 ? 0 : k + 1};
    /* this node is corner b of the element whose low corner is node - offset(b) */
    int s[8];
    int any = 0;
#pragma unroll
    for (int b = 0; b < 8; ++b) {
        s[b] = owner[(I[1 - (b & 1)] * n2 + J[1 - ((b >> 1) & 1)]) * n3 + K[1 - ((b >> 2) & 1)]];
        any |= s[b] >= 0;
    }
#if defined(ADD) && ADD
    if (!any) return;
#endif
    real acc[3 * NCASE];
#pragma unroll
    for (int t = 0; t < 3 * NCASE; ++t) acc[t] = (real)0;
    if (any) {
        /* the 27 neighbours, wrapped once; each 3 x 3 block of a matrix is read once for all
           the cases (a coarse level's matrices differ from element to element) */
        int nb[27];
        for (int q = 0; q < 27; ++q) nb[q] = (I[q % 3] * n2 + J[(q / 3) % 3]) * n3 + K[q / 9];
        for (int b = 0; b < 8; ++b) {
            if (s[b] < 0) continue;
            for (int a = 0; a < 8; ++a) {
                /* corner a of that element is this node + offset(a) - offset(b) */
                const int q = (1 + (a & 1) - (b & 1)) + 3 * (1 + ((a >> 1) & 1) - ((b >> 1) & 1))
                              + 9 * (1 + ((a >> 2) & 1) - ((b >> 2) & 1));
                __global const real *row = mats + (size_t)s[b] * 576 + (3 * b) * 24 + 3 * a;
                const real k00 = row[0], k01 = row[1], k02 = row[2];
                const real k10 = row[24], k11 = row[25], k12 = row[26];
                const real k20 = row[48], k21 = row[49], k22 = row[50];
                const int m = nb[q];
#pragma unroll
                for (int c = 0; c < NCASE; ++c) {
                    const real ux = u[(3 * c) * n + m], uy = u[(3 * c + 1) * n + m], uz = u[(3 * c + 2) * n + m];
                    acc[c] += k00 * ux + k01 * uy + k02 * uz;
                    acc[NCASE + c] += k10 * ux + k11 * uy + k12 * uz;
                    acc[2 * NCASE + c] += k20 * ux + k21 * uy + k22 * uz;
                }
            }
        }
    }
    for (int c = 0; c < NCASE; ++c) {
#if defined(ADD) && ADD
        f[(3 * c + 0) * n + node] += acc[c];
        f[(3 * c + 1) * n + node] += acc[NCASE + c];
        f[(3 * c + 2) * n + node] += acc[2 * NCASE + c];
#else
        f[(3 * c + 0) * n + node] = acc[c];
        f[(3 * c + 1) * n + node] = acc[NCASE + c];
        f[(3 * c + 2) * n + node] = acc[2 * NCASE + c];
#endif
    }
}

/* The start of a node function of the 3-D kernels (stiffness_node, pattern_node): n, and the
 * nine rows (i', j') around node (i, j, k), each + K: uniform over a row's work items */
#define NODE_ROWS                                                                                          \
    const int n = n1 * n2 * n3;                                                                            \
    const int I0 = (i == 0 ? n1 : i) - 1, I2 = i + 1 == n1 ? 0 : i + 1;                                    \
    const int J0 = (j == 0 ? n2 : j) - 1, J2 = j + 1 == n2 ? 0 : j + 1;                                    \
    const int R[9] = {(I0 * n2 + J0) * n3, (i * n2 + J0) * n3, (I2 * n2 + J0) * n3,                        \
                      (I0 * n2 + j) * n3,  (i * n2 + j) * n3,  (I2 * n2 + j) * n3,                         \
                      (I0 * n2 + J2) * n3, (i * n2 + J2) * n3, (I2 * n2 + J2) * n3};                       \
    const int K[3] = {K0, k, K2};

/* The 3-D kernels' arguments, and their bodies over a node function: <name>_rows covers
 * k = 1 .. n3 - 2 (gid 0 + 1), whose neighbours k - 1, k + 1 need no wrap (contiguous loads), and
 * j = gid 1 < n2 (the host rounds that range up to its work groups' rows);
 * <name>_ends covers k = 0 and k = n3 - 1 (gid 0 = 0, 1), wrapped. */
#define NODE_ARGS                                                                                          \
    __global const uchar *flags, __constant real *mat, __global const real *u, __global real *f, const int n1, \
        const int n2, const int n3, const int first
#define ROWS_BODY(node_fn)                                                                                 \
    {                                                                                                      \
        const int k = (int)get_global_id(0) + 1;                                                           \
        if (k >= n3 - 1 || (int)get_global_id(1) >= n2) return;                                           \
        node_fn(flags, mat, u, f, n1, n2, n3, first, (int)get_global_id(2), (int)get_global_id(1), k, k - 1, \
                k + 1, VOTE);                                                                              \
    }
#define ENDS_BODY(node_fn)                                                                                 \
    {                                                                                                      \
        const int g = (int)get_global_id(0);                                                               \
        if (g >= 2 || (g == 1 && n3 == 1)) return;                                                         \
        const int k = g ? n3 - 1 : 0;                                                                      \
        node_fn(flags, mat, u, f, n1, n2, n3, first, (int)get_global_id(2), (int)get_global_id(1), k,      \
                (k == 0 ? n3 : k) - 1, k + 1 == n3 ? 0 : k + 1, 0);                                        \
    }

/* The fine operator: one element matrix `ke` (in constant memory) for every solid voxel, `solid`
 * its 0/1 flags. Laid out for a CPU's vector units: a 3-D range (k, j, i), so that the work
 * items a CPU runtime packs into one vector (consecutive k) read consecutive words.
 * stiffness_rows covers k = 1 .. n3 - 2 (gid 0 + 1), whose neighbours k - 1, k + 1 need no
 * wrap (contiguous loads); stiffness_ends covers k = 0 and k = n3 - 1 (gid 0 = 0, 1), wrapped.
 *
 * The 27 neighbours are visited once each (three loads a case), and each adds its share to the
 * eight voxels' row blocks t[b] it is a corner of; a voxel's block is then added to the node's
 * sum when the voxel is solid (multiplied by its 0/1 flag: no divergent branch, and the sum's
 * order is fixed, so the result does not depend on how work items are packed). A node that
 * some solid voxel touches does 576 multiply-adds per case, in full vectors (16 floats a vector
 * on an AVX-512 CPU); a vector of nodes none of which is touched skips them (on the 128^3
 * scaffold of the benchmark 13 % of the vectors of 16, and the kernel's time fell by a quarter).
 * Reference: implicit_scaffold.mechanics.apply_stiffness (NumPy). */
/* inlined always: left as a call, the runtime vectorized it reading the rows as gathers (8 times slower) */
static inline __attribute__((always_inline)) void stiffness_node(
    __global const uchar *solid, __constant real *ke, __global const real *u, __global real *f, const int n1,
    const int n2, const int n3, const int first, const int i, const int j, const int k, const int K0, const int K2,
    const int vote)
{
    NODE_ROWS
    /* voxel b (this node its corner b) has its low corner at node - offset(b) */
    real w[8];
#pragma unroll
    for (int b = 0; b < 8; ++b)
        w[b] = solid[R[(1 - (b & 1)) + 3 * (1 - ((b >> 1) & 1))] + K[1 - ((b >> 2) & 1)]] ? (real)1 : (real)0;
    const int node = R[4] + k;
    /* a node no solid voxel touches is 0 (a vector of such nodes skips the products) */
    const int any = w[0] + w[1] + w[2] + w[3] + w[4] + w[5] + w[6] + w[7] > (real)0;
    const int go = vote ? VECTOR_ANY(any) : any;
    for (int c = first; c < first + NCASE; ++c) {
        /* size_t offsets: an int sum that may overflow would read as a gather */
        __global const real *ux = u + (size_t)(3 * c) * n, *uy = ux + n, *uz = uy + n;
        real t[24];
#pragma unroll
        for (int e = 0; e < 24; ++e) t[e] = (real)0;
        if (go) {
#pragma unroll
            for (int q = 0; q < 27; ++q) {
                /* neighbour q at offset (q % 3, q / 3 % 3, q / 9) - 1 */
                const int m = R[q % 9] + K[q / 9];
                const real vx = ux[m], vy = uy[m], vz = uz[m];
#pragma unroll
                for (int b = 0; b < 8; ++b) {
                    /* it is corner a of voxel b when offset(a) = offset(q) - 1 + offset(b) is in {0, 1}^3 */
                    const int ax = q % 3 - 1 + (b & 1), ay = (q / 3) % 3 - 1 + ((b >> 1) & 1), az = q / 9 - 1 + ((b >> 2) & 1);
                    if (ax < 0 || ax > 1 || ay < 0 || ay > 1 || az < 0 || az > 1) continue;
                    __constant const real *row = ke + (3 * b) * 24 + 3 * (ax + 2 * ay + 4 * az);
                    /* fma: one instruction each (a sum of three products was compiled as a multiply
                       and an add more) */
                    t[3 * b] = fma(row[0], vx, fma(row[1], vy, fma(row[2], vz, t[3 * b])));
                    t[3 * b + 1] = fma(row[24], vx, fma(row[25], vy, fma(row[26], vz, t[3 * b + 1])));
                    t[3 * b + 2] = fma(row[48], vx, fma(row[49], vy, fma(row[50], vz, t[3 * b + 2])));
                }
            }
        }
        real fx = (real)0, fy = (real)0, fz = (real)0;
#pragma unroll
        for (int b = 0; b < 8; ++b) {
            fx = fma(w[b], t[3 * b], fx);
            fy = fma(w[b], t[3 * b + 1], fy);
            fz = fma(w[b], t[3 * b + 2], fz);
        }
        __global real *f0 = f + (size_t)(3 * c) * n;
        f0[node] = fx;
        f0[n + node] = fy;
        f0[2 * n + node] = fz;
    }
}

__kernel void stiffness_rows(NODE_ARGS) ROWS_BODY(stiffness_node)
__kernel void stiffness_ends(NODE_ARGS) ENDS_BODY(stiffness_node)

/* The first coarse level of the multigrid, on its elements whose matrix is a 0/1 sum of eight
 * fixed ones: an element with no fixed unknown and full length along every axis has the Galerkin
 * matrix  A_e = sum over its children c (fine voxels a + 2b + 4c) of solid_c M_c,  with
 * M_c = W_c^T Ke W_c (W_c: trilinear interpolation from the element's corners to child c's).
 * `code` holds each element's 8 child bits (0: not covered here; stiffness_apply -DADD=1 adds
 * those elements after), `pm` the eight M_c (8 x 24 x 24, in constant memory).
 *
 * The structure of stiffness_node (one constant matrix, 0/1 flags), laid out the same way
 * (3-D range, rows and ends): per node, each of the 27 neighbours q gets its 3 x 3 stencil block
 * S_q = sum over the elements b around the node that contain q of sum_c w_{b,c} M_c[b, a(q, b)]
 * (64 * 72 multiply-adds a node, whatever the number of cases), then each case in turn adds
 * S_q u_q over the 27 neighbours, as stiffness_node does a case at a time. The matrices' words
 * are the same for every work item (broadcasts), the 0/1 weights and the vectors differ: the
 * runtime runs it in full vectors, where stiffness_apply gathers a matrix per node.
 * Variants measured on the 64^3 first level of the 128^3 benchmark, six cases, as a share of
 * stiffness_apply's time in the same process (Intel CPU runtime, AVX-512; the machine shared):
 * - the 27 neighbours as a loop (even under #pragma unroll): the runtime rolled it back up and
 *   read u through per-lane index arrays (gathers): 2.0 to 4.4 times stiffness_apply; hence the
 *   macros below, where q is a literal;
 * - the children's loop unrolled as well: 1.77 times (and minutes to build); by two: no gain;
 * - each neighbour's block applied to the six cases at once (18 sums): 0.88; the 27 blocks kept
 *   (S, 243 words) and the cases a loop over them, as here: 0.71;
 * - without the skip of untouched nodes: slower (172 against 144 ms; 0.90 against 0.71), though
 *   only 0.6 % of the vectors of 16 are untouched there.
 * Reference: implicit_scaffold.multigrid.Level.apply (numba). */
/* S_q of neighbour q (offset (q % 3, q / 3 % 3, q / 9) - 1): the children in a loop (the same for
   every work item), the elements unrolled: q, b and a are constants, so the matrices' words are
   read at constant offsets from pm + 576 c */
#define PATTERN_S(q)                                                                                      \
    {                                                                                                     \
        real *s = S + 9 * (q);                                                                            \
        for (int e = 0; e < 9; ++e) s[e] = (real)0;                                                       \
        _Pragma("unroll 1") for (int c = 0; c < 8; ++c)                                                   \
        {                                                                                                 \
            __constant const real *mc = pm + 576 * c;                                                     \
            _Pragma("unroll") for (int b = 0; b < 8; ++b)                                                 \
            {                                                                                             \
                const int ax = (q) % 3 - 1 + (b & 1), ay = ((q) / 3) % 3 - 1 + ((b >> 1) & 1),            \
                          az = (q) / 9 - 1 + ((b >> 2) & 1);                                              \
                if (ax < 0 || ax > 1 || ay < 0 || ay > 1 || az < 0 || az > 1) continue;                   \
                __constant const real *row = mc + (3 * b) * 24 + 3 * (ax + 2 * ay + 4 * az);              \
                const real x = (real)((cb[b] >> c) & 1);                                                  \
                s[0] = fma(row[0], x, s[0]);                                                              \
                s[1] = fma(row[1], x, s[1]);                                                              \
                s[2] = fma(row[2], x, s[2]);                                                              \
                s[3] = fma(row[24], x, s[3]);                                                             \
                s[4] = fma(row[25], x, s[4]);                                                             \
                s[5] = fma(row[26], x, s[5]);                                                             \
                s[6] = fma(row[48], x, s[6]);                                                             \
                s[7] = fma(row[49], x, s[7]);                                                             \
                s[8] = fma(row[50], x, s[8]);                                                             \
            }                                                                                             \
        }                                                                                                 \
    }
/* one case's S_q u_q (contiguous loads in pattern_rows: q is a literal) */
#define PATTERN_A(q)                                                                                      \
    {                                                                                                     \
        const real *s = S + 9 * (q);                                                                      \
        const size_t m = (size_t)(R[(q) % 9] + K[(q) / 9]);                                               \
        const real vx = ux[m], vy = uy[m], vz = uz[m];                                                    \
        fx = fma(s[0], vx, fma(s[1], vy, fma(s[2], vz, fx)));                                             \
        fy = fma(s[3], vx, fma(s[4], vy, fma(s[5], vz, fy)));                                             \
        fz = fma(s[6], vx, fma(s[7], vy, fma(s[8], vz, fz)));                                             \
    }

static inline __attribute__((always_inline)) void pattern_node(
    __global const uchar *code, __constant real *pm, __global const real *u, __global real *f, const int n1,
    const int n2, const int n3, const int first, const int i, const int j, const int k, const int K0, const int K2,
    const int vote)
{
    NODE_ROWS
    /* element b (this node its corner b) has its low corner at node - offset(b) */
    int cb[8];
    int any = 0;
#pragma unroll
    for (int b = 0; b < 8; ++b) {
        cb[b] = code[R[(1 - (b & 1)) + 3 * (1 - ((b >> 1) & 1))] + K[1 - ((b >> 2) & 1)]];
        any |= cb[b];
    }
    const int node = R[4] + k;
    /* a node no pattern element touches is 0 here (a vector of such nodes skips the products) */
    const int go = vote ? VECTOR_ANY(any) : any;
    real S[243];
    if (go) {
        PATTERN_S(0) PATTERN_S(1) PATTERN_S(2) PATTERN_S(3) PATTERN_S(4) PATTERN_S(5) PATTERN_S(6) PATTERN_S(7)
        PATTERN_S(8) PATTERN_S(9) PATTERN_S(10) PATTERN_S(11) PATTERN_S(12) PATTERN_S(13) PATTERN_S(14)
        PATTERN_S(15) PATTERN_S(16) PATTERN_S(17) PATTERN_S(18) PATTERN_S(19) PATTERN_S(20) PATTERN_S(21)
        PATTERN_S(22) PATTERN_S(23) PATTERN_S(24) PATTERN_S(25) PATTERN_S(26)
    }
    for (int c = first; c < first + NCASE; ++c) {
        /* size_t offsets: an int sum that may overflow would read as a gather */
        __global const real *ux = u + (size_t)(3 * c) * n, *uy = ux + n, *uz = uy + n;
        real fx = (real)0, fy = (real)0, fz = (real)0;
        if (go) {
            PATTERN_A(0) PATTERN_A(1) PATTERN_A(2) PATTERN_A(3) PATTERN_A(4) PATTERN_A(5) PATTERN_A(6) PATTERN_A(7)
            PATTERN_A(8) PATTERN_A(9) PATTERN_A(10) PATTERN_A(11) PATTERN_A(12) PATTERN_A(13) PATTERN_A(14)
            PATTERN_A(15) PATTERN_A(16) PATTERN_A(17) PATTERN_A(18) PATTERN_A(19) PATTERN_A(20) PATTERN_A(21)
            PATTERN_A(22) PATTERN_A(23) PATTERN_A(24) PATTERN_A(25) PATTERN_A(26)
        }
        __global real *f0 = f + (size_t)(3 * c) * n;
        f0[node] = fx;
        f0[(size_t)n + node] = fy;
        f0[(size_t)2 * n + node] = fz;
    }
}

__kernel void pattern_rows(NODE_ARGS) ROWS_BODY(pattern_node)
__kernel void pattern_ends(NODE_ARGS) ENDS_BODY(pattern_node)

/* A coarse level as assembled node stencils: `st` holds, for every node, the 3 x 3 blocks of its
 * neighbours q = 13 .. 26 (offset (q % 3, q / 3 % 3, q / 9) - 1: the node itself and the 13 "forward"
 * ones), entry x = 9 (q - 13) + 3 d + e (row d, column e) of node (row r = i n2 + j, k) at
 * st[(126 r + x) n3 + k]: a row's stencils are one contiguous block, read in order; `live` is 1 at a
 * node some element touches. A level's matrix is symmetric, so the block of a neighbour q < 13 at
 * node n is the transpose of the block of neighbour 26 - q at that neighbour, n + offset(q): read
 * there, transposed (126 words a node stored where all 27 blocks took 243: on the 128^3 benchmark
 * scaffold the 32^3 level's and those below took 58 bytes a solid voxel of the one-case solve's
 * peak, half of it now). The same sums as stiffness_apply (the elements' row blocks added per
 * neighbour by the host, implicit_scaffold.multigrid.node_stencils), in the structure of the fine
 * kernels (3-D range, rows and ends, neighbours as literals): a vector's work items read consecutive
 * words of every stencil entry and of u, where stiffness_apply gathers one element matrix per work
 * item. Each neighbour's block is read once for all NCASE cases. */
/* one neighbour's block s0 .. s8 (row-major) times its values, for every case */
#define STENCIL_MAC(q)                                                                                    \
    {                                                                                                     \
        const size_t m = (size_t)(R[(q) % 9] + K[(q) / 9]);                                               \
        _Pragma("unroll") for (int c = 0; c < NCASE; ++c)                                                 \
        {                                                                                                 \
            __global const real *ux = u + (size_t)(3 * (first + c)) * n;                                  \
            const real vx = ux[m], vy = ux[(size_t)n + m], vz = ux[(size_t)2 * n + m];                    \
            acc[3 * c] = fma(s0, vx, fma(s1, vy, fma(s2, vz, acc[3 * c])));                               \
            acc[3 * c + 1] = fma(s3, vx, fma(s4, vy, fma(s5, vz, acc[3 * c + 1])));                       \
            acc[3 * c + 2] = fma(s6, vx, fma(s7, vy, fma(s8, vz, acc[3 * c + 2])));                       \
        }                                                                                                 \
    }
/* neighbour q >= 13: its block in this node's own stencil */
#define STENCIL_OWN(q)                                                                                    \
    {                                                                                                     \
        __global const real *s = row + (size_t)(9 * ((q) - 13)) * n3;                                    \
        const real s0 = s[0], s1 = s[n3], s2 = s[2 * n3], s3 = s[3 * n3], s4 = s[4 * n3], s5 = s[5 * n3], \
                   s6 = s[6 * n3], s7 = s[7 * n3], s8 = s[8 * n3];                                       \
        STENCIL_MAC(q)                                                                                    \
    }
/* neighbour q < 13: the transpose of block 26 - q of the neighbour's stencil (its row R[q % 9], its
   node K[q / 9]: consecutive along a row, as this node's own) */
#define STENCIL_T(q)                                                                                      \
    {                                                                                                     \
        __global const real *s = st + (size_t)R[(q) % 9] * 126 + K[(q) / 9] + (size_t)(9 * (13 - (q))) * n3; \
        const real s0 = s[0], s3 = s[n3], s6 = s[2 * n3], s1 = s[3 * n3], s4 = s[4 * n3], s7 = s[5 * n3], \
                   s2 = s[6 * n3], s5 = s[7 * n3], s8 = s[8 * n3];                                       \
        STENCIL_MAC(q)                                                                                    \
    }

static inline __attribute__((always_inline)) void stencil_node(
    __global const uchar *live, __global const real *st, __global const real *u, __global real *f, const int n1,
    const int n2, const int n3, const int first, const int i, const int j, const int k, const int K0, const int K2,
    const int vote)
{
    NODE_ROWS
    const int node = R[4] + k;
    const int any = live[node];
    const int go = vote ? VECTOR_ANY(any) : any;
    /* this node's row of the stencils: its 126 entries, each a run of the row's n3 nodes */
    __global const real *row = st + (size_t)R[4] * 126 + k;
    real acc[3 * NCASE];
#pragma unroll
    for (int t = 0; t < 3 * NCASE; ++t) acc[t] = (real)0;
    /* an untouched node's stencil is 0: in a vector that runs, its sums stay 0 */
    if (go) {
        /* in the order of q, as with the 27 blocks stored */
        STENCIL_T(0) STENCIL_T(1) STENCIL_T(2) STENCIL_T(3) STENCIL_T(4) STENCIL_T(5) STENCIL_T(6) STENCIL_T(7)
        STENCIL_T(8) STENCIL_T(9) STENCIL_T(10) STENCIL_T(11) STENCIL_T(12) STENCIL_OWN(13) STENCIL_OWN(14)
        STENCIL_OWN(15) STENCIL_OWN(16) STENCIL_OWN(17) STENCIL_OWN(18) STENCIL_OWN(19) STENCIL_OWN(20)
        STENCIL_OWN(21) STENCIL_OWN(22) STENCIL_OWN(23) STENCIL_OWN(24) STENCIL_OWN(25) STENCIL_OWN(26)
    }
#pragma unroll
    for (int c = 0; c < NCASE; ++c) {
        __global real *f0 = f + (size_t)(3 * (first + c)) * n;
        f0[node] = acc[3 * c];
        f0[(size_t)n + node] = acc[3 * c + 1];
        f0[(size_t)2 * n + node] = acc[3 * c + 2];
    }
}

#define STENCIL_ARGS                                                                                       \
    __global const uchar *flags, __global const real *mat, __global const real *u, __global real *f, const int n1, \
        const int n2, const int n3, const int first
__kernel void stencil_rows(STENCIL_ARGS) ROWS_BODY(stencil_node)
__kernel void stencil_ends(STENCIL_ARGS) ENDS_BODY(stencil_node)
