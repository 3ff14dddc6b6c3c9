// The toolchain's random numbers (header-only): splitmix64 (Steele, Lea and Flood, "Fast
// splittable pseudorandom number generators", OOPSLA 2014). Tiny, and the same sequence
// on every platform and compiler, which the determinism guarantees need (std::
// distributions differ between standard libraries). Not for cryptography.
#pragma once

#include <cstdint>

namespace lsnif::base {

// The Weyl increment of splitmix64 (2^64 / golden ratio, odd).
inline constexpr std::uint64_t kGoldenGamma = 0x9E3779B97F4A7C15ull;

// splitmix64's output function: a bijective 64-bit mix, also used alone to derive
// unrelated stream seeds from (seed, index).
constexpr std::uint64_t mix64(std::uint64_t z) {
    z = (z ^ (z >> 30)) * 0xBF58476D1CE4E5B9ull;
    z = (z ^ (z >> 27)) * 0x94D049BB133111EBull;
    return z ^ (z >> 31);
}

struct SplitMix64 {
    std::uint64_t s;
    std::uint64_t next() { return mix64(s += kGoldenGamma); }
    // Uniform in [0, 1) with 24 random bits (float resolution).
    float uniform01f() { return float(next() >> 40) * (1.0f / 16777216.0f); }
    // Uniform in [lo, hi) with 24 random bits. Written as one expression on purpose: with
    // FMA contraction, regrouping the products would change the last bit of the result
    // (and with it every trained weight).
    float uniform(float lo, float hi) { return lo + (hi - lo) * float(next() >> 40) * (1.0f / 16777216.0f); }
    // Uniform in [0, 1) with 53 random bits.
    double u01() { return double(next() >> 11) * (1.0 / 9007199254740992.0); }
};

}  // namespace lsnif::base
