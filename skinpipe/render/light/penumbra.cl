
// penumbra_texels at the texels of the list at (flat indices): the maximum and minimum
// of the visibility over traced texels within PERIOD - 1 of the texel (the filter's
// reach), where an untraced texel or one beyond the texture's edge counts 0 for the
// maximum and 1 for the minimum (the numpy definition's constant edges); comparisons
// only, so the same booleans
__kernel void penumbra_at(__global const float *vis, __global const uchar *traced,
                          __global const int *at, const int h, const int w, const int n,
                          __global uchar *out)
{
    const int o = get_global_id(0);
    if (o >= n) return;
    const int i = at[o], x = i % w, y = i / w;
    float hi = -INFINITY, lo = INFINITY;
    for (int dy = 1 - PERIOD; dy < PERIOD; ++dy) {
        for (int dx = 1 - PERIOD; dx < PERIOD; ++dx) {
            const int xx = x + dx, yy = y + dy;
            const int j = yy * w + xx;
            const int in = xx >= 0 && xx < w && yy >= 0 && yy < h && traced[j];
            const float up = in ? vis[j] : 0.0f, down = in ? vis[j] : 1.0f;
            hi = up > hi ? up : hi;
            lo = down < lo ? down : lo;
        }
    }
    const float v = vis[i];
    out[o] = traced[i] && (hi > lo || (v > 0.0f && v < 1.0f));
}
