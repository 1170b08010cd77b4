/* The voxel finite-element operator f = K u over solid voxels (issue 14).
 *
 * One work item per node of a periodic node grid (n1, n2, n3) (a box sample is padded with
 * one void layer by the host, so it never wraps). A node is corner b of the eight voxels
 * around it; for each solid one it adds row block b of the element stiffness times the
 * voxel's 24 corner displacements. Gather only: no atomics, and the sum's order is fixed,
 * so the result does not depend on the work-group size.
 *
 * NCASE load cases are done together (one read of the solid flags and the stiffness for
 * all of them). REAL is float unless the host asks for double (-DUSE_DOUBLE=1) on a device
 * that has cl_khr_fp64: the solver's CG runs in double, and a float operator limits its
 * residual to about 1e-6.
 * Reference: implicit_scaffold.mechanics.apply_stiffness (NumPy).
 */
#ifndef NCASE
#define NCASE 1
#endif
#if defined(USE_DOUBLE) && USE_DOUBLE
#pragma OPENCL EXTENSION cl_khr_fp64 : enable
typedef double real;
#else
typedef float real;
#endif

__kernel void stiffness_apply(__global const uchar *solid, __constant real *ke, __global const real *u,
                              __global real *f, const int n1, const int n2, const int n3)
{
    const int node = (int)get_global_id(0);
    const int n = n1 * n2 * n3;
    if (node >= n) return;
    const int i = node / (n2 * n3), j = (node / n3) % n2, k = node % n3;
    real acc[3 * NCASE];
    for (int c = 0; c < 3 * NCASE; ++c) acc[c] = (real)0;
    for (int b = 0; b < 8; ++b) {
        /* the voxel of which this node is corner b */
        const int ei = (i - (b & 1) + n1) % n1;
        const int ej = (j - ((b >> 1) & 1) + n2) % n2;
        const int ek = (k - ((b >> 2) & 1) + n3) % n3;
        if (!solid[(ei * n2 + ej) * n3 + ek]) continue;
        for (int a = 0; a < 8; ++a) {
            const int mi = (ei + (a & 1)) % n1;
            const int mj = (ej + ((a >> 1) & 1)) % n2;
            const int mk = (ek + ((a >> 2) & 1)) % n3;
            const int m = (mi * n2 + mj) * n3 + mk;
            __constant const real *row = ke + (3 * b) * 24 + 3 * a;
            for (int c = 0; c < NCASE; ++c) {
                const real ux = u[(3 * c + 0) * n + m];
                const real uy = u[(3 * c + 1) * n + m];
                const real uz = u[(3 * c + 2) * n + m];
                acc[3 * c + 0] += row[0] * ux + row[1] * uy + row[2] * uz;
                acc[3 * c + 1] += row[24] * ux + row[25] * uy + row[26] * uz;
                acc[3 * c + 2] += row[48] * ux + row[49] * uy + row[50] * uz;
            }
        }
    }
    for (int c = 0; c < NCASE; ++c)
        for (int d = 0; d < 3; ++d) f[(3 * c + d) * n + node] = acc[3 * c + d];
}
