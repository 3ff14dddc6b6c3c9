// IEEE 754 binary16 <-> binary32 conversion, portable and exact.
// float_to_half rounds to nearest, ties to even (the rounding F16C's VCVTPS2PH uses with
// imm 0), so weights exported here match what a GPU upload path would compute.
#pragma once

#include <bit>
#include <cstdint>
#include <span>
#include <vector>

namespace lsnif::format {

inline float half_to_float(std::uint16_t h) {
    const std::uint32_t sign = std::uint32_t(h & 0x8000u) << 16;
    std::uint32_t exp = (h >> 10) & 0x1Fu;
    std::uint32_t man = h & 0x3FFu;
    std::uint32_t bits;
    if (exp == 0x1F) {  // Inf / NaN (payload kept, quiet bit forced)
        bits = sign | 0x7F800000u | (man << 13) | (man ? 0x00400000u : 0u);
    } else if (exp != 0) {
        bits = sign | ((exp + 112u) << 23) | (man << 13);
    } else if (man == 0) {
        bits = sign;
    } else {  // subnormal half: value = man * 2^-24; normalize it
        int e = -1;
        do {
            ++e;
            man <<= 1;
        } while ((man & 0x400u) == 0);
        bits = sign | (std::uint32_t(112 - e) << 23) | ((man & 0x3FFu) << 13);
    }
    return std::bit_cast<float>(bits);
}

inline std::uint16_t float_to_half(float f) {
    const std::uint32_t x = std::bit_cast<std::uint32_t>(f);
    const std::uint16_t sign = std::uint16_t((x >> 16) & 0x8000u);
    const std::uint32_t exp = (x >> 23) & 0xFFu;
    std::uint32_t man = x & 0x7FFFFFu;
    if (exp == 0xFF) return std::uint16_t(sign | 0x7C00u | (man ? 0x200u | (man >> 13) : 0u));
    const int e = int(exp) - 127 + 15;
    if (e >= 0x1F) return std::uint16_t(sign | 0x7C00u);  // overflow -> Inf
    if (e <= 0) {
        if (e < -10) return sign;  // underflows to signed zero (also below half of min subnormal)
        man |= 0x800000u;
        const int shift = 14 - e;  // 14..24
        std::uint32_t h = man >> shift;
        const std::uint32_t rem = man & ((1u << shift) - 1u);
        const std::uint32_t half = 1u << (shift - 1);
        if (rem > half || (rem == half && (h & 1u))) ++h;
        return std::uint16_t(sign | h);
    }
    std::uint32_t h = (std::uint32_t(e) << 10) | (man >> 13);
    const std::uint32_t rem = man & 0x1FFFu;
    if (rem > 0x1000u || (rem == 0x1000u && (h & 1u))) ++h;  // may carry into exponent: correct
    return std::uint16_t(sign | h);
}

// Every value of `halves` as binary32 (exact: each binary16 is a binary32).
inline std::vector<float> halves_to_floats(std::span<const std::uint16_t> halves) {
    std::vector<float> f(halves.size());
    for (std::size_t i = 0; i < halves.size(); ++i) f[i] = half_to_float(halves[i]);
    return f;
}

inline bool half_is_finite(std::uint16_t h) {
    return (h & 0x7C00u) != 0x7C00u;
}

}  // namespace lsnif::format
