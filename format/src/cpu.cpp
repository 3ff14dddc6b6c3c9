// CPUID and XCR0 read once (cpu.hpp). Bit positions: Intel SDM vol. 2A, CPUID leaf 1 (ECX)
// and leaf 7 sub-leaves 0 and 1; XCR0 state components: vol. 1 §13.1.
#include <lsnif/format/cpu.hpp>

#include "x86.hpp"

#include <cstdlib>
#include <cstring>
#include <iterator>

namespace lsnif::format {

namespace {

#if LSNIF_HAVE_X86

constexpr unsigned bit(int k) {
    return 1u << k;
}

// XCR0: the register states the OS saves on context switches. 0 when XGETBV is not allowed.
std::uint64_t enabled_state_components(unsigned leaf1_ecx) {
    if (!(leaf1_ecx & bit(27))) return 0;  // OSXSAVE
    std::uint32_t lo, hi;
    __asm__ volatile("xgetbv" : "=a"(lo), "=d"(hi) : "c"(0));
    return (std::uint64_t(hi) << 32) | lo;
}

CpuFeatures detect() {
    CpuFeatures f;
    unsigned a, b, c, d;
    if (!__get_cpuid(1, &a, &b, &c, &d)) return f;
    const unsigned leaf1_ecx = c;
    const std::uint64_t xcr0 = enabled_state_components(leaf1_ecx);
    constexpr std::uint64_t kYmm = bit(1) | bit(2);                    // SSE, AVX
    constexpr std::uint64_t kZmm = kYmm | bit(5) | bit(6) | bit(7);    // opmask, ZMM_Hi256, Hi16_ZMM
    constexpr std::uint64_t kTile = std::uint64_t(bit(17) | bit(18));  // XTILECFG, XTILEDATA
    if (!__get_cpuid_count(7, 0, &a, &b, &c, &d)) return f;
    const unsigned max_subleaf = a, leaf7_ebx = b, leaf7_ecx = c, leaf7_edx = d;
    const bool fma = leaf1_ecx & bit(12), f16c = leaf1_ecx & bit(29), avx2 = leaf7_ebx & bit(5);
    f.avx2_fma = fma && f16c && avx2 && (xcr0 & kYmm) == kYmm;
    const bool avx512 = (leaf7_ebx & bit(16)) && (leaf7_ebx & bit(17)) && (leaf7_ebx & bit(30)) &&
                        (leaf7_ebx & bit(31));  // F, DQ, BW, VL
    f.avx512 = f.avx2_fma && avx512 && (xcr0 & kZmm) == kZmm;
    f.avx512_vnni = f.avx512 && (leaf7_ecx & bit(11));
    const bool bf16 = max_subleaf >= 1 && __get_cpuid_count(7, 1, &a, &b, &c, &d) && (a & bit(5));
    f.avx512_bf16 = f.avx512 && bf16;
    const bool amx = (leaf7_edx & bit(22)) && (leaf7_edx & bit(24));  // AMX-BF16, AMX-TILE
    f.amx_bf16 = f.avx512_bf16 && amx && (xcr0 & kTile) == kTile;
    return f;
}

#else

CpuFeatures detect() {
    return {};
}

#endif

constexpr const char* kLevelNames[] = {"generic", "avx2", "avx512", "avx512bf16", "amx"};

struct Cap {
    IsaLevel level = IsaLevel::amx;
    std::string error;
};

Cap read_cap() {
    Cap cap;
    const char* v = std::getenv("LSNIF_ISA");
    if (!v || !*v) return cap;
    for (std::uint8_t i = 0; i < std::size(kLevelNames); ++i)
        if (std::strcmp(v, kLevelNames[i]) == 0) {
            cap.level = IsaLevel(i);
            return cap;
        }
    cap.error = std::string("LSNIF_ISA=") + v + ": not one of generic, avx2, avx512, avx512bf16, amx";
    return cap;
}

const Cap& cap() {
    static const Cap c = read_cap();
    return c;
}

CpuFeatures capped(CpuFeatures f, IsaLevel level) {
    if (level < IsaLevel::amx) f.amx_bf16 = false;
    if (level < IsaLevel::avx512bf16) f.avx512_bf16 = false;
    if (level < IsaLevel::avx512) f.avx512 = f.avx512_vnni = false;
    if (level < IsaLevel::avx2) f.avx2_fma = false;
    return f;
}

}  // namespace

const CpuFeatures& detected_cpu_features() {
    static const CpuFeatures features = detect();  // thread-safe one-time initialization
    return features;
}

const CpuFeatures& cpu_features() {
    static const CpuFeatures features = capped(detected_cpu_features(), cap().level);
    return features;
}

const char* isa_level_name(IsaLevel level) {
    return kLevelNames[std::size_t(level)];
}

IsaLevel isa_cap() {
    return cap().level;
}

const std::string& isa_cap_error() {
    return cap().error;
}

IsaLevel isa_level() {
    const CpuFeatures& f = cpu_features();
    return f.amx_bf16      ? IsaLevel::amx
           : f.avx512_bf16 ? IsaLevel::avx512bf16
           : f.avx512      ? IsaLevel::avx512
           : f.avx2_fma    ? IsaLevel::avx2
                           : IsaLevel::generic;
}

}  // namespace lsnif::format
