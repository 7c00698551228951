
#pragma OPENCL FP_CONTRACT OFF
// rgb (S, S, 3) times max(image resampled at its texel, 0)^power, the resampled value
// made as resample_bilinear makes it: the axes' neighbours and weights from the host (its
// _axis_weights), each product and sum rounded to float32 in numpy's order (no fused
// multiply-adds); POWER 1: the value itself, 2: its square root (as numpy's np.sqrt),
// else pow (PoCL's is a call: 3.5 s at texture 4096, against 0.08 s for the root)
__kernel void times_resampled_power(__global const float *image, __global const int *x0,
                                    __global const float *fx, __global const int *y0,
                                    __global const float *fy, const int w, const int h,
                                    const int size, const float power, __global float *rgb)
{
    const int x = get_global_id(0), y = get_global_id(1);
    if (x >= size || y >= size) return;
    const int xa = x0[x], ya = y0[y];
    const int xb = xa + 1 < w ? xa + 1 : w - 1, yb = ya + 1 < h ? ya + 1 : h - 1;
    const float bx = fx[x], ax = 1.0f - bx, by = fy[y], ay = 1.0f - by;
    __global const float *p = image + 3 * ((size_t)ya * w + xa);
    __global const float *q = image + 3 * ((size_t)ya * w + xb);
    __global const float *r = image + 3 * ((size_t)yb * w + xa);
    __global const float *s = image + 3 * ((size_t)yb * w + xb);
    __global float *out = rgb + 3 * ((size_t)y * size + x);
    for (int c = 0; c < 3; ++c) {
        const float top = p[c] * ax + q[c] * bx, bottom = r[c] * ax + s[c] * bx;
        const float v = top * ay + bottom * by;
        const float clipped = v > 0.0f ? v : 0.0f;
#if POWER == 1
        out[c] *= clipped;
#elif POWER == 2
        out[c] *= sqrt(clipped);
#else
        out[c] *= pow(clipped, power);
#endif
    }
}
