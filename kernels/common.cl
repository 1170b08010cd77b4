// Geometry shared by the field kernels. Coordinates are relative to the grid
// origin (mm), so float32 keeps its precision on large patients.

#ifndef BLOCK
#define BLOCK 8
#endif

// Squared distance from p to the segment [a, b].
inline float segment_dist2(float3 p, float3 a, float3 b)
{
    float3 ab = b - a;
    float3 ap = p - a;
    float len2 = dot(ab, ab);
    float t = len2 > 0.0f ? clamp(dot(ap, ab) / len2, 0.0f, 1.0f) : 0.0f;
    float3 q = ap - t * ab;
    return dot(q, q);
}

// Squared distance from p to a planar convex polygon of 3 or 4 vertices with
// unit normal n; plane_dist is dot(n, p) - dot(n, v0). The vertices wind
// counter-clockwise about n.
inline float polygon_dist2(float3 p, float3 n, float plane_dist,
                           float3 v0, float3 v1, float3 v2, float3 v3, int nv)
{
    float3 v[4] = {v0, v1, v2, v3};
    int inside = 1;
    for (int i = 0; i < nv; ++i) {
        float3 a = v[i];
        float3 b = v[(i + 1) % nv];
        if (dot(cross(b - a, p - a), n) < 0.0f) { inside = 0; break; }
    }
    if (inside) return plane_dist * plane_dist;
    float best = INFINITY;
    for (int i = 0; i < nv; ++i)
        best = fmin(best, segment_dist2(p, v[i], v[(i + 1) % nv]));
    return best;
}

// The voxel this work-item computes: global index in the whole grid and the
// index of its block. Dimension 0 is z, the fastest-varying array axis.
#define VOXEL_SETUP                                                          \
    const int gz = tile_lo_z + (int)get_global_id(0);                       \
    const int gy = tile_lo_y + (int)get_global_id(1);                       \
    const int gx = tile_lo_x + (int)get_global_id(2);                       \
    const int lz = (int)get_global_id(0);                                   \
    const int ly = (int)get_global_id(1);                                   \
    const int lx = (int)get_global_id(2);                                   \
    const int inside_tile = (lx < tile_nx) && (ly < tile_ny) && (lz < tile_nz); \
    const int block_id = ((gx / BLOCK) * blocks_y + (gy / BLOCK)) * blocks_z + (gz / BLOCK); \
    const float3 p = (float3)((float)gx, (float)gy, (float)gz) * h;

#define VOXEL_ARGS                                                           \
    const int tile_lo_x, const int tile_lo_y, const int tile_lo_z,          \
    const int tile_nx, const int tile_ny, const int tile_nz,                \
    const int blocks_y, const int blocks_z, const float h

#define OUT_INDEX (((size_t)lx * tile_ny + ly) * tile_nz + lz)
