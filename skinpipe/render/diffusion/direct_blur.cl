
// Weights: PER_TEXEL 0, one set per axis (wu, wv: in registers); PER_TEXEL 1, row
// iu[texel] of `wut` (RU + 1 one-sided weights a row) horizontally and row iv[texel]
// of `wvt` vertically, each texel's own Gaussian (its sigma from the stretch map) cut
// at the widest one's radius. Per texel, each weight is stored four times: its float4
// load is the broadcast the float4 taps need (building the pair from two scalar loads
// cost 24 against 18 ms at radius 4). PAIR_W / ONE_W(w, k): the weight of tap k for a
// texel pair (float8) or one texel, w naming the axis's one-sigma weights.
#if PER_TEXEL
#define WEIGHTS __global const float4 *wut, __global const float4 *wvt, \
                __global const ushort *iu, __global const ushort *iv
#define AT_PAIR(t, idx, R) __global const float4 *wa = t + (idx)[0] * (R + 1), \
                                         *wb = t + (idx)[1] * (R + 1);
#define AT_ONE(t, idx, R) __global const float4 *wa = t + (idx)[0] * (R + 1);
#define PAIR_W(w, k) both(wa, wb, k)
#define ONE_W(w, k) wa[k]
#else
#define WEIGHTS __constant float *wuc, __constant float *wvc
#define AT_PAIR(t, idx, R)
#define AT_ONE(t, idx, R)
#define PAIR_W(w, k) w[k]
#define ONE_W(w, k) w[k]
#endif
__kernel void KERNEL_NAME(__global const float4 *src, __global float4 *dst, WEIGHTS,
                          __local float8 *ring, const int width, const int height,
                          const int strip)
{
    const int x0 = get_global_id(0) * B;
    const int y0 = get_global_id(1) * strip;
    if (x0 >= width || y0 >= height) return;
    const int y1 = y0 + strip < height ? y0 + strip : height;
    const int nx = width - x0 < B ? width - x0 : B;
    const bool interior = x0 >= RU && x0 + B + RU <= width;
#if !PER_TEXEL
    float wu[RU + 1], wv[RV + 1];
#pragma unroll
    for (int k = 0; k <= RU; ++k) wu[k] = wuc[k];
#pragma unroll
    for (int k = 0; k <= RV; ++k) wv[k] = wvc[k];
#endif
    __local float4 *ring4 = (__local float4 *)ring;
    for (int yy = y0 - RV; yy < y1 + RV; ++yy) {
        const int slot = SLOT(yy);
        if (yy < 0 || yy >= height) {
            for (int c = 0; c < nx; ++c) ring4[slot * B + c] = 0.0f;
        } else if (interior) {
            __global const float4 *row = src + (size_t)yy * width;
#if PER_TEXEL
            __global const ushort *ir = iu + (size_t)yy * width;
#endif
            __local float8 *out = ring + slot * (B / 2);
            for (int c = 0; c < B / 2; ++c) {
                const int x = x0 + 2 * c;
                AT_PAIR(wut, ir + x, RU)
                float8 h = PAIR_W(wu, 0) * pair(row, x);
#pragma unroll
                for (int k = 1; k <= RU; ++k)
                    h += PAIR_W(wu, k) * (pair(row, x - k) + pair(row, x + k));
                out[c] = h;
            }
        } else {
            __global const float4 *row = src + (size_t)yy * width;
#if PER_TEXEL
            __global const ushort *ir = iu + (size_t)yy * width;
#endif
            for (int c = 0; c < nx; ++c) {
                const int x = x0 + c;
                AT_ONE(wut, ir + x, RU)
                float4 h = ONE_W(wu, 0) * row[x];
                for (int k = 1; k <= RU; ++k)
                    h += ONE_W(wu, k) * (tex0(row, x - k, width) + tex0(row, x + k, width));
                ring4[slot * B + c] = h;
            }
        }
        if (yy < y0 + RV) continue;
        const int yo = yy - RV;
        int rows[2 * RV + 1];
#pragma unroll
        for (int j = 0; j <= 2 * RV; ++j) rows[j] = SLOT(yo - RV + j);
#if PER_TEXEL
        __global const ushort *ir_v = iv + (size_t)yo * width + x0;
#endif
        if (interior) {
            __local const float8 *rk[2 * RV + 1];
#pragma unroll
            for (int j = 0; j <= 2 * RV; ++j) rk[j] = ring + rows[j] * (B / 2);
            // two float4 stores: an odd width leaves rows 16-byte aligned only
            __global float4 *out = dst + (size_t)yo * width + x0;
            for (int c = 0; c < B / 2; ++c) {
                AT_PAIR(wvt, ir_v + 2 * c, RV)
                float8 v = PAIR_W(wv, 0) * rk[RV][c];
#pragma unroll
                for (int k = 1; k <= RV; ++k)
                    v += PAIR_W(wv, k) * (rk[RV - k][c] + rk[RV + k][c]);
                STORE(v.lo, out + 2 * c);
                STORE(v.hi, out + 2 * c + 1);
            }
        } else {
            __global float4 *out = dst + (size_t)yo * width + x0;
            for (int c = 0; c < nx; ++c) {
                AT_ONE(wvt, ir_v + c, RV)
                float4 v = ONE_W(wv, 0) * ring4[rows[RV] * B + c];
                for (int k = 1; k <= RV; ++k)
                    v += ONE_W(wv, k) * (ring4[rows[RV - k] * B + c] + ring4[rows[RV + k] * B + c]);
                out[c] = v;
            }
        }
    }
}
#undef WEIGHTS
#undef AT_PAIR
#undef AT_ONE
#undef PAIR_W
#undef ONE_W
