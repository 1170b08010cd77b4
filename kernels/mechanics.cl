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
    /* the three planes around this node along each axis, wrapped once here (no % in the loops) */
    const int I[3] = {(i == 0 ? n1 : i) - 1, i, i + 1 == n1 ? 0 : i + 1};
    const int J[3] = {(j == 0 ? n2 : j) - 1, j, j + 1 == n2 ? 0 : j + 1};
    const int K[3] = {(k == 0 ? n3 : k) - 1, k, k + 1 == n3 ? 0 : k + 1};
    /* this node is corner b of the voxel whose low corner is node - offset(b) */
    uchar s[8];
    uchar any = 0;
#pragma unroll
    for (int b = 0; b < 8; ++b) {
        s[b] = solid[(I[1 - (b & 1)] * n2 + J[1 - ((b >> 1) & 1)]) * n3 + K[1 - ((b >> 2) & 1)]];
        any |= s[b];
    }
    for (int c = 0; c < NCASE; ++c) {
        real ax = (real)0, ay = (real)0, az = (real)0;
        if (any) {
            /* the 27 neighbours' displacements, read once */
            real U[81];
#pragma unroll
            for (int q = 0; q < 27; ++q) {
                const int m = (I[q % 3] * n2 + J[(q / 3) % 3]) * n3 + K[q / 9];
                U[3 * q + 0] = u[(3 * c + 0) * n + m];
                U[3 * q + 1] = u[(3 * c + 1) * n + m];
                U[3 * q + 2] = u[(3 * c + 2) * n + m];
            }
#pragma unroll
            for (int b = 0; b < 8; ++b) {
                if (!s[b]) continue;
#pragma unroll
                for (int a = 0; a < 8; ++a) {
                    /* corner a of that voxel is this node + offset(a) - offset(b) */
                    const int q = (1 + (a & 1) - (b & 1)) + 3 * (1 + ((a >> 1) & 1) - ((b >> 1) & 1))
                                  + 9 * (1 + ((a >> 2) & 1) - ((b >> 2) & 1));
                    __constant const real *row = ke + (3 * b) * 24 + 3 * a;
                    const real ux = U[3 * q], uy = U[3 * q + 1], uz = U[3 * q + 2];
                    ax += row[0] * ux + row[1] * uy + row[2] * uz;
                    ay += row[24] * ux + row[25] * uy + row[26] * uz;
                    az += row[48] * ux + row[49] * uy + row[50] * uz;
                }
            }
        }
        f[(3 * c + 0) * n + node] = ax;
        f[(3 * c + 1) * n + node] = ay;
        f[(3 * c + 2) * n + node] = az;
    }
}
