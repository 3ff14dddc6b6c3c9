// splitmix64 (Steele, Lea & Flood, "Fast splittable pseudorandom number generators",
// 2014): tiny, and the same sequence on every platform and compiler, which the
// determinism guarantees need (std:: distributions differ between standard libraries).
// Internal to trainer/.
#pragma once

#include <cstdint>

namespace lsnif::trainer::detail {

struct SplitMix64 {
    std::uint64_t s;
    std::uint64_t next() {
        std::uint64_t z = (s += 0x9E3779B97F4A7C15ull);
        z = (z ^ (z >> 30)) * 0xBF58476D1CE4E5B9ull;
        z = (z ^ (z >> 27)) * 0x94D049BB133111EBull;
        return z ^ (z >> 31);
    }
    // Uniform in [lo, hi) with 24 random bits (float resolution).
    float uniform(float lo, float hi) { return lo + (hi - lo) * float(next() >> 40) * (1.0f / 16777216.0f); }
    // Uniform in [0, 1) with 53 random bits.
    double u01() { return double(next() >> 11) * (1.0 / 9007199254740992.0); }
};

}  // namespace lsnif::trainer::detail
