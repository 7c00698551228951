
#pragma OPENCL EXTENSION cl_khr_fp64 : enable
#pragma OPENCL FP_CONTRACT OFF
#include "half_bits.cl"

// the numpy reference's arithmetic, in the same order: no fused multiply-adds
#define CORNERS(t) \
    const double ax = tq[6 * (t)], ay = tq[6 * (t) + 1]; \
    const double e1x = tq[6 * (t) + 2] - ax, e1y = tq[6 * (t) + 3] - ay; \
    const double e2x = tq[6 * (t) + 4] - ax, e2y = tq[6 * (t) + 5] - ay;

// One triangle: every texel centre of its bounding box (clipped to the texture) that
// its barycentrics put inside, with 1e-9 of slack, takes the triangle's index unless
// a higher one already has it.
__kernel void claim_texels(__global const double *tq, __global const double *det,
                           __global int *triangle, const int size, const int n_tris)
{
    const int t = get_global_id(0);
    if (t >= n_tris) return;
    const double d = det[t];
    if (!(fabs(d) > 1e-12)) return;
    CORNERS(t)
    const double bx = ax + e1x, by = ay + e1y, cx = ax + e2x, cy = ay + e2y;
    const double top = size - 1;
    const int x0 = (int)ceil(clamp(fmin(ax, fmin(bx, cx)), 0.0, top));
    const int x1 = (int)floor(clamp(fmax(ax, fmax(bx, cx)), 0.0, top));
    const int y0 = (int)ceil(clamp(fmin(ay, fmin(by, cy)), 0.0, top));
    const int y1 = (int)floor(clamp(fmax(ay, fmax(by, cy)), 0.0, top));
    const double inv = 1.0 / d;
    for (int y = y0; y <= y1; ++y) {
        const double dy = (double)y - ay;
        for (int x = x0; x <= x1; ++x) {
            const double dx = (double)x - ax;
            const double b1 = (dx * e2y - dy * e2x) * inv;
            const double b2 = (e1x * dy - e1y * dx) * inv;
            if (b1 >= -1e-9 && b2 >= -1e-9 && b1 + b2 <= 1.0 + 1e-9)
                atomic_max(triangle + (size_t)y * size + x, t);
        }
    }
}

// One texel: its triangle's barycentrics at the texel centre (float32, as stored by the
// reference) and the interpolated attributes; zero where no triangle covers it.
__kernel void texel_attributes(__global const int *triangle, __global const double *tq,
                               __global const double *det, __global const int *corners,
                               __global const float *table, __global const float *tri_mm,
                               __global float *position, __global float *normal,
                               __global float *mm_u, __global float *mm_v,
                               __global ushort *regions, const int size, const int n_regions)
{
    const int x = get_global_id(0), y = get_global_id(1);
    if (x >= size || y >= size) return;
    const size_t i = (size_t)y * size + x;
    const int t = triangle[i];
    const int channels = 6 + n_regions;
    if (t < 0) {
        for (int c = 0; c < 3; ++c) { position[3 * i + c] = 0.0f; normal[3 * i + c] = 0.0f; }
        for (int r = 0; r < n_regions; ++r) regions[i * n_regions + r] = 0;
        mm_u[i] = 0.0f; mm_v[i] = 0.0f;
        return;
    }
    CORNERS(t)
    const double inv = 1.0 / det[t];
    const double dx = (double)x - ax, dy = (double)y - ay;
    const float b1 = (float)((dx * e2y - dy * e2x) * inv);
    const float b2 = (float)((e1x * dy - e1y * dx) * inv);
    const float w0 = 1.0f - b1 - b2;
    __global const float *p0 = table + (size_t)corners[3 * t] * channels;
    __global const float *p1 = table + (size_t)corners[3 * t + 1] * channels;
    __global const float *p2 = table + (size_t)corners[3 * t + 2] * channels;
    float n[3];
    for (int c = 0; c < 3; ++c) {
        position[3 * i + c] = p0[c] * w0 + p1[c] * b1 + p2[c] * b2;
        n[c] = p0[3 + c] * w0 + p1[3 + c] * b1 + p2[3 + c] * b2;
    }
    const float len = sqrt(n[0] * n[0] + n[1] * n[1] + n[2] * n[2]);
    const float scale = 1.0f / (len > 1e-12f ? len : 1e-12f);
    for (int c = 0; c < 3; ++c) normal[3 * i + c] = n[c] * scale;
    for (int r = 0; r < n_regions; ++r) {
        // >= 0: the barycentrics' slack leaves -1e-9 at edges (a plain comparison: PoCL
        // calls its fmax); rounded to nearest even, as numpy's astype
        const float v = p0[6 + r] * w0 + p1[6 + r] * b1 + p2[6 + r] * b2;
        regions[i * n_regions + r] = float_to_half_bits(v > 0.0f ? v : 0.0f);
    }
    mm_u[i] = tri_mm[2 * t]; mm_v[i] = tri_mm[2 * t + 1];
}
