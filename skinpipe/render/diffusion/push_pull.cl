
// Pull: level k+1 texel = sum of the (up to) 2 x 2 texels of level k it covers, of the
// values times coverage (premultiplied on level 0, where `weight` is the coverage) and
// of the coverage. Values are `channels` floats a texel.
__kernel void pull(__global const float *src, __global const float *src_c,
                   __global float *dst, __global float *dst_c, const int sw, const int sh,
                   const int dw, const int dh, const int channels, const int premultiply)
{
    const int x = get_global_id(0), y = get_global_id(1);
    if (x >= dw || y >= dh) return;
    const size_t o = (size_t)y * dw + x;
    float cs = 0.0f;
    for (int c = 0; c < channels; ++c) dst[o * channels + c] = 0.0f;
    for (int j = 0; j < 2; ++j) {
        const int sy = 2 * y + j;
        if (sy >= sh) break;
        for (int i = 0; i < 2; ++i) {
            const int sx = 2 * x + i;
            if (sx >= sw) break;
            const size_t s = (size_t)sy * sw + sx;
            const float cov = src_c[s];
            const float m = premultiply ? cov : 1.0f;
            for (int c = 0; c < channels; ++c) dst[o * channels + c] += m * src[s * channels + c];
            cs += cov;
        }
    }
    dst_c[o] = cs;
}

// Push: a texel of level k keeps its normalised value where it has coverage and takes
// its parent's filled value (level k+1, already pushed) where it has none. On level 0
// (`keep`) a covered texel keeps its own value, unnormalised.
__kernel void push(__global float *lvl, __global const float *lvl_c,
                   __global const float *parent, __global float *out, const int w,
                   const int h, const int pw, const int channels, const int keep)
{
    const int x = get_global_id(0), y = get_global_id(1);
    if (x >= w || y >= h) return;
    const size_t o = (size_t)y * w + x;
    const size_t p = (size_t)(y / 2) * pw + x / 2;
    const float cov = lvl_c[o];
    for (int c = 0; c < channels; ++c) {
        const float v = lvl[o * channels + c];
        out[o * channels + c] = cov > 0.0f ? (keep ? v : v / cov) : parent[p * channels + c];
    }
}

// The coarsest level's normalised value (zero where nothing is covered).
__kernel void normalise(__global float *lvl, __global const float *lvl_c, const int texels,
                        const int channels)
{
    const int i = get_global_id(0);
    if (i >= texels) return;
    const float cov = lvl_c[i] > 1e-30f ? lvl_c[i] : 1e-30f;
    for (int c = 0; c < channels; ++c) lvl[(size_t)i * channels + c] /= cov;
}
