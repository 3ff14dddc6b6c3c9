// Whether this build compiles the reader's x86 vector kernels (LSNIF_HAVE_X86 = 1: GCC or
// Clang on x86-64) or only its portable code (0: other CPUs and compilers, and any build
// with LSNIF_PORTABLE defined — the CMake option of the same name, with which the format
// tests check the portable code on an x86 machine). The kernels are chosen at run time by
// cpu_features(); with LSNIF_HAVE_X86 = 0 they do not exist and cpu_features() reports
// no vector extension. Internal to format/src.
#pragma once

#if defined(__x86_64__) && defined(__GNUC__) && !defined(LSNIF_PORTABLE)
#define LSNIF_HAVE_X86 1
#include <cpuid.h>
#include <immintrin.h>

#include <cstddef>

namespace lsnif::format::detail {

// The mask of a 16-lane vector whose lane 0 is element `begin` of a run ending at `end`:
// lanes [0, min(end - begin, 16)), none when end <= begin.
inline __mmask16 lane_mask16(std::size_t begin, std::size_t end) {
    return begin >= end        ? __mmask16(0)
           : end - begin >= 16 ? __mmask16(0xffff)
                               : __mmask16((1u << (end - begin)) - 1u);
}

}  // namespace lsnif::format::detail
#else
#define LSNIF_HAVE_X86 0
#endif
