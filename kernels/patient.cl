// Patient mesh distance: exact point-to-triangle distances, under the same block
// culling as the lattice kernels (triangles are one more kind of primitive).
#include "common.cl"

// Squared distance from p to triangle t of `tris` (6 float4 each: v0, v1, v2,
// (n, n.v0) with n the unit normal of v0 v1 v2, so the vertices wind
// counter-clockwise about n as polygon_dist2 expects, and the box lo, hi).
#define TRI 6
inline float triangle_dist2(float3 p, __global const float4 *tris, int t, float *plane)
{
    const float4 nd = tris[TRI * t + 3];
    const float pd = dot(nd.xyz, p) - nd.w;
    *plane = pd * pd;
    const float3 v0 = tris[TRI * t].xyz;
    // never below the plane distance, whatever the rounding of the edge tests
    return fmax(polygon_dist2(p, nd.xyz, pd, v0, tris[TRI * t + 1].xyz, tris[TRI * t + 2].xyz, v0, 3), pd * pd);
}

// The nearest triangle nearer than `cutoff` (its index, or -1) and its squared
// distance (cutoff^2 when none). Ties go to the lowest index (the block's list is
// ascending), so the result depends neither on the order of the list nor on the
// tiling. The lists may cover a slab of the grid only: they start at block
// `first_block` of the whole grid.
#define NEAREST_TRIANGLE(best, arg)                                               \
    float best = cutoff * cutoff;                                                 \
    int arg = -1;                                                                 \
    {                                                                             \
        const int k0 = offsets[block_id - first_block], k1 = offsets[block_id - first_block + 1]; \
        for (int k = k0; k < k1; ++k) {                                           \
            const int t = items[k];                                               \
            float plane;                                                          \
            /* the box and the plane each bound the distance from below */        \
            const float3 gap = fmax(fmax(tris[TRI * t + 4].xyz - p, p - tris[TRI * t + 5].xyz), 0.0f); \
            if (dot(gap, gap) >= best) continue;                                  \
            const float4 nd = tris[TRI * t + 3];                                  \
            const float pd = dot(nd.xyz, p) - nd.w;                               \
            if (pd * pd >= best) continue;                                        \
            const float d2 = triangle_dist2(p, tris, t, &plane);                  \
            if (d2 < best) { best = d2; arg = t; }                                \
        }                                                                         \
    }

#define NEAREST_ARGS                                                              \
    __global const int *offsets, __global const int *items,                       \
    __global const float4 *tris, const float cutoff, const int first_block

// Index of the nearest triangle nearer than `cutoff`, or -1.
__kernel void triangle_nearest(__global int *nearest, VOXEL_ARGS, NEAREST_ARGS)
{
    VOXEL_SETUP
    if (!inside_tile) return;
    NEAREST_TRIANGLE(best, arg)
    nearest[OUT_INDEX] = arg;
}

// Distance to the nearest triangle, clamped at `cutoff`, in one pass: the value
// triangle_distance gives for triangle_nearest's triangle (the same squared
// distance, by the same function), bit for bit, without the index going through
// the host.
__kernel void triangle_clamped(__global float *out, VOXEL_ARGS, NEAREST_ARGS)
{
    VOXEL_SETUP
    if (!inside_tile) return;
    NEAREST_TRIANGLE(best, arg)
    out[OUT_INDEX] = arg < 0 ? cutoff : fmin(sqrt(best), cutoff);
}

// Distance from each voxel to one given triangle (`which`, tile-local, one per
// voxel; -1 gives INFINITY): the exact value once the nearest triangle is known.
__kernel void triangle_distance(
    __global float *out, VOXEL_ARGS,
    __global const int *which, __global const float4 *tris)
{
    VOXEL_SETUP
    if (!inside_tile) return;
    const int t = which[OUT_INDEX];
    float plane;
    out[OUT_INDEX] = t < 0 ? INFINITY : sqrt(triangle_dist2(p, tris, t, &plane));
}
