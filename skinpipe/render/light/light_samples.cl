
// Sample k of every point of a sphere light (KIND 1: uniform in the cone it subtends)
// or an untextured dome (KIND 2: cosine-weighted about the normal), as
// LightSampler.sample does it, with the fraction that enters the skin folded into the
// weight: the boundary's transmission T(cos), linear in the table (boundary.py). The cone and the
// frame (Duff et al. 2017) are made here per point, not uploaded.
// Eight points per work-item, their arithmetic in float8 (loads and stores lane by
// lane): PoCL's LLVM finds vectorising its work-item loop "not beneficial" for this
// kernel (the strided xyz, the gathered strata and table), and the scalar loop took
// 8.9 ms for the sphere on 481k points, against 2.3-3.0 in vectors, the same values
// bit for bit (each lane's operations are the scalar ones, in the same order; the
// square root is OpenCL's correctly rounded one). Lanes past n repeat the last point
// and are not stored.
// The shadow ray's length comes out too (to the sphere's surface, from the distance
// made here): 0 where the sample carries nothing (the host's np.where for it took 2.2 ms
// a sample at texture 1024, the cast rays' own time 80 ms).
#define LANES(M) M(0) M(1) M(2) M(3) M(4) M(5) M(6) M(7)
__kernel void sample_entering(__global const float *origin, __global const float *normal,
                              __global const float *strata_uv, __global const uchar *classes,
                              __global const int *sets,
                              const float lx, const float ly, const float lz,
                              const float radius, __global const float *table,
                              const int table_n, const int k, __global float *dir,
                              __global float *weight, __global float *ray_far, const int n,
                              const int first)
{
    const int i0 = (int)get_global_id(0) * 8;
    if (i0 >= n) return;
    size_t at[8];  // each lane's point: n of them from `first`, written from 0
#define AT(l) at[l] = (size_t)first + (size_t)(i0 + l < n ? i0 + l : n - 1);
    LANES(AT)
    // (u, cos 2 pi v, sin 2 pi v) of the stratum: the host takes the trigonometry
    float8 u, cv, sv;
#if INTERLEAVED  // the k-th stratum of the point's class (sets: a row of COUNT each)
#define UV(l) { __global const float *uv = strata_uv + \
                    (size_t)4 * sets[(int)classes[at[l]] * COUNT + k]; \
                u.s##l = uv[0]; cv.s##l = uv[1]; sv.s##l = uv[2]; }
    LANES(UV)
#else
    u = strata_uv[4 * k]; cv = strata_uv[4 * k + 1]; sv = strata_uv[4 * k + 2];
#endif
    float8 nx, ny, nz;
#define NORMAL(l) nx.s##l = normal[3 * at[l]]; ny.s##l = normal[3 * at[l] + 1]; \
                  nz.s##l = normal[3 * at[l] + 2];
    LANES(NORMAL)
    float8 ax, ay, az, a, b, c;  // the frame's axis; local coordinates along t, b, axis
#if KIND == 1
    float8 ox, oy, oz;
#define ORIGIN(l) ox.s##l = origin[3 * at[l]]; oy.s##l = origin[3 * at[l] + 1]; \
                  oz.s##l = origin[3 * at[l] + 2];
    LANES(ORIGIN)
    const float8 tx = lx - ox, ty = ly - oy, tz = lz - oz;
    const float8 dist = sqrt(tx * tx + ty * ty + tz * tz);
    const float8 inv = 1.0f / (dist > 1e-12f ? dist : 1e-12f);
    ax = tx * inv; ay = ty * inv; az = tz * inv;
    const float8 q = radius / (dist > 1.0001f * radius ? dist : 1.0001f * radius);
    const float8 cos_max = sqrt(1.0f - q * q);
    const float8 one_minus = q * q / (1.0f + cos_max);  // 1 - cos_max without cancellation
    c = 1.0f - u * one_minus;
    const float8 s2 = 1.0f - c * c;
    const float8 sin_t = sqrt(s2 > 0.0f ? s2 : 0.0f);
    a = sin_t * cv; b = sin_t * sv;
#else
    ax = nx; ay = ny; az = nz;
    const float8 r = sqrt(u);
    c = sqrt(u < 1.0f ? 1.0f - u : 0.0f);
    a = r * cv; b = r * sv;
#endif
    const float8 sgn = az >= 0.0f ? 1.0f : -1.0f;
    const float8 kk = -1.0f / (sgn + az);
    const float8 xy = ax * ay * kk;
    const float8 dx = a * (1.0f + sgn * ax * ax * kk) + b * xy + c * ax;
    const float8 dy = a * sgn * xy + b * (sgn + ay * ay * kk) + c * ay;
    const float8 dz = -a * sgn * ax - b * ay + c * az;
    const float8 cos_n = nx * dx + ny * dy + nz * dz;
    const float8 x = (cos_n > 0.0f ? (cos_n < 1.0f ? cos_n : 1.0f) : 0.0f) *
                     (float)(table_n - 1);
    const int8 xi = convert_int8(x);  // toward zero, as C's cast
    const int8 j = xi < table_n - 2 ? xi : table_n - 2;
    float8 t0, t1;
#define TABLE(l) t0.s##l = table[j.s##l]; t1.s##l = table[j.s##l + 1];
    LANES(TABLE)
    const float8 enters = t0 + (x - convert_float8(j)) * (t1 - t0);
#if KIND == 1
    const float8 wi = (cos_n > 0.0f ? cos_n : 0.0f) * 6.283185307179586f * one_minus
                      / (float)COUNT * enters;
    const float8 far = wi > 0.0f && dist > radius ? dist - radius : 0.0f;  // ends at it
#else
    const float8 wi = 3.141592653589793f / (float)COUNT * enters;
    const float8 far = wi > 0.0f ? INFINITY : 0.0f;
#endif
#define STORE(l) if (i0 + l < n) { const size_t o = (size_t)(i0 + l); \
        dir[3 * o] = dx.s##l; dir[3 * o + 1] = dy.s##l; dir[3 * o + 2] = dz.s##l; \
        weight[o] = wi.s##l; ray_far[o] = far.s##l; }
    LANES(STORE)
}
