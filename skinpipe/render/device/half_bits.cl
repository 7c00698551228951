
// Half floats by their bits, as numpy's float16 <-> float32 (round to nearest even):
// vload_half and vstore_half are calls on PoCL, not inlined (with vload_half the
// diffusion's level-0 batches at texture 4096 took 120 ms, 70 with float32 weights).
// half_bits_to_float (finite halves): the exponent and mantissa shifted into a float's
// place, the exponent rebased from half's bias (15) to float's (127); a subnormal half
// (exponent 0, m 2^-24) read as the normal number 2^-14 (1 + m 2^-10), less 2^-14: both
// exact.
__attribute__((always_inline)) inline float half_bits_to_float(ushort h)
{
    const uint b = (uint)(h & 0x7fff) << 13;
    const float v = (h & 0x7c00) ? as_float(b + (112u << 23))
                                 : as_float(b + (113u << 23)) - 6.103515625e-05f;
    return (h & 0x8000) ? -v : v;
}
// float_to_half_bits (finite floats below 65520, half's largest after rounding; after
// Giesen's float_to_half_fast3_rtne): below 2^-14 the float's addition to 0.5 (whose
// ulp is 2^-24, a subnormal half's step) rounds to nearest even, and its bits less 0.5's
// are the half's; above, the exponent rebased and the 13 dropped bits rounded by adding
// 0xfff plus the kept mantissa's lowest bit (ties to even).
__attribute__((always_inline)) inline ushort float_to_half_bits(float f)
{
    const uint sign = as_uint(f) & 0x80000000u, u = as_uint(f) ^ sign;
    const uint small = as_uint(as_float(u) + 0.5f) - as_uint(0.5f);
    const uint normal = (u + 0xc8000fffu + ((u >> 13) & 1u)) >> 13;  // 0xc8...: -112 << 23
    return (ushort)((u < (113u << 23) ? small : normal) | (sign >> 16));
}
