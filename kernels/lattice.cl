// Lattice fields: the paper's pores-and-channels lattice and the struts lattice.
#include "common.cl"

// Signed distance to the paper's lattice surface, negative in the solid.
//
// The surface is the union of the channels' side quads (trapezoids between a
// pore face and its window rim): |s| is the distance to the nearest quad, clamped
// at `cutoff`. The sign is positive inside the void, the union of the convex
// pieces (pores and channels), each given by its planes (inside: n.p <= d).
//
// quads: 5 float4 per quad, v0 v1 v2 v3 and (n, n.v0).
// pieces: boxes (lo, hi) and a CSR range of planes (n, d).
__kernel void lattice_paper(
    __global float *out, VOXEL_ARGS,
    __global const int *quad_offsets, __global const int *quad_items,
    __global const float4 *quads,
    __global const int *piece_offsets, __global const int *piece_items,
    __global const float4 *piece_boxes, __global const int *plane_start,
    __global const float4 *planes,
    const float cutoff)
{
    VOXEL_SETUP
    if (!inside_tile) return;

    float best = cutoff * cutoff;
    const int q0 = quad_offsets[block_id], q1 = quad_offsets[block_id + 1];
    for (int k = q0; k < q1; ++k) {
        const int q = quad_items[k];
        const float4 nd = quads[5 * q + 4];
        const float3 n = nd.xyz;
        const float pd = dot(n, p) - nd.w;
        if (pd * pd >= best) continue;
        const float d2 = polygon_dist2(p, n, pd, quads[5 * q].xyz, quads[5 * q + 1].xyz,
                                       quads[5 * q + 2].xyz, quads[5 * q + 3].xyz, 4);
        // never below the plane distance, so the skip above cannot depend on order
        best = fmin(best, fmax(d2, pd * pd));
    }
    float dist = sqrt(best);

    int in_void = 0;
    const int c0 = piece_offsets[block_id], c1 = piece_offsets[block_id + 1];
    for (int k = c0; k < c1 && !in_void; ++k) {
        const int c = piece_items[k];
        const float3 lo = piece_boxes[2 * c].xyz, hi = piece_boxes[2 * c + 1].xyz;
        if (any(p < lo) || any(p > hi)) continue;
        int inside = 1;
        for (int j = plane_start[c]; j < plane_start[c + 1]; ++j) {
            const float4 pl = planes[j];
            if (dot(pl.xyz, p) - pl.w > 0.0f) { inside = 0; break; }
        }
        in_void = inside;
    }
    out[OUT_INDEX] = in_void ? dist : -dist;
}

// Smooth-minimum distance to the struts' axes (Voronoi edges), unsigned:
// F = -k ln sum_i exp(-d_i / k) over the edges nearer than `cutoff`
// (the plain minimum when k == 0), clamped at `cutoff`. The solid is F < r.
__kernel void lattice_struts(
    __global float *out, VOXEL_ARGS,
    __global const int *seg_offsets, __global const int *seg_items,
    __global const float4 *segments,
    const float cutoff, const float k)
{
    VOXEL_SETUP
    if (!inside_tile) return;

    const int s0 = seg_offsets[block_id], s1 = seg_offsets[block_id + 1];
    float best = cutoff * cutoff;
    for (int i = s0; i < s1; ++i) {
        const int s = seg_items[i];
        best = fmin(best, segment_dist2(p, segments[2 * s].xyz, segments[2 * s + 1].xyz));
    }
    float m = sqrt(best);
    if (k > 0.0f && m < cutoff) {
        // sum over the same set whatever the block's list: only d < cutoff counts
        float sum = 0.0f;
        for (int i = s0; i < s1; ++i) {
            const int s = seg_items[i];
            const float d = sqrt(segment_dist2(p, segments[2 * s].xyz, segments[2 * s + 1].xyz));
            if (d < cutoff) sum += exp(-(d - m) / k);
        }
        m = fmin(m - k * log(sum), cutoff);
    }
    out[OUT_INDEX] = m;
}
