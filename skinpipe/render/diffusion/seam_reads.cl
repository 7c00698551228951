
// TileLevel.read_across_seams on the device: atlas texel i's RGBA plus what it reads
// across the seams (SeamReads: reads rows[i] .. rows[i + 1] - 1, each at its atlas
// position xy), each read's taps made as _bilinear_taps (level 0) or _cubic_taps make
// them (doubles in numpy's order, weights rounded to float32) and their products added
// in turn from zero in float32 as scipy's csr_matvecs adds the matrix's rows (no fused
// multiply-adds): the same texels bit for bit as SeamReads.matrix's product.
#pragma OPENCL EXTENSION cl_khr_fp64 : enable
#pragma OPENCL FP_CONTRACT OFF

#define ADD_TAP(at, weight)                                                            \
    y = y + (float)(weight) * *(__global const float4 *)(src + 4 * (size_t)(at));

// floor as a conversion and a comparison, for atlas positions (within an int): PoCL
// calls its floor(); the arrays of weights and sums written out as vectors (PoCL kept
// them on the stack). The same arithmetic lane by lane; warm, at texture 4096: level 0
// (20 M texels, 7.9 M reading) 0.13-0.14 -> 0.08 s, level 1 0.086 -> 0.044 s.
__attribute__((always_inline)) inline int floor_int(double v)
{
    const int i = (int)v;
    return i - (v < (double)i);
}

// _cubic_weights at phase t, clamped to [0, 1]
__attribute__((always_inline)) inline double4 cubic_weights(double t)
{
    t = t < 0.0 ? 0.0 : (t > 1.0 ? 1.0 : t);
    const double t2 = t * t, t3 = t * t * t;
    return (double4)((-t3 + 2.0 * t2 - t) / 2.0, (3.0 * t3 - 5.0 * t2 + 2.0) / 2.0,
                     (-3.0 * t3 + 4.0 * t2 + t) / 2.0, (t3 - t2) / 2.0);
}

#define CUBIC_ROW(dy, wyd)                                                             \
    ADD_TAP((y0 + dy - 1) * w + x0 - 1, (wyd) * wx.x);                                  \
    ADD_TAP((y0 + dy - 1) * w + x0, (wyd) * wx.y);                                      \
    ADD_TAP((y0 + dy - 1) * w + x0 + 1, (wyd) * wx.z);                                  \
    ADD_TAP((y0 + dy - 1) * w + x0 + 2, (wyd) * wx.w);

__kernel void read_seams(__global const int *rows, __global const float *xy, const int h,
                         const int w, const int cubic, __global const float *src,
                         const int n, __global float *out)
{
    const int i = get_global_id(0);
    if (i >= n) return;
    float4 y = (float4)(0.0f);
    for (int r = rows[i]; r < rows[i + 1]; ++r) {
        const double px = (double)xy[2 * (size_t)r], py = (double)xy[2 * (size_t)r + 1];
        if (!cubic) {
            int x0 = floor_int(px), y0 = floor_int(py);
            x0 = x0 < 0 ? 0 : (x0 > w - 2 ? w - 2 : x0);
            y0 = y0 < 0 ? 0 : (y0 > h - 2 ? h - 2 : y0);
            double ax = px - (double)x0, ay = py - (double)y0;
            ax = ax < 0.0 ? 0.0 : (ax > 1.0 ? 1.0 : ax);
            ay = ay < 0.0 ? 0.0 : (ay > 1.0 ? 1.0 : ay);
            const int at = y0 * w + x0;
            ADD_TAP(at, (1.0 - ax) * (1.0 - ay));
            ADD_TAP(at + 1, ax * (1.0 - ay));
            ADD_TAP(at + w, (1.0 - ax) * ay);
            ADD_TAP(at + w + 1, ax * ay);
            continue;
        }
        int x0 = floor_int(px), y0 = floor_int(py);
        x0 = x0 < 1 ? 1 : (x0 > w - 3 ? w - 3 : x0);
        y0 = y0 < 1 ? 1 : (y0 > h - 3 ? h - 3 : y0);
        const double4 wx = cubic_weights(px - (double)x0), wy = cubic_weights(py - (double)y0);
        CUBIC_ROW(0, wy.x)
        CUBIC_ROW(1, wy.y)
        CUBIC_ROW(2, wy.z)
        CUBIC_ROW(3, wy.w)
    }
    *(__global float4 *)(out + 4 * (size_t)i) =
        *(__global const float4 *)(src + 4 * (size_t)i) + y;
}
