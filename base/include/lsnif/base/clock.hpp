// The toolchain's one wall-clock helper (header-only): elapsed seconds on the steady clock,
// for stage timings and benchmarks (never for anything that changes results).
#pragma once

#include <chrono>

namespace lsnif::base {

using Clock = std::chrono::steady_clock;

inline double seconds_since(Clock::time_point t0) {
    return std::chrono::duration<double>(Clock::now() - t0).count();
}

}  // namespace lsnif::base
