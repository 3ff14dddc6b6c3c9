// bf16 operands for the MLP products (lsnif/format/bf16.hpp): rounding, packing into the
// row and VNNI layouts, and the AVX-512 BF16 product. Everything that needs AVX-512 BF16 is
// compiled with function-level target attributes and chosen at run time, so the library
// builds and runs on any x86-64 (and elsewhere, on the scalar paths).
#include <lsnif/format/bf16.hpp>
#include <lsnif/format/cpu.hpp>

#include <algorithm>
#include <cstring>

#include "x86.hpp"
#if LSNIF_HAVE_X86
#include "avx512_transpose.hpp"
#endif

namespace lsnif::format {

namespace {

// ---- scalar packers (reference, and machines without AVX-512 BF16) ----------------------

void pack_rows_scalar(const float* src, std::size_t rows, std::size_t cols, std::size_t lds, Bf16* dst,
                      std::size_t ldd, std::size_t rows_pad) {
    for (std::size_t r = 0; r < rows_pad; ++r)
        for (std::size_t c = 0; c < ldd; ++c)
            dst[r * ldd + c] = (r < rows && c < cols) ? to_bf16(src[r * lds + c]) : 0;
}

void pack_transposed_scalar(const float* src, std::size_t rows, std::size_t cols, std::size_t lds, Bf16* dst,
                            std::size_t ldd, std::size_t cols_pad) {
    for (std::size_t c = 0; c < cols_pad; ++c)
        for (std::size_t r = 0; r < ldd; ++r)
            dst[c * ldd + r] = (r < rows && c < cols) ? to_bf16(src[r * lds + c]) : 0;
}

void pack_vnni_scalar(const float* src, std::size_t k, std::size_t n, std::size_t lds, Bf16* dst,
                      std::size_t ldd, std::size_t k_pad) {
    for (std::size_t p = 0; p < k_pad / 2; ++p)
        for (std::size_t j = 0; j < ldd / 2; ++j)
            for (std::size_t h = 0; h < 2; ++h) {
                const std::size_t kk = 2 * p + h;
                dst[p * ldd + 2 * j + h] = (kk < k && j < n) ? to_bf16(src[kk * lds + j]) : 0;
            }
}

#if LSNIF_HAVE_X86

#define LSNIF_BF16_TARGET __attribute__((target("avx512f,avx512bw,avx512vl,avx512bf16")))

// ---- AVX-512 BF16 packers: VCVTNEPS2BF16 rounds exactly like to_bf16 --------------------

using detail::lane_mask16;

LSNIF_BF16_TARGET inline __m512 load_row(const float* row, bool valid, __mmask16 mask) {
    return valid ? _mm512_maskz_loadu_ps(mask, row) : _mm512_setzero_ps();
}

// 32 bf16 as 16 dwords, dword j = (bf16(even[j]), bf16(odd[j])): one VNNI row segment.
LSNIF_BF16_TARGET inline __m512i interleave_pairs(__m512 even, __m512 odd) {
    // cvtne2ps puts `even` in the low 16 bf16 lanes and `odd` in the high ones.
    const __m512i idx = _mm512_set_epi16(31, 15, 30, 14, 29, 13, 28, 12, 27, 11, 26, 10, 25, 9, 24, 8, 23, 7,
                                         22, 6, 21, 5, 20, 4, 19, 3, 18, 2, 17, 1, 16, 0);
    return _mm512_permutexvar_epi16(idx, (__m512i)_mm512_cvtne2ps_pbh(odd, even));
}

LSNIF_BF16_TARGET void pack_rows_avx512(const float* src, std::size_t rows, std::size_t cols, std::size_t lds,
                                        Bf16* dst, std::size_t ldd, std::size_t rows_pad) {
    for (std::size_t r = 0; r < rows_pad; ++r)
        for (std::size_t c = 0; c < ldd; c += 16) {
            const __m512 v = load_row(src + r * lds + c, r < rows, lane_mask16(c, cols));
            const __m256i h = (__m256i)_mm512_cvtneps_pbh(v);
            _mm256_mask_storeu_epi16(dst + r * ldd + c, lane_mask16(c, ldd), h);
        }
}

LSNIF_BF16_TARGET void pack_vnni_avx512(const float* src, std::size_t k, std::size_t n, std::size_t lds,
                                        Bf16* dst, std::size_t ldd, std::size_t k_pad) {
    const std::size_t width = ldd / 2;  // columns per VNNI row
    for (std::size_t p = 0; p < k_pad / 2; ++p)
        for (std::size_t j = 0; j < width; j += 16) {
            const __mmask16 m = lane_mask16(j, n);
            const __m512 even = load_row(src + 2 * p * lds + j, 2 * p < k, m);
            const __m512 odd = load_row(src + (2 * p + 1) * lds + j, 2 * p + 1 < k, m);
            _mm512_mask_storeu_epi32(dst + p * ldd + 2 * j, lane_mask16(j, width),
                                     interleave_pairs(even, odd));
        }
}

// Blocks of 32 source rows x 16 columns: row pairs become dwords (as in the VNNI packer),
// then a 16 x 16 dword transpose turns them into 16 destination rows of 32 bf16.
// Requires ldd % 32 == 0 and cols_pad % 16 == 0 (the caller checks).
LSNIF_BF16_TARGET void pack_transposed_avx512(const float* src, std::size_t rows, std::size_t cols,
                                              std::size_t lds, Bf16* dst, std::size_t ldd,
                                              std::size_t cols_pad) {
    for (std::size_t r0 = 0; r0 < ldd; r0 += 32)
        for (std::size_t c0 = 0; c0 < cols_pad; c0 += 16) {
            const __mmask16 m = lane_mask16(c0, cols);
            __m512i d[16];
            for (std::size_t p = 0; p < 16; ++p) {
                const std::size_t r = r0 + 2 * p;
                d[p] = interleave_pairs(load_row(src + r * lds + c0, r < rows, m),
                                        load_row(src + (r + 1) * lds + c0, r + 1 < rows, m));
            }
            detail::transpose16(d);
            for (std::size_t j = 0; j < 16; ++j) _mm512_storeu_si512(dst + (c0 + j) * ldd + r0, d[j]);
        }
}

// ---- AVX-512 BF16 GEMM (machines without AMX) ------------------------------------------

// One block of MB rows x NV 16-column vectors of C. VDPBF16PS multiplies a broadcast dword
// of A (the bf16 pair A[r][2p], A[r][2p+1]) with B's VNNI row p (16 such pairs) and adds
// both products to each fp32 lane: the VNNI layout the AMX path uses serves here unchanged.
// With MB = 6, NV = 4: 24 accumulators, 4 B vectors and one broadcast in 29 of 32 registers.
// The block runs over pairs [0, head) and [tail, end) (head <= tail <= end <= pairs, from
// live_groups): the rows' other pairs are zero (ZeroColumns) and add nothing.
template <int MB, int NV>
LSNIF_BF16_TARGET void dp_block(std::size_t r0, std::size_t j0, std::size_t n, std::size_t head,
                                std::size_t tail, std::size_t end, const Bf16* a, std::size_t lda,
                                const Bf16* b, std::size_t ldb, float* c, std::size_t ldc,
                                const Epilogue& e) {
    __m512 acc[MB][NV];
    __mmask16 mask[NV];
    for (int v = 0; v < NV; ++v) mask[v] = lane_mask16(j0 + 16 * v, n);
    for (int m = 0; m < MB; ++m)
        for (int v = 0; v < NV; ++v)
            acc[m][v] = e.accumulate ? _mm512_maskz_loadu_ps(mask[v], c + (r0 + m) * ldc + j0 + 16 * v)
                        : e.bias     ? _mm512_maskz_loadu_ps(mask[v], e.bias + j0 + 16 * v)
                                     : _mm512_setzero_ps();
    const Bf16* arow = a + r0 * lda;
    const Bf16* bcol = b + 2 * j0;
    const auto pair_step = [&](std::size_t p) LSNIF_BF16_TARGET {
        __m512bh bv[NV];
        for (int v = 0; v < NV; ++v) bv[v] = (__m512bh)_mm512_loadu_si512(bcol + p * ldb + 32 * v);
        for (int m = 0; m < MB; ++m) {
            std::int32_t pair;
            std::memcpy(&pair, arow + m * lda + 2 * p, sizeof pair);
            const __m512bh av = (__m512bh)_mm512_set1_epi32(pair);
            for (int v = 0; v < NV; ++v) acc[m][v] = _mm512_dpbf16_ps(acc[m][v], av, bv[v]);
        }
    };
    for (std::size_t p = 0; p < head; ++p) pair_step(p);
    for (std::size_t p = tail; p < end; ++p) pair_step(p);
    for (int m = 0; m < MB; ++m)
        for (int v = 0; v < NV; ++v) {
            // ReLU as a masked move: x > 0 ? x : +0, like dense_layer (GCC 12 warns falsely
            // about _mm512_max_ps's undefined merge source).
            const __m512 x =
                e.relu ? _mm512_maskz_mov_ps(_mm512_cmp_ps_mask(acc[m][v], _mm512_setzero_ps(), _CMP_GT_OQ),
                                             acc[m][v])
                       : acc[m][v];
            _mm512_mask_storeu_ps(c + (r0 + m) * ldc + j0 + 16 * v, mask[v], x);
        }
}

template <int NV>
LSNIF_BF16_TARGET void dp_columns(std::size_t j0, std::size_t m, std::size_t n, std::size_t pairs,
                                  const Bf16* a, std::size_t lda, const Bf16* b, std::size_t ldb, float* c,
                                  std::size_t ldc, const Epilogue& e, const ZeroColumns* zeros) {
    constexpr std::size_t MB = 6;
    std::size_t r = 0;
    for (; r + MB <= m; r += MB) {
        const LiveGroups live = live_groups(zeros, r, MB, pairs, 2);
        dp_block<MB, NV>(r, j0, n, live.head, live.tail, live.end, a, lda, b, ldb, c, ldc, e);
    }
    for (; r < m; ++r) {
        const LiveGroups live = live_groups(zeros, r, 1, pairs, 2);
        dp_block<1, NV>(r, j0, n, live.head, live.tail, live.end, a, lda, b, ldb, c, ldc, e);
    }
}

LSNIF_BF16_TARGET void gemm_dp(std::size_t m, std::size_t n, std::size_t k, const Bf16* a, std::size_t lda,
                               const Bf16* b, std::size_t ldb, float* c, std::size_t ldc, const Epilogue& e,
                               const ZeroColumns* zeros) {
    const std::size_t pairs = k / 2;
    std::size_t j = 0;
    for (; j + 64 <= n; j += 64) dp_columns<4>(j, m, n, pairs, a, lda, b, ldb, c, ldc, e, zeros);
    for (; j < n; j += 16) dp_columns<1>(j, m, n, pairs, a, lda, b, ldb, c, ldc, e, zeros);
}

#endif  // LSNIF_HAVE_X86

}  // namespace

void pack_rows(const float* src, std::size_t rows, std::size_t cols, std::size_t lds, Bf16* dst,
               std::size_t ldd, std::size_t rows_pad) {
#if LSNIF_HAVE_X86
    if (cpu_features().avx512_bf16) return pack_rows_avx512(src, rows, cols, lds, dst, ldd, rows_pad);
#endif
    pack_rows_scalar(src, rows, cols, lds, dst, ldd, rows_pad);
}

void pack_transposed(const float* src, std::size_t rows, std::size_t cols, std::size_t lds, Bf16* dst,
                     std::size_t ldd, std::size_t cols_pad) {
#if LSNIF_HAVE_X86
    if (cpu_features().avx512_bf16 && ldd % 32 == 0 && cols_pad % 16 == 0)
        return pack_transposed_avx512(src, rows, cols, lds, dst, ldd, cols_pad);
#endif
    pack_transposed_scalar(src, rows, cols, lds, dst, ldd, cols_pad);
}

void pack_vnni(const float* src, std::size_t k, std::size_t n, std::size_t lds, Bf16* dst, std::size_t ldd,
               std::size_t k_pad) {
#if LSNIF_HAVE_X86
    if (cpu_features().avx512_bf16 && ldd % 2 == 0) return pack_vnni_avx512(src, k, n, lds, dst, ldd, k_pad);
#endif
    pack_vnni_scalar(src, k, n, lds, dst, ldd, k_pad);
}

void gemm_bf16_dp(std::size_t m, std::size_t n, std::size_t k, const Bf16* a, std::size_t lda, const Bf16* b,
                  std::size_t ldb, float* c, std::size_t ldc, const Epilogue& e,
                  [[maybe_unused]] const ZeroColumns* zeros) {
#if LSNIF_HAVE_X86
    if (m && n && cpu_features().avx512_bf16) return gemm_dp(m, n, k, a, lda, b, ldb, c, ldc, e, zeros);
#endif
    // No AVX-512 BF16: the same product in plain loops (fp32 accumulation of exact bf16
    // products; summation order differs from the kernel's). Far too slow for real work; it
    // exists so a contract violation degrades to slowness instead of SIGILL.
    for (std::size_t r = 0; r < m; ++r)
        for (std::size_t j = 0; j < n; ++j) {
            float s = e.accumulate ? c[r * ldc + j] : e.bias ? e.bias[j] : 0.0f;
            for (std::size_t kk = 0; kk < k; ++kk)
                s += from_bf16(a[r * lda + kk]) * from_bf16(b[(kk / 2) * ldb + 2 * j + kk % 2]);
            c[r * ldc + j] = e.relu ? std::max(s, 0.0f) : s;
        }
}

}  // namespace lsnif::format
