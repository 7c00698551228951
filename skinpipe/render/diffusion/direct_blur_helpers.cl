
// One work item: a band of B texels (float4) across a strip of rows. Every input row
// of the strip and its RV-row halo is filtered horizontally into slot y % (2RV + 1) of
// the ring; each output row is the vertical filter over the ring. Interior bands work
// on pairs of texels (float8, one AVX register) without bounds tests; edge bands per
// texel with zero outside the image. Helpers are always_inline and loads are plain
// pointer reads: PoCL leaves inline functions and vload/vstore as calls, which keep
// the work-item loop from using registers for the weights (measured 2x slower).
#define INL __attribute__((always_inline)) inline
#define RING (2 * RV + 1)
#define SLOT(y) (((y) + RING * 4096) % RING)
typedef float8 __attribute__((aligned(16))) float8_u;  // one unaligned 256-bit load
INL float8 pair(__global const float4 *row, int x) { return *(__global const float8_u *)(row + x); }
INL float4 tex0(__global const float4 *row, int x, int width) {
    return (x >= 0 && x < width) ? row[x] : (float4)(0.0f);
}
INL float8 both(__global const float4 *wa, __global const float4 *wb, int k) {
    return (float8)(wa[k], wb[k]);
}
