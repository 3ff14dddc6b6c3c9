// A 16 x 16 in-register transpose of dwords for the AVX-512 kernels of format/ (the bf16
// packers, the output layer), and the split of 16 points' xyz into three vectors. Internal
// to format/; x86-64 with GCC or Clang only.
#pragma once

#include <immintrin.h>

namespace lsnif::format::detail {

// Rows r[0..15] (16 dwords each) become columns: afterwards r[j] holds element j of every
// former row. GCC 12's unpack/shuffle intrinsics pass a self-initialized
// _mm512_undefined_epi32() as the (unused) merge source, which -W(maybe-)uninitialized
// reports once inlined (the sanitizer build says -Wuninitialized); a false positive.
#pragma GCC diagnostic push
#pragma GCC diagnostic ignored "-Wmaybe-uninitialized"
#pragma GCC diagnostic ignored "-Wuninitialized"
__attribute__((target("avx512f"))) inline void transpose16(__m512i r[16]) {
    __m512i t[16], u[16];
    for (int i = 0; i < 8; ++i) {
        t[2 * i] = _mm512_unpacklo_epi32(r[2 * i], r[2 * i + 1]);
        t[2 * i + 1] = _mm512_unpackhi_epi32(r[2 * i], r[2 * i + 1]);
    }
    // u[4i + q], 128-bit lane L: rows 4i..4i+3 at column 4L + q.
    for (int i = 0; i < 4; ++i) {
        u[4 * i + 0] = _mm512_unpacklo_epi64(t[4 * i], t[4 * i + 2]);
        u[4 * i + 1] = _mm512_unpackhi_epi64(t[4 * i], t[4 * i + 2]);
        u[4 * i + 2] = _mm512_unpacklo_epi64(t[4 * i + 1], t[4 * i + 3]);
        u[4 * i + 3] = _mm512_unpackhi_epi64(t[4 * i + 1], t[4 * i + 3]);
    }
    // Column 4L + q gathers lane L of u[q], u[4 + q], u[8 + q], u[12 + q].
    for (int q = 0; q < 4; ++q) {
        const __m512i v0 = _mm512_shuffle_i32x4(u[q], u[4 + q], 0x44);
        const __m512i v1 = _mm512_shuffle_i32x4(u[q], u[4 + q], 0xee);
        const __m512i v2 = _mm512_shuffle_i32x4(u[8 + q], u[12 + q], 0x44);
        const __m512i v3 = _mm512_shuffle_i32x4(u[8 + q], u[12 + q], 0xee);
        r[q] = _mm512_shuffle_i32x4(v0, v2, 0x88);
        r[4 + q] = _mm512_shuffle_i32x4(v0, v2, 0xdd);
        r[8 + q] = _mm512_shuffle_i32x4(v1, v3, 0x88);
        r[12 + q] = _mm512_shuffle_i32x4(v1, v3, 0xdd);
    }
}

// Points xyz[0..15] (48 floats, point k's coordinate on axis a at 3k + a, as RayPoints::g
// holds them) as three vectors: x[a] holds axis a of every point, point k in lane k.
__attribute__((target("avx512f"))) inline void point_axes16(const float* xyz, __m512 (&x)[3]) {
    const __m512 v0 = _mm512_loadu_ps(xyz), v1 = _mm512_loadu_ps(xyz + 16), v2 = _mm512_loadu_ps(xyz + 32);
    const __m512i three_k = _mm512_setr_epi32(0, 3, 6, 9, 12, 15, 18, 21, 24, 27, 30, 33, 36, 39, 42, 45);
    for (int a = 0; a < 3; ++a) {
        const __m512i at = _mm512_add_epi32(three_k, _mm512_set1_epi32(a));
        const __mmask16 third = _mm512_cmpge_epi32_mask(at, _mm512_set1_epi32(32));
        x[a] = _mm512_mask_permutexvar_ps(_mm512_permutex2var_ps(v0, at, v1), third, at, v2);
    }
}
#pragma GCC diagnostic pop

}  // namespace lsnif::format::detail
