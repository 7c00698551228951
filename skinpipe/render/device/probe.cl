
__kernel void probe(__global const float4 *src, __global float4 *dst,
                    volatile __global int *peak, __local float4 *tile) {
    const int l = get_local_id(0), n = get_local_size(0), g = get_global_id(0);
    tile[l] = src[g];
    barrier(CLK_LOCAL_MEM_FENCE);
    float4 v = tile[n - 1 - l] * 2.0f;
#if NT_STORE
    __builtin_nontemporal_store(v, dst + g);
#else
    dst[g] = v;
#endif
    atomic_max(peak, (int)src[g].x);
}
