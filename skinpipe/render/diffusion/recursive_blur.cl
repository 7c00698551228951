
// A pass along rows that writes its result transposed: run twice, it blurs u then v
// and leaves the image as it was, and every read walks memory in order (a pass down
// columns reads 16 bytes of each 64-byte line and is 7x slower on a CPU). Each work
// item runs LINES rows side by side: the recursion is a chain of dependent multiply-adds
// and independent rows fill its latency, and the transposed writes of LINES rows fill
// whole 64-byte cache lines. The causal half goes to `scratch`, local memory the size
// of LINES rows that stays in cache for the anticausal half (GLOBAL_SCRATCH: this work
// item's LINES rows of a global buffer, where a device's local memory holds fewer
// texels than a row: a GPU's 48 KiB). Rows past `lines` repeat the last one and are
// not written.
//
// Coefficients: 12 floats (3 float4) per entry of `coefs`; entry index[texel] (or entry
// 0 for every texel when UNIFORM). Loading them per texel costs less than testing
// whether they changed (measured: 32 vs 40 ms per 2D blur at 2048^2).
#if UNIFORM
#define COEFFS(t)
#else
#define COEFFS(t) \
    const __global float4 *cp = coefs + 3 * index[t]; \
    const float4 c0 = cp[0], c1 = cp[1], c2 = cp[2];
#endif
#if GLOBAL_SCRATCH
#define SCRATCH_SPACE __global
#else
#define SCRATCH_SPACE __local
#endif
__kernel void iir_rows_transposed(__global const float4 *src, __global float4 *dst,
                                  SCRATCH_SPACE float4 *scratch_base,
                                  __global const int *index,
                                  __global const float4 *coefs, const int n,
                                  const int lines)
{
    const int L0 = get_global_id(0) * LINES;
    if (L0 >= lines) return;
#if GLOBAL_SCRATCH
    __global float4 *scratch = scratch_base + (size_t)L0 * (size_t)n;
#else
    __local float4 *scratch = scratch_base;
#endif
#if UNIFORM
    const float4 c0 = coefs[0], c1 = coefs[1], c2 = coefs[2];
#endif
    size_t row[LINES];
    float4 x1[LINES], p1[LINES], p2[LINES], q1[LINES], q2[LINES];
    for (int l = 0; l < LINES; ++l) {
        row[l] = (size_t)min(L0 + l, lines - 1) * (size_t)n;
        x1[l] = 0.0f; p1[l] = 0.0f; p2[l] = 0.0f; q1[l] = 0.0f; q2[l] = 0.0f;
    }
    for (int i = 0; i < n; ++i) {
#pragma unroll
        for (int l = 0; l < LINES; ++l) {
            COEFFS(row[l] + i)
            const float4 x = src[row[l] + i];
            const float4 p = c0.x * x + c0.y * x1[l] - c1.x * p1[l] - c1.y * p2[l];
            const float4 q = c1.z * x + c1.w * x1[l] - c2.z * q1[l] - c2.w * q2[l];
            scratch[l * n + i] = p + q;
            x1[l] = x; p2[l] = p1[l]; p1[l] = p; q2[l] = q1[l]; q1[l] = q;
        }
    }
    float4 a1[LINES], a2[LINES];
    for (int l = 0; l < LINES; ++l) {
        a1[l] = 0.0f; a2[l] = 0.0f; p1[l] = 0.0f; p2[l] = 0.0f; q1[l] = 0.0f; q2[l] = 0.0f;
    }
    const int valid = min(LINES, lines - L0);
    for (int i = n - 1; i >= 0; --i) {
#pragma unroll
        for (int l = 0; l < LINES; ++l) {
            COEFFS(row[l] + i)
            const float4 p = c0.z * a1[l] + c0.w * a2[l] - c1.x * p1[l] - c1.y * p2[l];
            const float4 q = c2.x * a1[l] + c2.y * a2[l] - c2.z * q1[l] - c2.w * q2[l];
            const float4 x = src[row[l] + i];
            if (l < valid) STORE(scratch[l * n + i] + p + q,
                                 dst + (size_t)i * (size_t)lines + (size_t)(L0 + l));
            a2[l] = a1[l]; a1[l] = x; p2[l] = p1[l]; p1[l] = p; q2[l] = q1[l]; q1[l] = q;
        }
    }
}
