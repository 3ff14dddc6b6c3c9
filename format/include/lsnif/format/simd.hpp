// Vector types and a lane-wise fused multiply-add for kernels written once and compiled per
// instruction set (format's dense_layer, the trainer's weight-gradient product).
//
// The project compiles without FMA contraction (CMakeLists.txt), so that a * b + c rounds
// twice in every build, -march=native or not. A kernel that wants one rounding per
// multiply-add says so with simd::fma, and every variant of it computes exactly std::fma of
// each lane: the AVX-512, AVX2 and portable variants of a kernel give the same bits
// (docs/pipeline.md "The same bytes everywhere"). Internal C++ API, like forward.hpp.
#pragma once

#include <cmath>
#include <cstdint>

#include <lsnif/format/half.hpp>

#if defined(__x86_64__) && defined(__GNUC__)
#include <immintrin.h>
#endif

namespace lsnif::format::simd {

typedef float F4 __attribute__((vector_size(16), aligned(4)));
typedef float F8 __attribute__((vector_size(32), aligned(4)));
typedef float F16 __attribute__((vector_size(64), aligned(4)));

template <int W>
struct Lanes;
template <>
struct Lanes<4> {
    using type = F4;
};
template <>
struct Lanes<8> {
    using type = F8;
};
template <>
struct Lanes<16> {
    using type = F16;
};
// W floats, unaligned (loads and stores of rows at any float offset).
template <int W>
using Vec = typename Lanes<W>::type;

// a * b + c on every lane with one rounding, a broadcast. The portable variant calls std::fma
// per lane (a hardware instruction where the compiler targets FMA, the C library's exact
// software routine elsewhere); the x86 variants are VFMADD with the same rounding.
inline F4 fma(float a, F4 b, F4 c) {
    F4 r;
    for (int i = 0; i < 4; ++i) r[i] = std::fma(a, b[i], c[i]);
    return r;
}

#if defined(__x86_64__) && defined(__GNUC__)
__attribute__((target("avx2,fma"))) inline F8 fma(float a, F8 b, F8 c) {
    return (F8)_mm256_fmadd_ps(_mm256_set1_ps(a), (__m256)b, (__m256)c);
}
__attribute__((target("avx512f"))) inline F16 fma(float a, F16 b, F16 c) {
    return (F16)_mm512_fmadd_ps(_mm512_set1_ps(a), (__m512)b, (__m512)c);
}
#endif

// W weights from fp32 or from fp16 storage, chosen by the type of the tag `V` (a Vec<W>).
// Widening binary16 to binary32 is exact (VCVTPH2PS, or half_to_float), so a kernel reading
// fp16 weights computes the same bits as one reading the same values stored in fp32.
inline F4 load(const float* p, F4) {
    return *reinterpret_cast<const F4*>(p);
}
inline F4 load(const std::uint16_t* p, F4) {
    return F4{half_to_float(p[0]), half_to_float(p[1]), half_to_float(p[2]), half_to_float(p[3])};
}

#if defined(__x86_64__) && defined(__GNUC__)
__attribute__((target("avx2,fma"))) inline F8 load(const float* p, F8) {
    return *reinterpret_cast<const F8*>(p);
}
__attribute__((target("avx2,fma,f16c"))) inline F8 load(const std::uint16_t* p, F8) {
    return (F8)_mm256_cvtph_ps(_mm_loadu_si128(reinterpret_cast<const __m128i*>(p)));
}
__attribute__((target("avx512f"))) inline F16 load(const float* p, F16) {
    return *reinterpret_cast<const F16*>(p);
}
__attribute__((target("avx512f"))) inline F16 load(const std::uint16_t* p, F16) {
    return (F16)_mm512_cvtph_ps(_mm256_loadu_si256(reinterpret_cast<const __m256i*>(p)));
}
#endif

}  // namespace lsnif::format::simd
