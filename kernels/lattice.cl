// Lattice fields: the paper's pores-and-channels lattice and the struts lattice.
//
// A work-item computes ROW_Z voxels along z (the fastest array axis) in each of
// two neighbouring rows along y, as one float16, so that the CPU driver's vector
// units do the work whatever it makes of the work-group; a work-group of 8 x 4
// work-items is one block of 8^3 voxels, whose primitives the block's list holds.
// Every per-voxel value is a pure function of the voxel's global index and of the
// block's list, so neither the tiling nor the order of the primitives changes a
// bit of it.
#include "common.cl"

#define ROW_Z 8
#if BLOCK != ROW_Z
#error "the row kernels need BLOCK == ROW_Z (a row spans one block along z)"
#endif

typedef float16 rowf;
typedef int16 rowi;

// lane i is voxel (z0 + i % 8) of row (y0 + i / 8)
#define LANES_Z ((rowf)(0.0f, 1.0f, 2.0f, 3.0f, 4.0f, 5.0f, 6.0f, 7.0f, \
                        0.0f, 1.0f, 2.0f, 3.0f, 4.0f, 5.0f, 6.0f, 7.0f))
#define LANES_Y ((rowf)(0.0f, 0.0f, 0.0f, 0.0f, 0.0f, 0.0f, 0.0f, 0.0f, \
                        1.0f, 1.0f, 1.0f, 1.0f, 1.0f, 1.0f, 1.0f, 1.0f))

// Minimum, maximum and the lane masks' all/any as plain operators: the driver
// does not inline its built-ins, and a call in the inner loop spills every vector
// register. (No NaN reaches them.)
#define VMIN(a, b) ((a) < (b) ? (a) : (b))
#define VMAX(a, b) ((a) > (b) ? (a) : (b))
#define ALL8(m) ((((m).s0 & (m).s1 & (m).s2 & (m).s3) & ((m).s4 & (m).s5 & (m).s6 & (m).s7)) < 0)
#define ANY8(m) ((((m).s0 | (m).s1 | (m).s2 | (m).s3) | ((m).s4 | (m).s5 | (m).s6 | (m).s7)) < 0)
#define ROW_ALL(m) ALL8((m).lo & (m).hi)
#define ROW_ANY(m) ANY8((m).lo | (m).hi)
// a scalar condition as a lane mask (scalar comparisons give 1, vector ones -1)
#define MASK(c) ((rowi)((c) ? -1 : 0))

// The work-item's voxels, and the centre of the block they lie in.
#define ROW_SETUP                                                                 \
    const int bz = (int)get_global_id(0);                                         \
    const int y0 = 2 * (int)get_global_id(1);                                     \
    const int lx = (int)get_global_id(2);                                         \
    if (lx >= tile_nx || y0 >= ny) return;                                        \
    const int gx = tile_lo_x + lx;                                                \
    const int z0 = bz * ROW_Z;                                                    \
    const int block_id = ((gx / BLOCK - block_x0) * blocks_y + y0 / BLOCK) * blocks_z + bz; \
    const float px = (float)gx * h;                                               \
    const rowf py = ((float)y0 + LANES_Y) * h;                                    \
    const rowf pz = ((float)z0 + LANES_Z) * h;                                    \
    const float pylo = (float)y0 * h, pyhi = (float)(y0 + 1) * h;                 \
    const float zlo = (float)z0 * h, zhi = (float)(z0 + ROW_Z - 1) * h;           \
    const float cx = ((float)((gx / BLOCK) * BLOCK) + 0.5f * (BLOCK - 1)) * h;    \
    const float cy = ((float)((y0 / BLOCK) * BLOCK) + 0.5f * (BLOCK - 1)) * h;    \
    const float cz = ((float)z0 + 0.5f * (BLOCK - 1)) * h;                        \
    const rowf rp = sqrt((px - cx) * (px - cx) + (py - cy) * (py - cy)            \
                         + (pz - cz) * (pz - cz));                                \
    /* lanes beyond the grid (their values are not stored) */                     \
    const rowi beyond = (convert_int16(LANES_Z) >= (rowi)(nz - z0))               \
                        | (convert_int16(LANES_Y) >= (rowi)(ny - y0));            \
    const size_t row_start = ((size_t)lx * ny + y0) * nz + z0;

#define ROW_ARGS                                                                  \
    const int tile_lo_x, const int tile_nx, const int ny, const int nz,           \
    const int block_x0, const int blocks_y, const int blocks_z, const float h

// Store one row of 8, leaving out the voxels beyond the grid's last z.
#define STORE8(v8, start)                                                         \
    if (z0 + ROW_Z <= nz) {                                                       \
        vstore8((v8), 0, out + (start));                                          \
    } else {                                                                      \
        float vals[ROW_Z];                                                        \
        vstore8((v8), 0, vals);                                                   \
        for (int i = 0; i < nz - z0; ++i) out[(start) + i] = vals[i];             \
    }

// Store both rows, leaving out the one beyond the grid's last y.
#define ROW_STORE(value)                                                          \
    {                                                                             \
        const rowf v_ = (value);                                                  \
        STORE8(v_.lo, row_start)                                                  \
        if (y0 + 1 < ny) {                                                        \
            STORE8(v_.hi, row_start + nz)                                         \
        }                                                                         \
    }

// A quad is 9 float4, in its own frame (U, W, n) with origin at vertex 0:
//   [0..2] rows of the frame with offsets, coordinate c = A.xyz . p + A.w;
//   [3..4] the vertices in the plane (x0, y0, x1, y1), (x2, y2, x3, y3);
//   [5..6] the edges e_i = v_{i+1} - v_i, likewise;
//   [7..8] the edges divided by their squared length (0 for a point edge).
// The vertices wind counter-clockwise about n, so a point is over the quad when
// it lies left of every edge; then its distance is the plane distance, else the
// nearest edge's.
#define QUAD_WORDS 9

#define SIDE_SOLID 1
#define SIDE_VOID 2

// Squared distance from (x, y, z), in the quad's frame, to one edge's segment
// (accumulated into d) and whether the point is left of it (into inside), in
// type T: float or rowf.
#define QUAD_EDGE(T, vx, vy, ex, ey, sx, sy)                                         \
    {                                                                             \
        const T ax = x - (vx), ay = y - (vy);                         \
        T t = ax * (sx) + ay * (sy);                                  \
        t = VMAX(t, (T)(0.0f));                                       \
        t = VMIN(t, (T)(1.0f));                                       \
        const T dx = ax - t * (ex), dy = ay - t * (ey);               \
        d = VMIN(d, dx * dx + dy * dy);                                           \
        inside = inside & (((ex) * ay - (ey) * ax) >= 0.0f);                      \
    }

#define QUAD_EDGES(T, q)                                                             \
    {                                                                             \
        const float4 v01 = q[3], v23 = q[4], e01 = q[5], e23 = q[6];              \
        const float4 s01 = q[7], s23 = q[8];                                      \
        QUAD_EDGE(T, v01.x, v01.y, e01.x, e01.y, s01.x, s01.y)                       \
        QUAD_EDGE(T, v01.z, v01.w, e01.z, e01.w, s01.z, s01.w)                       \
        QUAD_EDGE(T, v23.x, v23.y, e23.x, e23.y, s23.x, s23.y)                       \
        QUAD_EDGE(T, v23.z, v23.w, e23.z, e23.w, s23.z, s23.w)                       \
    }

// Squared distance from point c to the quad q (scalar; for the block culling).
inline float quad_point_dist2(__global const float4 *q, float3 c)
{
    const float x = dot(q[0].xyz, c) + q[0].w;
    const float y = dot(q[1].xyz, c) + q[1].w;
    const float z = dot(q[2].xyz, c) + q[2].w;
    float d = INFINITY;
    int inside = 1;
    QUAD_EDGES(float, q)
    return z * z + (inside ? 0.0f : d);
}

// Binning and culling of the quads, on the device, per block of BLOCK^3 voxels
// with centre c and radius R (centre to corner voxel). A quad can be nearest for
// some voxel of the block only if its distance d_q from c is at most
// min(D + R, cutoff) + R, where D is the least d_q of the block: a voxel's
// nearest quad is nearer than D + R (and a nearer one than the cut-off changes
// nothing), and quad q is farther than d_q - R from every voxel. `slack` covers
// float32 rounding, so a quad that could be nearest is never dropped.
//
// quad_bin_count (one work-item per quad): over the blocks its box, grown by the
// cut-off, meets: counts the blocks' candidates and takes the least d_q (as the
// bits of a non-negative float, whose order is the integers').
// quad_bin_fill (per quad): writes the quads that pass the test above, with d_q,
// into each block's slots (in whatever order the atomics give).
// bin_sort (per block): sorts each block's list by (d_q, index), so the
// list, and everything computed from it, is the same whatever the order of the
// quads or of the atomics; the voxel loop stops at the first quad whose d_q minus
// the voxel's distance from c exceeds its best so far.

#define BLOCK_RADIUS(h) (sqrt(3.0f) * 0.5f * (BLOCK - 1) * (h))

// The blocks that primitive `q` (WORDS float4 from `prims`, bounding box in
// `boxes`) can matter to, grown by the cut-off; d is the distance from the
// block's centre c to the primitive, by DIST2(primitive, c). Blocks whose `skip`
// is set get no primitive: their values cannot change the scaffold.
#define PRIM_BLOCKS_BEGIN(WORDS, DIST2)                                           \
    const int q = (int)get_global_id(0);                                          \
    if (q >= n_prims) return;                                                     \
    __global const float4 *prim = prims + (WORDS) * q;                            \
    const float span = BLOCK * h;                                                 \
    const float4 lo = boxes[2 * q] - (cutoff + slack), hi = boxes[2 * q + 1] + (cutoff + slack); \
    const int x0 = max((int)floor(lo.x / span), block_x0), x1 = min((int)floor(hi.x / span), block_x0 + blocks_x - 1); \
    const int y0 = max((int)floor(lo.y / span), 0), y1 = min((int)floor(hi.y / span), blocks_y - 1); \
    const int z0 = max((int)floor(lo.z / span), 0), z1 = min((int)floor(hi.z / span), blocks_z - 1); \
    const float radius = BLOCK_RADIUS(h);                                         \
    for (int bx = x0; bx <= x1; ++bx)                                             \
    for (int by = y0; by <= y1; ++by)                                             \
    for (int bz = z0; bz <= z1; ++bz) {                                           \
        const int b = ((bx - block_x0) * blocks_y + by) * blocks_z + bz;          \
        if (skip[b]) continue;                                                    \
        const float3 c = ((float3)((float)(bx * BLOCK), (float)(by * BLOCK), (float)(bz * BLOCK)) \
                          + 0.5f * (BLOCK - 1)) * h;                              \
        const float d = sqrt(DIST2(prim, c));

#define BIN_ARGS                                                                  \
    __global const float4 *prims, __global const float4 *boxes, const int n_prims, \
    __global const uchar *skip,                                                   \
    const int block_x0, const int blocks_x, const int blocks_y, const int blocks_z, \
    const float h, const float cutoff, const float slack

__kernel void quad_bin_count(BIN_ARGS, __global int *counts, __global int *dmin_bits)
{
    PRIM_BLOCKS_BEGIN(QUAD_WORDS, quad_point_dist2)
        atomic_min(dmin_bits + b, as_int(d));
        if (d <= cutoff + radius + slack) atomic_inc(counts + b);
    }
}

__kernel void quad_bin_fill(BIN_ARGS, __global const int *dmin_bits, __global const int *offsets,
                            __global int *fill, __global int *items, __global float *keys)
{
    PRIM_BLOCKS_BEGIN(QUAD_WORDS, quad_point_dist2)
        const float limit = fmin(as_float(dmin_bits[b]) + radius, cutoff) + radius + slack;
        if (d <= limit) {
            const int slot = offsets[b] + atomic_inc(fill + b);
            items[slot] = q;
            keys[slot] = d;
        }
    }
}

// (d, q) before (e, r) in the lists' order: by distance, then by index
#define BIN_BEFORE(d, q, e, r) ((d) < (e) || ((d) == (e) && (q) < (r)))

// Move entry `root` down the max-heap of the n entries k[0..n), it[0..n).
inline void bin_sift(__global float *k, __global int *it, int root, const int n)
{
    const float d = k[root];
    const int q = it[root];
    for (;;) {
        int child = 2 * root + 1;
        if (child >= n) break;
        if (child + 1 < n && BIN_BEFORE(k[child], it[child], k[child + 1], it[child + 1])) ++child;
        if (!BIN_BEFORE(d, q, k[child], it[child])) break;
        k[root] = k[child];
        it[root] = it[child];
        root = child;
    }
    k[root] = d;
    it[root] = q;
}

// Insertion sort for short lists; heapsort beyond, since a block's list grows
// with the cube of the block's width in pores (thousands of quads at a few voxels
// per pore) and insertion sort's n^2 then outweighed the voxel loop. Both give
// the one order of the distinct (d_q, index) pairs.
#define BIN_SORT_SHORT 32

__kernel void bin_sort(__global const int *offsets, __global const int *fill,
                            __global int *items, __global float *keys, const int n_blocks)
{
    const int b = (int)get_global_id(0);
    if (b >= n_blocks) return;
    const int o = offsets[b], n = fill[b];
    __global float *k = keys + o;
    __global int *it = items + o;
    if (n > BIN_SORT_SHORT) {
        for (int root = n / 2 - 1; root >= 0; --root) bin_sift(k, it, root, n);
        for (int end = n - 1; end > 0; --end) {
            const float d = k[end];
            const int q = it[end];
            k[end] = k[0];
            it[end] = it[0];
            k[0] = d;
            it[0] = q;
            bin_sift(k, it, 0, end);
        }
        return;
    }
    for (int i = 1; i < n; ++i) {
        const float d = k[i];
        const int q = it[i];
        int j = i;
        while (j > 0 && BIN_BEFORE(d, q, k[j - 1], it[j - 1])) {
            k[j] = k[j - 1];
            it[j] = it[j - 1];
            --j;
        }
        k[j] = d;
        it[j] = q;
    }
}

// Segments (struts' axes) as 2 float4: (a, 1 / |b - a|^2) and (b - a, 0); the
// same binning, without the nearest-based cut: the smooth minimum sums every
// segment nearer than the cut-off, so a block keeps every segment whose distance
// from its centre is within cutoff + R.
#define SEG_WORDS 2

inline float seg_point_dist2(__global const float4 *s, float3 c)
{
    const float4 a = s[0], ab = s[1];
    const float3 ap = c - a.xyz;
    float t = dot(ap, ab.xyz) * a.w;
    t = VMIN(VMAX(t, 0.0f), 1.0f);
    const float3 r = ap - t * ab.xyz;
    return dot(r, r);
}

__kernel void seg_bin_count(BIN_ARGS, __global int *counts)
{
    PRIM_BLOCKS_BEGIN(SEG_WORDS, seg_point_dist2)
        if (d <= cutoff + radius + slack) atomic_inc(counts + b);
    }
}

__kernel void seg_bin_fill(BIN_ARGS, __global const int *offsets, __global int *fill,
                           __global int *items, __global float *keys)
{
    PRIM_BLOCKS_BEGIN(SEG_WORDS, seg_point_dist2)
        if (d <= cutoff + radius + slack) {
            const int slot = offsets[b] + atomic_inc(fill + b);
            items[slot] = q;
            keys[slot] = d;
        }
    }
}

// Signed distance to the paper's lattice surface, negative in the solid.
//
// The surface is the union of the channels' side quads (trapezoids between a
// pore face and its window rim): |s| is the distance to the nearest quad, clamped
// at `cutoff`. The sign is positive inside the void, the union of the convex
// pieces (pores and channels), each given by its planes (inside: n.p <= d).
//
// quads: QUAD_WORDS float4 each, listed per block by lattice_cull (sorted, with
// their distances from the block's centre); pieces: boxes (lo, hi) and a CSR
// range of planes (n, d).
__kernel void lattice_paper(
    __global float *out, ROW_ARGS,
    __global const int *quad_offsets, __global const int *quad_counts,
    __global const int *quad_items, __global const float *quad_keys,
    __global const float4 *quads,
    __global const int *piece_offsets, __global const int *piece_items,
    __global const float4 *piece_boxes, __global const int *plane_start,
    __global const float4 *planes,
    const float cutoff, const float slack, const float4 box_lo, const float4 box_hi)
{
    ROW_SETUP

    rowf best = (rowf)(cutoff * cutoff);
    // a squared distance off by at most `slack` (below the cut-off) is off by at most this
    const float margin = slack * (2.0f * cutoff + slack);
    // which side of its nearest quad each voxel is on, when that quad is nearest
    // through its face (not an edge): SIDE_SOLID, SIDE_VOID or 0 (not known)
    rowi side = (rowi)(0);
    const int q0 = quad_offsets[block_id], q1 = q0 + quad_counts[block_id];
    for (int k = q0; k < q1; ++k) {
        // a lower bound on the distance to this quad and to every later one
        const rowf lb = (quad_keys[k] - slack) - rp;
        if (ROW_ALL((lb > 0.0f) & (lb * lb > best))) break;
        __global const float4 *q = quads + QUAD_WORDS * quad_items[k];
        const float4 fz = q[2];
        const rowf z = (fz.x * px + fz.y * py + fz.w) + fz.z * pz;
        const rowf z2 = z * z;
        const float4 fx = q[0], fy = q[1];
        const rowf x = (fx.x * px + fx.y * py + fx.w) + fx.z * pz;
        const rowf y = (fy.x * px + fy.y * py + fy.w) + fy.z * pz;
        // The quad's bounding rectangle in its plane is too far: then so is the quad, and its
        // d2 below would exceed best (a tie must be seen, for the side). The margin covers
        // d2's rounding, so a quad is skipped only where its evaluation would change nothing.
        // (It replaces the plane's own test: with both, the loop was no faster than with the
        // plane's alone.)
        {
            const float4 v01 = q[3], v23 = q[4];
            const float xlo = VMIN(VMIN(v01.x, v01.z), VMIN(v23.x, v23.z));
            const float xhi = VMAX(VMAX(v01.x, v01.z), VMAX(v23.x, v23.z));
            const float ylo = VMIN(VMIN(v01.y, v01.w), VMIN(v23.y, v23.w));
            const float yhi = VMAX(VMAX(v01.y, v01.w), VMAX(v23.y, v23.w));
            const rowf ox = VMAX(VMAX(xlo - x, x - xhi), (rowf)(0.0f));
            const rowf oy = VMAX(VMAX(ylo - y, y - yhi), (rowf)(0.0f));
            if (ROW_ALL((z2 + ox * ox) + oy * oy > best + margin)) continue;
        }
        rowf d = (rowf)(INFINITY);
        rowi inside = (rowi)(-1);
        QUAD_EDGES(rowf, q)
        const rowf d2 = z2 + (inside ? (rowf)(0.0f) : d);
        // the normal points into the solid
        const rowi side_q = inside ? (z > 0.0f ? (rowi)(SIDE_SOLID) : (z < 0.0f ? (rowi)(SIDE_VOID) : (rowi)(0)))
                                   : (rowi)(0);
        // a strictly nearer quad decides; quads at the same distance must agree
        side = d2 < best ? side_q : (d2 == best ? (side == side_q ? side : (rowi)(0)) : side);
        best = VMIN(best, d2);
    }
    const rowf dist = sqrt(best);

    // The side of the nearest quad is the voxel's sign when the nearest point is
    // inside that quad's face and the voxel is inside the box of the cells: the
    // segment to it then crosses no other part of the void's boundary (the side
    // quads, and the window rims of the channels that open in the box's walls).
    // Elsewhere, and beyond the cut-off, the pieces decide.
    const rowi in_box = MASK(px > box_lo.x && px < box_hi.x) & (py > box_lo.y) & (py < box_hi.y)
                        & (pz > box_lo.z) & (pz < box_hi.z);
    const rowi known = in_box & (side != 0);
    rowi in_void = known & (side == SIDE_VOID);
    // lanes beyond the grid count as done, so that the early exit can fire
    rowi done = known | beyond;
    const int c0 = piece_offsets[block_id], c1 = piece_offsets[block_id + 1];
    for (int k = c0; k < c1 && !ROW_ALL(done); ++k) {
        const int c = piece_items[k];
        const float4 lo = piece_boxes[2 * c], hi = piece_boxes[2 * c + 1];
        if (px < lo.x || px > hi.x || pyhi < lo.y || pylo > hi.y || zhi < lo.z || zlo > hi.z) continue;
        rowi inside = ~done;
        for (int j = plane_start[c]; j < plane_start[c + 1] && ROW_ANY(inside); ++j) {
            const float4 pl = planes[j];
            inside = inside & (((pl.x * px + pl.y * py - pl.w) + pl.z * pz) <= 0.0f);
        }
        in_void = in_void | inside;
        done = done | inside;
    }
    const rowf value = in_void ? dist : -dist;
    ROW_STORE(value)
}

// Smooth-minimum distance to the struts' axes (Voronoi edges), unsigned:
// F = -k ln sum_i exp(-d_i / k) over the edges nearer than `cutoff`
// (the plain minimum when k == 0), clamped at `cutoff`. The solid is F < r.
// Each block's segments are sorted by their distance from its centre, so both
// loops stop where no later segment can count.
#define SEG_ROW_DIST2(s)                                                          \
    const float4 a = s[0], ab = s[1];                                             \
    const float apx = px - a.x;                                                   \
    const rowf apy = py - a.y;                                                    \
    const rowf apz = pz - a.z;                                                    \
    rowf t = ((apx * ab.x + apy * ab.y) + apz * ab.z) * a.w;                      \
    t = VMIN(VMAX(t, (rowf)(0.0f)), (rowf)(1.0f));                                \
    const rowf rx = apx - t * ab.x, ry = apy - t * ab.y, rz = apz - t * ab.z;     \
    const rowf d2 = rx * rx + ry * ry + rz * rz;

// exp(x) for x <= 0, inline (the driver's exp is a call, which spills every
// vector register in the loop): 2^(x log2 e) split into 2^n, set in the exponent
// bits, and 2^f, f in [0, 1), by its degree-8 Taylor polynomial in f ln 2. The
// relative error is below 4e-6 (mostly the float32 rounding of x log2 e), far
// under the 1e-4 mm the field is held to: a relative change e of the sum moves F
// by k e. Underflows to 0 below 2^-126.
inline rowf exp_nonpositive(rowf x)
{
    const rowf y = VMAX(x * 1.44269504f, (rowf)(-126.0f));
    const rowf n = floor(y);
    const rowf g = (y - n) * 0.693147181f;
    rowf p = 1.0f / 40320.0f;
    p = p * g + 1.0f / 5040.0f;
    p = p * g + 1.0f / 720.0f;
    p = p * g + 1.0f / 120.0f;
    p = p * g + 1.0f / 24.0f;
    p = p * g + 1.0f / 6.0f;
    p = p * g + 0.5f;
    p = p * g + 1.0f;
    p = p * g + 1.0f;
    const rowf scale = as_float16((convert_int16(n) + 127) << 23);
    return y > (rowf)(-126.0f) ? p * scale : (rowf)(0.0f);
}

__kernel void lattice_struts(
    __global float *out, ROW_ARGS,
    __global const int *seg_offsets, __global const int *seg_counts,
    __global const int *seg_items, __global const float *seg_keys,
    __global const float4 *segments,
    const float cutoff, const float k, const float slack)
{
    ROW_SETUP

    const int s0 = seg_offsets[block_id], s1 = s0 + seg_counts[block_id];
    rowf best = (rowf)(cutoff * cutoff);
    for (int i = s0; i < s1; ++i) {
        const rowf lb = (seg_keys[i] - slack) - rp;
        if (ROW_ALL((lb > 0.0f) & (lb * lb > best))) break;
        __global const float4 *s = segments + SEG_WORDS * seg_items[i];
        SEG_ROW_DIST2(s)
        best = VMIN(best, d2);
    }
    rowf m = sqrt(best);
    const rowi near = m < cutoff;
    if (k > 0.0f && ROW_ANY(near)) {
        // sum over the same set whatever the block's list: only d < cutoff counts
        rowf sum = (rowf)(0.0f);
        const float inv_k = 1.0f / k;
        for (int i = s0; i < s1; ++i) {
            if (ROW_ALL(((seg_keys[i] - slack) - rp) >= cutoff)) break;
            __global const float4 *s = segments + SEG_WORDS * seg_items[i];
            SEG_ROW_DIST2(s)
            const rowf d = sqrt(d2);
            sum += d < cutoff ? exp_nonpositive((m - d) * inv_k) : (rowf)(0.0f);
        }
        const rowf f = m - k * log(sum);
        m = near ? VMIN(f, (rowf)(cutoff)) : m;
    }
    ROW_STORE(m)
}
