
// One batch of blurred terms added up at each texel, each (sum_r rw[r] tw[job, r]) times
// rgb / alpha of its blurred (E cov, cov) texture (normalised convolution: texels off
// the charts give nothing and take nothing), read in the texel's own chart's tile of a
// pyramid level 2^-level as large: at ((x + 0.5) 2^-level - 0.5, likewise y) plus the
// chart's shift in that level's atlas, through a cubic B-spline (level 0: the texel).
// Job n of the batch: jobs[6n .. 6n+5] = (offset of its texture in `terms` in float4;
// job index into tw; level width; level height; its level, -1 for the unblurred
// irradiance `e`; the level's first entry in `shift`). The region weights (half floats)
// are read once for the whole batch (a pass per term read them, 24 bytes a texel with
// six regions, once per term) and scaled to sum to 1 (a texel is all skin: half floats
// round a blend's sum off 1 by up to 2.4e-4). The sum goes to `rgb` (the result's own
// memory on a CPU device); acc_in: added to what the previous batches left there.
#define INL __attribute__((always_inline)) inline
// Plain comparisons, not clamp/min: PoCL leaves those builtins as calls, which keep it
// from vectorising the work items (measured: one bilinear term 47-53 ms at 2048^2 with
// them).
#include "half_bits.cl"

// the cubic B-spline's four weights at phase t in [0, 1) (cells -1 .. 2): their spread
// about the read position is 1/3 cell^2 at every phase
INL float4 bspline3(float t)
{
    const float t2 = t * t, t3 = t2 * t, s = 1.0f - t;
    return (float4)(s * s * s, 3.0f * t3 - 6.0f * t2 + 4.0f,
                    -3.0f * t3 + 3.0f * t2 + 3.0f * t + 1.0f, t3) * (1.0f / 6.0f);
}
// one row's four taps from column x0, clamped to the row (a read beyond a tile's edge
// repeats its last texel)
INL float4 bspline_row(__global const float4 *row, int x0, int lw, float4 wx)
{
    const int x1 = x0 + 1, x2 = x0 + 2, x3 = x0 + 3, last = lw - 1;
    const int a = x0 < 0 ? 0 : (x0 > last ? last : x0);
    const int b = x1 < 0 ? 0 : (x1 > last ? last : x1);
    const int c = x2 < 0 ? 0 : (x2 > last ? last : x2);
    const int d = x3 < 0 ? 0 : (x3 > last ? last : x3);
    return wx.x * row[a] + wx.y * row[b] + wx.z * row[c] + wx.w * row[d];
}
// The 4 x 4 taps written out, no arrays of weights or loops: with them PoCL kept the
// weights on the stack (a batch of six coarse terms at texture 4096: 0.77 -> 0.52 s).
// floor as a conversion and a comparison: PoCL calls its floor(), not inlined
INL float4 bspline_read(__global const float4 *level, float fx, float fy, int lw, int lh)
{
    const int ix = (int)fx, iy = (int)fy;
    const int fxi = ix - (fx < (float)ix), fyi = iy - (fy < (float)iy);
    const int x0 = fxi - 1, y0 = fyi - 1, y1 = y0 + 1, y2 = y0 + 2, y3 = y0 + 3;
    const int last = lh - 1;
    const float4 wx = bspline3(fx - (float)fxi), wy = bspline3(fy - (float)fyi);
    const int a = y0 < 0 ? 0 : (y0 > last ? last : y0);
    const int b = y1 < 0 ? 0 : (y1 > last ? last : y1);
    const int c = y2 < 0 ? 0 : (y2 > last ? last : y2);
    const int d = y3 < 0 ? 0 : (y3 > last ? last : y3);
    return wy.x * bspline_row(level + (size_t)a * lw, x0, lw, wx)
         + wy.y * bspline_row(level + (size_t)b * lw, x0, lw, wx)
         + wy.z * bspline_row(level + (size_t)c * lw, x0, lw, wx)
         + wy.w * bspline_row(level + (size_t)d * lw, x0, lw, wx);
}
// (E, 1) of finest texel i from the irradiance's RGB (H W x 3): the (E cov, cov) pair the
// blurs carry, read in place (an (E, 1) copy was 268 MB at texture 4096)
#define E_ONE(e, i) ((float4)((e)[3 * (size_t)(i)], (e)[3 * (size_t)(i) + 1], \
                              (e)[3 * (size_t)(i) + 2], 1.0f))

#if BY_TRIANGLE  // the texel's region weights made again from its triangle's
#define REGION_ARGS __global const int *triangle, __global const float *frame, \
                    __global const int *corners, __global const float *vw
#else
#define REGION_ARGS __global const ushort *rw
#endif
#if BY_TRIANGLE
// Triangle t's REGIONS weights at texel (x, y) into r: its corners' weights (vw rows)
// interpolated at the texel centre's barycentrics, >= 0, in float32 (frame: its first
// corner and two edges in texels, 1 / their determinant; texture_maps.TexelRegions).
// The rasterizer's doubles and half floats cost a quarter of the diffusion at texture
// 4096 here (its four batches each make them); these are within 1e-5 of them.
INL void texel_region_weights(const int t, const int x, const int y,
                              __global const float *frame, __global const int *corners,
                              __global const float *vw, float *r)
{
    __global const float *f = frame + 8 * (size_t)t;
    const float dx = (float)x - f[0], dy = (float)y - f[1];
    const float b1 = (dx * f[5] - dy * f[4]) * f[6], b2 = (f[2] * dy - f[3] * dx) * f[6];
    const float w0 = 1.0f - b1 - b2;
    __global const float *p0 = vw + (size_t)corners[3 * t] * REGIONS;
    __global const float *p1 = vw + (size_t)corners[3 * t + 1] * REGIONS;
    __global const float *p2 = vw + (size_t)corners[3 * t + 2] * REGIONS;
#pragma unroll
    for (int k = 0; k < REGIONS; ++k) {
        const float v = p0[k] * w0 + p1[k] * b1 + p2[k] * b2;
        r[k] = v > 0.0f ? v : 0.0f;
    }
}
#endif

__kernel void accumulate_terms(__global const float4 *terms, __global const float *e,
                               __constant int *jobs, __global float *rgb,
                               __global const float *cover, REGION_ARGS,
                               __constant float4 *tw, __global const int *chart,
                               __global const float2 *shift, const int w, const int h,
                               const int n_jobs, const int acc_in)
{
    const int x = get_global_id(0), y = get_global_id(1);
    if (x >= w || y >= h) return;
    const int i = y * w + x;
    const int c = chart[i];
    if (c < 0 || !(cover[i] > 0.0f)) {  // off the charts: no tile to read
        rgb[3 * i] = 0.0f; rgb[3 * i + 1] = 0.0f; rgb[3 * i + 2] = 0.0f;
        return;
    }
    // every work item takes the same branches (the jobs are uniform): no divergence
    float4 sum = acc_in ? (float4)(rgb[3 * i], rgb[3 * i + 1], rgb[3 * i + 2], 0.0f)
                        : (float4)(0.0f);
#if REGIONS > 0
    float r[REGIONS];
#if BY_TRIANGLE
    texel_region_weights(triangle[i], x, y, frame, corners, vw, r);
#else
#pragma unroll
    for (int k = 0; k < REGIONS; ++k) r[k] = half_bits_to_float(rw[(size_t)i * REGIONS + k]);
#endif
    float total = 0.0f;
#pragma unroll
    for (int k = 0; k < REGIONS; ++k) total += r[k];
    const float unit = total > 0.0f ? 1.0f / total : 0.0f;
#pragma unroll
    for (int k = 0; k < REGIONS; ++k) r[k] *= unit;
#endif
    for (int n = 0; n < n_jobs; ++n) {
        const int off = jobs[6 * n], job = jobs[6 * n + 1], level = jobs[6 * n + 4];
        float4 t;
        if (level < 0) {
            t = E_ONE(e, i);
        } else if (level == 0) {
            const float2 s = shift[jobs[6 * n + 5] + c];
            t = terms[(size_t)off + (y + (int)s.y) * jobs[6 * n + 2] + x + (int)s.x];
        } else {
            const float2 s = shift[jobs[6 * n + 5] + c];
            const float scale = 1.0f / (float)(1 << level);
            t = bspline_read(terms + off, ((float)x + 0.5f) * scale - 0.5f + s.x,
                             ((float)y + 0.5f) * scale - 0.5f + s.y, jobs[6 * n + 2],
                             jobs[6 * n + 3]);
        }
#if REGIONS > 0
        float4 wgt = 0.0f;
#pragma unroll
        for (int k = 0; k < REGIONS; ++k) wgt += r[k] * tw[job * REGIONS + k];
#else
        const float4 wgt = tw[job];
#endif
        sum += (t.w > 1e-7f ? 1.0f / t.w : 0.0f) * wgt * t;
    }
    rgb[3 * i] = sum.x; rgb[3 * i + 1] = sum.y; rgb[3 * i + 2] = sum.z;
}

// A pyramid level's chart tiles from the finest texels (the reference this follows:
// tests/render/splat_reference.py's fill; the reads across the seams come after it):
// each atlas texel of chart c's tile sums, over the finest texels of chart c whose
// bilinear splat reaches it, weight x (E share, share), over 4^level. A finest texel x
// splats to its first cell g0 = floor((x + 0.5) / 2^k - 0.5) with 1 - f and to g0 + 1
// with f, f the fraction; so cell g gathers x in [g 2^k - 2^(k-1), g 2^k + 3 2^(k-1)):
// the first 2^k with f, the next 2^k with 1 - f (per axis; level 0: x = g, weight 1).
// e: E per finest texel (RGB, read as (E, 1)); share: the part of its square its chart
// covers;
// owner: each atlas texel's chart (-1: none); count: the splat's weights summed there
// (0: no finest texel reaches it).
__kernel void splat_level(__global const float *e, __global const float *share,
                          __global const int *chart,
                          __global const int *owner, __global const float *count,
                          __global const int2 *shift, __global float4 *out,
                          const int w, const int h, const int aw, const int ah,
                          const int level)
{
    const int x = get_global_id(0), y = get_global_id(1);
    if (x >= aw || y >= ah) return;
    const int i = y * aw + x;
    const int c = owner[i];
    float4 sum = (float4)(0.0f);
    if (c >= 0 && count[i] > 0.0f) {
        const int2 g = (int2)(x, y) - shift[c];
        if (level == 0) {
            if (g.x >= 0 && g.x < w && g.y >= 0 && g.y < h && chart[g.y * w + g.x] == c)
                sum = share[g.y * w + g.x] * E_ONE(e, g.y * w + g.x);
        } else {
            const int s = 1 << level;
            const float inv = 1.0f / (float)s;
            const int x0 = g.x * s - s / 2, y0 = g.y * s - s / 2;
            for (int dy = 0; dy < 2 * s; ++dy) {
                const int yy = y0 + dy;
                if (yy < 0 || yy >= h) continue;
                float fy = ((float)(yy & (s - 1)) + 0.5f) * inv - 0.5f;
                fy = fy < 0.0f ? fy + 1.0f : fy;
                const float wy = dy < s ? fy : 1.0f - fy;
                float4 row = (float4)(0.0f);
                for (int dx = 0; dx < 2 * s; ++dx) {
                    const int xx = x0 + dx;
                    if (xx < 0 || xx >= w || chart[yy * w + xx] != c) continue;
                    float fx = ((float)(xx & (s - 1)) + 0.5f) * inv - 0.5f;
                    fx = fx < 0.0f ? fx + 1.0f : fx;
                    row += ((dx < s ? fx : 1.0f - fx) * share[yy * w + xx])
                           * E_ONE(e, yy * w + xx);
                }
                sum += wy * row;
            }
            sum *= inv * inv;
        }
    }
    out[i] = sum;
}
