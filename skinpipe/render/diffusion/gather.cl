
// One 1D Gaussian pass along `axis` (0 = u/x, 1 = v/y) with a per-texel sigma (texels).
// Every index is clamped to the image before use: PoCL has no bounds checks.
__kernel void blur_axis(__global const float4 *src, __global float4 *dst,
                        __global const float *sigma, __global const float *cover,
                        const int width, const int height, const int axis,
                        const int max_radius)
{
    const int x = get_global_id(0);
    const int y = get_global_id(1);
    if (x >= width || y >= height) return;
    const int i = y * width + x;
    const float s = sigma[i];
    if (!(cover[i] > 0.0f) || !(s >= MIN_SIGMA)) { dst[i] = src[i]; return; }
    const int r = min((int)ceil(3.0f * s), max_radius);
    const float inv2s2 = 0.5f / (s * s);
    float4 acc = (float4)(0.0f);
    float wsum = 0.0f;
    const int lo = axis == 0 ? max(-r, -x) : max(-r, -y);
    const int hi = axis == 0 ? min(r, width - 1 - x) : min(r, height - 1 - y);
    const int step = axis == 0 ? 1 : width;
    for (int k = lo; k <= hi; ++k) {
        const int j = i + k * step;
        const float w = exp(-(float)(k * k) * inv2s2) * cover[j];
        acc += w * src[j];
        wsum += w;
    }
    dst[i] = wsum > 0.0f ? acc / wsum : src[i];
}
