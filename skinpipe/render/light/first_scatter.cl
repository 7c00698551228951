// Where each covered texel's light first scattered from (first_scatter.py): per point
// and channel the tangent-plane shift towards the light, sin(theta_t) x the mean path,
// mapped to texels through the point's triangle (its 2 x 3 map), read bilinearly over
// covered texels (renormalised) where the texel found there lies within a quarter of
// the shift (or two texels) of the shifted point; elsewhere (a seam, a fold, a chart's
// edge) flagged for Embree's projection and left at the point's own value.
__kernel void upstream_read(__global const int *row_of, const int size,
                            __global const int *texel, __global const int *triangle,
                            __global const float *texels_per_length,  // (T, 6)
                            __global const float *texel_length,       // (T,)
                            __global const float *points,             // (M, 3): all rows
                            const int at_point, const float lx, const float ly,
                            const float lz,  // the light's centre, or towards it
                            __global const float *normals,            // (N, 3)
                            __global const float *mean_path,          // (N, 3)
                            const float eta, const int first,
                            __global const float *values,             // (M, 3)
                            const int n, __global float *out,         // (N, 3)
                            __global uchar *cast)                     // (N, 3)
{
    const int i = get_global_id(0);
    if (i >= n) return;
    const int row = first + i;
    const float3 p = vload3(row, points), nrm = vload3(i, normals);
    const float3 l = (float3)(lx, ly, lz);
    const float3 w = at_point ? normalize(l - p) : l;
    const float cos_i = dot(w, nrm);
    const float3 tangent = w - cos_i * nrm;
    const float len = length(tangent);
    const float sin_t = (cos_i >= 0.0f ? len : 1.0f) / eta;
    const float3 unit = tangent / fmax(len, 1e-12f);
    const int flat = texel[i], tri = triangle[i];
    const float k0 = texels_per_length[6 * tri], k1 = texels_per_length[6 * tri + 1],
                k2 = texels_per_length[6 * tri + 2], k3 = texels_per_length[6 * tri + 3],
                k4 = texels_per_length[6 * tri + 4], k5 = texels_per_length[6 * tri + 5];
    const float near_enough = 2.0f * texel_length[tri];
    for (int c = 0; c < 3; ++c) {
        const float own = values[3 * row + c];
        const float3 s = unit * (sin_t * mean_path[3 * i + c]);
        const float ax = (float)(flat % size) + 0.5f + k0 * s.x + k1 * s.y + k2 * s.z;
        const float ay = (float)(flat / size) + 0.5f + k3 * s.x + k4 * s.y + k5 * s.z;
        const int nx = clamp((int)ax, 0, size - 1), ny = clamp((int)ay, 0, size - 1);
        const int found = row_of[ny * size + nx];
        int inside = 0;
        if (found >= 0)
            inside = length(vload3(found, points) - (p + s)) <= fmax(0.25f * length(s),
                                                                     near_enough);
        cast[3 * i + c] = (uchar)!inside;
        if (!inside) {
            out[3 * i + c] = own;
            continue;
        }
        const float fx = ax - 0.5f, fy = ay - 0.5f;
        const float x0 = floor(fx), y0 = floor(fy);
        const float tx = fx - x0, ty = fy - y0;
        float sum = 0.0f, total = 0.0f;
        for (int t = 0; t < 4; ++t) {
            const int dx = t & 1, dy = t >> 1;
            const int x = clamp((int)x0 + dx, 0, size - 1), y = clamp((int)y0 + dy, 0, size - 1);
            const int r = row_of[y * size + x];
            if (r < 0) continue;
            const float wt = (dx ? tx : 1.0f - tx) * (dy ? ty : 1.0f - ty);
            sum += wt * values[3 * r + c];
            total += wt;
        }
        out[3 * i + c] = total > 1e-6f ? sum / total : own;
    }
}
