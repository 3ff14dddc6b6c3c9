// The instruction sets this CPU and its operating system let the kernels use, detected
// once per process. The one place that asks CPUID and XCR0: every run-time dispatch in
// format/ and trainer/ reads cpu_features(), so a build without -march=native (or a CPU
// without AVX-512) takes the same decisions everywhere. Internal C++ API, like forward.hpp.
#pragma once

#include <cstdint>

namespace lsnif::format {

struct CpuFeatures {
    bool avx2_fma = false;     // AVX2 and FMA3, with the YMM state saved by the OS
    bool avx512 = false;       // AVX-512 F, BW, DQ and VL, with the opmask and ZMM states saved
    bool avx512_bf16 = false;  // avx512 and AVX512_BF16 (VDPBF16PS, VCVTNEPS2BF16)
    bool avx512_vnni = false;  // avx512 and AVX512_VNNI (VPDPBUSD)
    // avx512_bf16, AMX-TILE and AMX-BF16, with the tile state enabled in XCR0. Linux also
    // makes a process ask for the tile state before using it (trainer/src/amx.cpp does).
    bool amx_bf16 = false;
};

// Detected on the first call (thread-safe), constant afterwards; all false on non-x86 builds.
const CpuFeatures& cpu_features();

}  // namespace lsnif::format
