
// offset_ray_origin per coordinate (points and normals as 3N floats): the integer
// offset away from zero, or p + s n within OFFSET_ORIGIN of zero, rounded as numpy
// rounds it (a product and a sum, not one fused operation)
#pragma OPENCL FP_CONTRACT OFF
__kernel void offset_origin(__global const float *p, __global const float *nrm,
                            const float int_scale, const float near, const float origin,
                            const int n, __global float *out)
{
    const int i = get_global_id(0);
    if (i >= n) return;
    const float pc = p[i], nc = nrm[i];
    const int of_i = (int)(int_scale * nc);  // toward zero, as numpy's astype
    const uint shifted = (uint)as_int(pc) + (uint)(pc < 0.0f ? -of_i : of_i);
    out[i] = (pc < 0.0f ? -pc : pc) < origin ? pc + near * nc : as_float(shifted);
}
