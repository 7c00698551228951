// The wide diffusion terms on the surface itself (surface_terms.py). Points are sorted by
// the cell of a uniform 3D grid (a fraction of the reach on a side).

inline int grid_cell(const float at, const float origin, const float per_cell, const int n)
{
    return clamp((int)floor((at - origin) * per_cell), 0, n - 1);
}

// Distance from x to the interval [lo, lo + side] (0 inside it).
inline float outside(const float x, const float lo, const float side)
{
    return fmax(fmax(lo - x, x - lo - side), 0.0f);
}

// Per term k < n_terms: the sum over the points q within its reach of p (normal n) of
// (exp(-d^2 inv_two_var[k]) - its value at the reach) area(q) facing(q) value(q), with
// the weights' sum in w, into sum[k]. d is the distance between p and q in 3D, as in
// the dipole's BSSRDF (Jensen et al. 2001). Per row of the grid's cells only the run
// the ball of the widest reach crosses is read; the terms share the reads.
inline void gather(const float3 p, const float3 n, __global const float4 *point,
                   __global const float4 *normal, __global const float4 *value,
                   __global const int *grid_start, const float3 origin,
                   const float per_cell, const int nx, const int ny, const int nz,
                   const float4 inv_two_var, const float4 reach2, const int n_terms,
                   float4 *sum)
{
    const float iv[4] = {inv_two_var.x, inv_two_var.y, inv_two_var.z, inv_two_var.w};
    const float r2[4] = {reach2.x, reach2.y, reach2.z, reach2.w};
    float at_reach[4];
    float widest2 = 0.0f;
    for (int k = 0; k < n_terms; ++k) {
        // less its value at the reach: a point crossing the reach as p moves changes
        // nothing (cut off, one at 4 sigma would step a term 2% of its peak by 1.7%)
        at_reach[k] = exp(-r2[k] * iv[k]);
        widest2 = fmax(widest2, r2[k]);
        sum[k] = (float4)(0.0f);
    }
    const float side = 1.0f / per_cell, reach = sqrt(widest2);
    const int z0 = grid_cell(p.z - reach, origin.z, per_cell, nz);
    const int z1 = grid_cell(p.z + reach, origin.z, per_cell, nz);
    const int y0 = grid_cell(p.y - reach, origin.y, per_cell, ny);
    const int y1 = grid_cell(p.y + reach, origin.y, per_cell, ny);
    for (int z = z0; z <= z1; ++z) {
        const float dz = outside(p.z, origin.z + z * side, side);
        for (int y = y0; y <= y1; ++y) {
            const float dy = outside(p.y, origin.y + y * side, side);
            const float left = widest2 - dz * dz - dy * dy;
            if (left < 0.0f) continue;
            const float dx = sqrt(left);
            // a row's cells along x are consecutive in the sorted order
            const int row = (z * ny + y) * nx;
            const int stop = grid_start[row + grid_cell(p.x + dx, origin.x, per_cell, nx) + 1];
            for (int s = grid_start[row + grid_cell(p.x - dx, origin.x, per_cell, nx)];
                 s < stop; ++s) {
                const float4 q = point[s];
                const float3 d = q.xyz - p;
                const float chord2 = dot(d, d);
                if (chord2 > widest2) continue;
                // the profile was measured on a half-space: a point whose normal turns
                // from p's by theta lies off p's plane, and less of its light reaches
                // p through the thinner medium between them. Full weight to 60
                // degrees, none from 90 (the far side of a fold or a thin part: that
                // light comes through the volume, thin_parts.py)
                const float facing = clamp(2.0f * dot(n, normal[s].xyz), 0.0f, 1.0f);
                const float4 v = (float4)(value[s].xyz, 1.0f) * (q.w * facing);
                for (int k = 0; k < n_terms; ++k)
                    if (chord2 < r2[k]) sum[k] += (exp(-chord2 * iv[k]) - at_reach[k]) * v;
            }
        }
    }
}

inline float4 normalised(const float4 sum)
{
    return sum.w > 0.0f ? (float4)(sum.xyz / sum.w, 1.0f) : (float4)(0.0f);
}

// Up to four terms at each of the points (xyz mm, area mm^2; sorted), out[4 i + k]: the
// normalised sum over the points of a Gaussian of variance 1 / (2 inv_two_var[k]) of
// the distance between them, to its reach.
__kernel void gather_on_surface(__global const float4 *point, __global const float4 *normal,
                                __global const float4 *value, const int n_points,
                                __global const int *grid_start, const float ox,
                                const float oy, const float oz, const float per_cell,
                                const int nx, const int ny, const int nz,
                                const float4 inv_two_var, const float4 reach2,
                                const int n_terms, __global float4 *out)
{
    const int i = get_global_id(0);
    if (i >= n_points) return;
    float4 sum[4];
    gather(point[i].xyz, normal[i].xyz, point, normal, value, grid_start,
           (float3)(ox, oy, oz), per_cell, nx, ny, nz, inv_two_var, reach2, n_terms, sum);
    for (int k = 0; k < n_terms; ++k)
        out[4 * i + k] = normalised(sum[k]);
}

// The points' values at other places on the surface (``at``: xyz mm; ``facing``: their
// unit normals): the normalised Gaussian of the distance, narrow as the points' spacing.
__kernel void gather_at(__global const float4 *at, __global const float4 *facing,
                        const int n_at, __global const float4 *point,
                        __global const float4 *normal, __global const float4 *value,
                        __global const int *grid_start, const float ox, const float oy,
                        const float oz, const float per_cell, const int nx, const int ny,
                        const int nz, const float inv_two_var, const float reach2,
                        __global float4 *out)
{
    const int i = get_global_id(0);
    if (i >= n_at) return;
    float4 sum[1];
    gather(at[i].xyz, facing[i].xyz, point, normal, value, grid_start, (float3)(ox, oy, oz),
           per_cell, nx, ny, nz, (float4)(inv_two_var, 0.0f, 0.0f, 0.0f),
           (float4)(reach2, 0.0f, 0.0f, 0.0f), 1, sum);
    out[i] = normalised(sum[0]);
}
