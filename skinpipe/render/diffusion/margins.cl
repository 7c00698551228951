
// The margin points of _numpy_points on the device, in doubles, each operation as numpy
// does it and in its order (no contraction into fused multiply-adds), so that every
// point lands where numpy's lands, bit for bit. Point i: texel empty[i] at its centre
// for i < n_empty, else texel partial[j / S] at offset sub[j % S] (j = i - n_empty);
// b[texel index]: its start texel's frame (position, normal, J = dP / d level texel).
#pragma OPENCL EXTENSION cl_khr_fp64 : enable
#pragma OPENCL FP_CONTRACT OFF

#define POINT_TEXEL                                                                   \
    long m; int t; double ox = 0.0, oy = 0.0;                                         \
    if (i < n_empty) { m = empty[i]; t = i; }                                          \
    else {                                                                            \
        const int j = i - n_empty;                                                    \
        m = partial[j / S]; t = n_empty + j / S;                                      \
        ox = sub[2 * (j % S)]; oy = sub[2 * (j % S) + 1];                             \
    }                                                                                 \
    const int b = bs[t];                                                              \
    const double hx = (double)(m % w) + ox, hy = (double)(m / w) + oy;

__kernel void margin_rays(__global const long *empty, __global const long *partial,
                          __global const int *bs, __global const double *sub,
                          __global const long *start, __global const double *position,
                          __global const double *normal, __global const double *jac,
                          __global const double *jac_norm, const long w,
                          const int n_empty, const int n,
                          __global float *origin, __global float *direction,
                          __global double *reach_out)
{
    const int i = get_global_id(0);
    if (i >= n) return;
    POINT_TEXEL
    const long s = start[b];
    const double sx = hx - (double)(s % w), sy = hy - (double)(s / w);
    __global const double *J = jac + 6 * (size_t)b;  // (3, 2)
    double o[3];
    for (int r = 0; r < 3; ++r) { o[r] = J[2 * r] * sx; o[r] = o[r] + J[2 * r + 1] * sy; }
    const double len = sqrt(o[0] * o[0] + o[1] * o[1] + o[2] * o[2]);
    const double reach = 0.5 * len + 2.0 * jac_norm[b];
    for (int r = 0; r < 3; ++r) {
        const double nr = normal[3 * (size_t)b + r];
        const double target = position[3 * (size_t)b + r] + o[r];
        origin[3 * (size_t)i + r] = (float)(target + nr * reach);
        direction[3 * (size_t)i + r] = (float)(-nr);
    }
    reach_out[i] = reach;
}

__kernel void margin_hits(__global const long *empty, __global const long *partial,
                          __global const int *bs, __global const double *sub,
                          __global const double *jac, const long w, const int n_empty,
                          const int n, __global const long *prim, __global const float *bu,
                          __global const float *bv, __global const float *dist,
                          __global const double *reach, __global const long *scene_owner,
                          const long mesh_index, __global const double *corners,
                          __global const double *inverse_jac, __global const int *tri_chart,
                          __global const long *shift, __global const int *owner,
                          const double scale, __global uchar *keep,
                          __global int *chart_out, __global double *xy_out,
                          __global long *t_out)
{
    const int i = get_global_id(0);
    if (i >= n) return;
    POINT_TEXEL
    keep[i] = 0;
    const long p = prim[i];
    if (p < 0 || scene_owner[2 * p] != mesh_index || !((double)dist[i] <= 2.0 * reach[i]))
        return;
    const long tri = scene_owner[2 * p + 1];
    const float u = bu[i], v = bv[i];
    const float w0 = 1.0f - u - v;
    __global const double *c = corners + 6 * (size_t)tri;  // (3, 2)
    double xy[2];
    for (int k = 0; k < 2; ++k) {
        xy[k] = c[k] * (double)w0 + c[2 + k] * (double)u;
        xy[k] = xy[k] + c[4 + k] * (double)v;
    }
    const int chart = tri_chart[tri];
    const int is_partial = i >= n_empty;
    if (is_partial) {  // the centre carried back: J^+ (J o), o the point's offset
        __global const double *J = jac + 6 * (size_t)b;
        double back[3];
        for (int r = 0; r < 3; ++r) {
            back[r] = J[2 * r] * ox; back[r] = back[r] + J[2 * r + 1] * oy;
        }
        __global const double *I = inverse_jac + 6 * (size_t)tri;  // (2, 3)
        for (int k = 0; k < 2; ++k) {
            double d = I[3 * k] * back[0];
            d = d + I[3 * k + 1] * back[1];
            d = d + I[3 * k + 2] * back[2];
            xy[k] = xy[k] - d;
        }
    }
    const double lx = (xy[0] + 0.5) / scale - 0.5 + (double)shift[2 * chart];
    const double ly = (xy[1] + 0.5) / scale - 0.5 + (double)shift[2 * chart + 1];
    const double dx = lx - (hx - ox), dy = ly - (hy - oy);
    const int far = sqrt(dx * dx + dy * dy) > 2.0;
    keep[i] = (!is_partial || chart != owner[m] || far) ? 1 : 0;
    chart_out[i] = chart;
    xy_out[2 * (size_t)i] = lx;
    xy_out[2 * (size_t)i + 1] = ly;
    t_out[i] = tri;
}

// texel_coverage on the device: a texel its chart's border may cross (one of its eight
// neighbours on another chart or none) counts which of 4 x 4 sub-samples the chart's
// triangles on it and its neighbours cover, each test as numpy makes it.
__kernel void texel_coverage(__global const int *chart, __global const int *triangle,
                             __global const int *tri_chart, __global const double *corners,
                             const int h, const int w, __global float *out)
{
    const int x = get_global_id(0), y = get_global_id(1);
    if (x >= w || y >= h) return;
    const int own = chart[y * w + x];
    if (own < 0) { out[y * w + x] = 0.0f; return; }
    int border = 0;
    for (int dy = -1; dy <= 1; ++dy)
        for (int dx = -1; dx <= 1; ++dx) {
            const int yy = y + dy, xx = x + dx;
            const int c = (yy < 0 || yy >= h || xx < 0 || xx >= w) ? -1 : chart[yy * w + xx];
            border |= c != own;
        }
    if (!border) { out[y * w + x] = 1.0f; return; }
    int inside = 0;  // a bit per sub-sample
    for (int dy = -1; dy <= 1; ++dy)
        for (int dx = -1; dx <= 1; ++dx) {
            const int yy = y + dy, xx = x + dx;
            const int t = (yy < 0 || yy >= h || xx < 0 || xx >= w) ? -1
                          : triangle[yy * w + xx];
            if (t < 0 || tri_chart[t] != own) continue;
            __global const double *q = corners + 6 * (size_t)t;  // (3, 2)
            const double e1x = q[2] - q[0], e1y = q[3] - q[1];
            const double e2x = q[4] - q[0], e2y = q[5] - q[1];
            double det = e1x * e2y - e1y * e2x;
            det = fabs(det) > 1e-12 ? det : INFINITY;
            for (int s = 0; s < 16; ++s) {  // sub-sample (s % 4, s / 4) of 4 x 4
                const double sx = ((double)(s % 4) + 0.5) / 4.0 - 0.5;
                const double sy = ((double)(s / 4) + 0.5) / 4.0 - 0.5;
                const double ddx = ((double)x + sx) - q[0], ddy = ((double)y + sy) - q[1];
                const double b1 = (ddx * e2y - ddy * e2x) / det;
                const double b2 = (e1x * ddy - e1y * ddx) / det;
                if (b1 >= -1e-9 && b2 >= -1e-9 && b1 + b2 <= 1.0 + 1e-9) inside |= 1 << s;
            }
        }
    out[y * w + x] = (float)(max(popcount(inside), 1)) / 16.0f;
}
