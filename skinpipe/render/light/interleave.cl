
// one work-item per texel (AT: per texel of the list at, flat indices); planes (light,
// y, x) of the visibility, its sign bit set where the texel traced no ray toward the
// light (-0.0 for 0: visibility_plane): one load a light and tap where a plane of its
// own was two, and the host made that plane as floats (texture 4096, period 4, two
// lights: the kernel 0.53-0.56 -> 0.46 s); normals packed xyz per texel, read as
// floats (vload3, dot and abs are calls or vector values to PoCL, which then does not
// vectorise the work-item loop). The tent spans PERIOD - 1 texels each side, weights
// (PERIOD - |dx|)(PERIOD - |dy|): each class of the period weighs the same.
// A light's sums are scalars of their own (FOR_LIGHTS) and a tap beyond the texture's
// edge or across a crease weighs 0 rather than being skipped: with arrays of LIGHTS
// sums and a branch per tap the kernel kept its sums on the stack, and the 49 taps of
// period 4 at texture 4096 took 1.0-1.2 s against 0.7-1.0; the same values (a tap of
// weight 0 adds +0 to sums of non-negative terms)
#if LIGHTS == 1
#define FOR_LIGHTS(M) M(0)
#elif LIGHTS == 2
#define FOR_LIGHTS(M) M(0) M(1)
#elif LIGHTS == 3
#define FOR_LIGHTS(M) M(0) M(1) M(2)
#else
#define FOR_LIGHTS(M) M(0) M(1) M(2) M(3)
#endif
__kernel void filter_interleaved(__global const float *vis,
                                 __global const float *normal, __global float *out,
                                 const int h, const int w, const float min_cos
#if AT
                                 , __global const int *at, const int n)
{
    const int o = get_global_id(0);
    if (o >= n) return;
    const int i = at[o], x = i % w, y = i / w, stride = n;  // out: (light, n)
#else
                                 )
{
    const int x = get_global_id(0), y = get_global_id(1);
    if (x >= w || y >= h) return;
    const int i = y * w + x, o = i, stride = h * w;  // out: planes like vis
#endif
    const float nx = normal[3 * i], ny = normal[3 * i + 1], nz = normal[3 * i + 2];
    const int plane = h * w;
#define SUMS(l) float num##l = 0.0f, den##l = 0.0f;
    FOR_LIGHTS(SUMS)
    for (int dy = 1 - PERIOD; dy < PERIOD; ++dy) {
        const int yy = y + dy;
        const int y_in = yy >= 0 && yy < h;
        const int row = (y_in ? yy : y) * w;
        const float ty = (float)(PERIOD - (dy < 0 ? -dy : dy));
        for (int dx = 1 - PERIOD; dx < PERIOD; ++dx) {
            const int xx = x + dx;
            const int in = y_in && xx >= 0 && xx < w;
            const int j = row + (in ? xx : x);  // an edge's tap reads the texel, weight 0
            const float cos_n = nx * normal[3 * j] + ny * normal[3 * j + 1] +
                                nz * normal[3 * j + 2];
            const float tent = in && !(cos_n < min_cos) ?
                               ty * (float)(PERIOD - (dx < 0 ? -dx : dx)) : 0.0f;
// an untraced tap weighs 0 (its value is -v: 0 x -v adds -0 to sums of non-negative
// terms, which leaves them as they were)
#define TAP(l) { const float v = vis[l * plane + j]; \
                 const float kt = as_int(v) >= 0 ? tent : 0.0f; \
                 num##l += kt * v; den##l += kt; }
            FOR_LIGHTS(TAP)
        }
    }
// no tap weighed: the texel's own visibility, its sign bit cleared (fabs is a call)
#define OUT(l) out[l * stride + o] = den##l > 0.0f ? num##l / den##l : \
                                     as_float(as_uint(vis[l * plane + i]) & 0x7fffffffu);
    FOR_LIGHTS(OUT)
}
