// cpu_features() (lsnif/format/cpu.hpp) against GCC's own CPU detection (libgcc's
// __builtin_cpu_supports, which also checks the OS-enabled register states): the one
// place that reads CPUID must agree with it on every flag, whatever machine runs the test,
// after the cap LSNIF_ISA sets (CTest runs this binary under every cap: tests/CMakeLists.txt).
#include <doctest/doctest.h>

#include <lsnif/format/cpu.hpp>

using lsnif::format::cpu_features;
using lsnif::format::CpuFeatures;
using lsnif::format::isa_cap;
using lsnif::format::IsaLevel;

TEST_CASE("cpu_features agrees with the compiler's CPU detection on every flag") {
#if defined(__x86_64__) && defined(__GNUC__) && !defined(LSNIF_PORTABLE)
    __builtin_cpu_init();
    auto has = [](bool x) { return x; };
    const IsaLevel cap = isa_cap();
    const bool avx2_fma =
        cap >= IsaLevel::avx2 && has(__builtin_cpu_supports("avx2")) && has(__builtin_cpu_supports("fma"));
    const bool avx512 = cap >= IsaLevel::avx512 && avx2_fma && has(__builtin_cpu_supports("avx512f")) &&
                        has(__builtin_cpu_supports("avx512bw")) && has(__builtin_cpu_supports("avx512dq")) &&
                        has(__builtin_cpu_supports("avx512vl"));
    const bool avx512_bf16 =
        cap >= IsaLevel::avx512bf16 && avx512 && has(__builtin_cpu_supports("avx512bf16"));
    const bool avx512_vnni = avx512 && has(__builtin_cpu_supports("avx512vnni"));
    const bool amx_bf16 = cap >= IsaLevel::amx && avx512_bf16 && has(__builtin_cpu_supports("amx-tile")) &&
                          has(__builtin_cpu_supports("amx-bf16"));
    const CpuFeatures& f = cpu_features();
    MESSAGE("LSNIF_ISA cap: " << lsnif::format::isa_level_name(cap) << ", highest level offered: "
                              << lsnif::format::isa_level_name(lsnif::format::isa_level()));
    CHECK(lsnif::format::isa_cap_error().empty());
    CHECK(lsnif::format::isa_level() <= cap);
    MESSAGE("this CPU: avx2+fma " << f.avx2_fma << ", avx512 " << f.avx512 << ", avx512-bf16 "
                                  << f.avx512_bf16 << ", avx512-vnni " << f.avx512_vnni << ", amx-bf16 "
                                  << f.amx_bf16);
    CHECK(f.avx2_fma == avx2_fma);
    CHECK(f.avx512 == avx512);
    CHECK(f.avx512_bf16 == avx512_bf16);
    CHECK(f.avx512_vnni == avx512_vnni);
    CHECK(f.amx_bf16 == amx_bf16);
#else
    // Another CPU, or the portable build (LSNIF_PORTABLE): no vector kernel exists to pick.
    const CpuFeatures& f = cpu_features();
    CHECK_FALSE(f.avx2_fma);
    CHECK_FALSE(f.avx512);
    CHECK_FALSE(f.avx512_bf16);
    CHECK_FALSE(f.avx512_vnni);
    CHECK_FALSE(f.amx_bf16);
#endif
}

TEST_CASE("cpu_features is detected once: every call returns the same object") {
    CHECK(&cpu_features() == &cpu_features());
}
