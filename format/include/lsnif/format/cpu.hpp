// The instruction sets this CPU and its operating system let the kernels use, detected
// once per process. The one place that asks CPUID and XCR0: every run-time dispatch in
// format/ and trainer/ reads cpu_features(), so a build without -march=native (or a CPU
// without AVX-512) takes the same decisions everywhere. Internal C++ API, like forward.hpp.
#pragma once

#include <cstdint>
#include <string>

namespace lsnif::format {

struct CpuFeatures {
    bool avx2_fma = false;     // AVX2, FMA3 and F16C (x86-64-v3's vector set), YMM state saved by the OS
    bool avx512 = false;       // AVX-512 F, BW, DQ and VL, with the opmask and ZMM states saved
    bool avx512_bf16 = false;  // avx512 and AVX512_BF16 (VDPBF16PS, VCVTNEPS2BF16)
    bool avx512_vnni = false;  // avx512 and AVX512_VNNI (VPDPBUSD)
    // avx512_bf16, AMX-TILE and AMX-BF16, with the tile state enabled in XCR0. Linux also
    // makes a process ask for the tile state before using it (trainer/src/amx.cpp does).
    bool amx_bf16 = false;
};

// Detected on the first call (thread-safe), constant afterwards; all false on non-x86 builds.
// Capped by the environment variable LSNIF_ISA when it is set (isa_cap below): the cap only
// removes instruction sets, never adds one the CPU lacks.
const CpuFeatures& cpu_features();

// What the CPU and OS offer, before the cap: for code outside lsnif's own kernels that must
// make a choice the cap does not change (conversion pins Embree to AVX2 on every machine).
const CpuFeatures& detected_cpu_features();

// LSNIF_ISA caps the instruction sets every kernel may use, so that one machine can run each
// path it supports (tests compare their bytes; a user can reproduce another machine's
// speed). The levels, each including the ones before it:
//   generic     no vector kernels (the portable C++ paths)
//   avx2        AVX2 + FMA3 + F16C (x86-64-v3)
//   avx512      AVX-512 F/BW/DQ/VL and, where present, AVX-512 VNNI (the reader's int8)
//   avx512bf16  AVX-512 BF16
//   amx         AMX-TILE + AMX-BF16: no cap
// Conversion results (assets, metrics, decisions) are the same at every level; speed and
// the reader's own int8/bf16 inference choice are not.
enum class IsaLevel : std::uint8_t { generic, avx2, avx512, avx512bf16, amx };
const char* isa_level_name(IsaLevel level);

// The cap LSNIF_ISA asks for: amx (no cap) when the variable is unset or empty. A value that
// names no level is reported by isa_cap_error() and leaves the features uncapped; callers
// that can refuse to run (the lsnif command) check it first.
IsaLevel isa_cap();
// "" or "LSNIF_ISA=VALUE: not one of generic, avx2, avx512, avx512bf16, amx".
const std::string& isa_cap_error();
// The highest level cpu_features() offers (after the cap).
IsaLevel isa_level();

}  // namespace lsnif::format
