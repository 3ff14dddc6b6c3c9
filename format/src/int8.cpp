// 8-bit hidden layers (lsnif/format/int8.hpp): weight and row quantization, and the product
// on AVX-512 VNNI with a scalar path of identical results. The AVX-512 code is compiled with
// function-level target attributes and chosen at run time, so the library builds and runs on
// any x86-64 (and elsewhere, on the scalar paths).
#include <lsnif/format/cpu.hpp>
#include <lsnif/format/int8.hpp>

#include <algorithm>
#include <cmath>
#include <cstring>
#include <limits>

#include "x86.hpp"
#if LSNIF_HAVE_X86
#include "avx512_transpose.hpp"
#endif

namespace lsnif::format {

namespace {

// Range of the quantized values: symmetric 127 levels each way for signed data, 255 for
// unsigned (a ReLU's output).
struct QuantRange {
    float lo, hi;
};
constexpr QuantRange kSigned{-127.0f, 127.0f}, kUnsigned{0.0f, 255.0f};

// nearbyint(v) clamped to the range; NaN -> 0. The clamp bounds are integers, so clamping
// before or after rounding gives the same value (the vector path clamps first too).
inline std::int32_t quantize_value(float v, QuantRange r) {
    if (!(v == v)) return 0;
    return std::int32_t(std::nearbyint(std::clamp(v, r.lo, r.hi)));
}

// The scale of a row or column whose largest magnitude is m, and its reciprocal for
// quantizing. Both 0 for m = 0, so an all-zero row quantizes to zeros with scale 0.
struct Scale {
    float scale, inverse;
};
inline Scale scale_for(float m, QuantRange r) {
    return m > 0 ? Scale{m / r.hi, r.hi / m} : Scale{0.0f, 0.0f};
}

// The largest |x| (signed) or x (unsigned) of n values; NaN is skipped (`a > m` is false).
inline float row_max(const float* x, std::size_t n, bool signed_input) {
    float m = 0;
    for (std::size_t i = 0; i < n; ++i) {
        const float a = signed_input ? std::fabs(x[i]) : x[i];
        if (a > m) m = a;
    }
    return m;
}

void quantize_rows_scalar(const float* src, std::size_t n, std::size_t cols, std::size_t lds,
                          bool signed_input, Int8Rows& out) {
    const QuantRange range = signed_input ? kSigned : kUnsigned;
    for (std::size_t r = 0; r < n; ++r) {
        const float* x = src + r * lds;
        const Scale s = scale_for(row_max(x, cols, signed_input), range);
        std::uint8_t* q = out.q.data() + r * out.ld;
        std::int32_t sum = 0;
        for (std::size_t k = 0; k < cols; ++k) {
            const std::int32_t v = quantize_value(x[k] * s.inverse, range);
            q[k] = std::uint8_t(v);  // two's complement byte for signed values
            sum += v;
        }
        std::fill(q + cols, q + out.ld, std::uint8_t(0));
        out.scale[r] = s.scale;
        out.sum[r] = signed_input ? sum : 0;
    }
}

// The row's exact integer sum turned into the layer's output: sx * sw * sum + bias, ReLU.
inline float rescale(std::int32_t sum, float sx, float sw, float bias, bool relu) {
    const float y = std::fma(float(sum), sx * sw, bias);
    return relu ? (y > 0 ? y : 0.0f) : y;
}

void gemm_int8_scalar(std::size_t m, const Int8Rows& a, const Int8Layer& w, const float* bias, bool relu,
                      float* c, std::size_t ldc) {
    const std::size_t np = w.out_padded, quads = (w.in + 3) / 4;
    for (std::size_t r = 0; r < m; ++r)
        for (std::size_t j = 0; j < np; ++j) {
            std::int32_t sum = 0;
            for (std::size_t p = 0; p < quads; ++p)
                for (std::size_t h = 0; h < 4; ++h) {
                    const std::uint8_t x = a.q[r * a.ld + 4 * p + h], b = w.b[p * 4 * np + 4 * j + h];
                    // Signed inputs: x is a two's complement byte, b = weight + 128.
                    sum += w.signed_input ? std::int32_t(std::int8_t(x)) * std::int32_t(b)
                                          : std::int32_t(x) * std::int32_t(std::int8_t(b));
                }
            if (w.signed_input) sum -= 128 * a.sum[r];
            c[r * ldc + j] = rescale(sum, a.scale[r], w.scale[j], bias[j], relu);
        }
}

#if LSNIF_HAVE_X86

#define LSNIF_AVX512_TARGET __attribute__((target("avx512f,avx512bw,avx512vl")))
#define LSNIF_VNNI_TARGET __attribute__((target("avx512f,avx512bw,avx512vl,avx512vnni")))

// GCC 12's max, reduce and narrowing intrinsics pass a self-initialized _mm*_undefined_*()
// as the (unused) merge source, which -W(maybe-)uninitialized reports once inlined; false
// positives, silenced for the vector code only.
#pragma GCC diagnostic push
#pragma GCC diagnostic ignored "-Wmaybe-uninitialized"
#pragma GCC diagnostic ignored "-Wuninitialized"

using detail::lane_mask16;

// scale_for on 16 maxima at once: scale m / hi and inverse hi / m, both 0 where m is not
// > 0; VDIVPS rounds each lane as the scalar division does.
struct Scales16 {
    __m512 scale, inverse;
};
LSNIF_AVX512_TARGET inline Scales16 scales16(__m512 m, __m512 hi) {
    const __mmask16 live = _mm512_cmp_ps_mask(m, _mm512_setzero_ps(), _CMP_GT_OQ);
    return {_mm512_maskz_div_ps(live, m, hi), _mm512_maskz_div_ps(live, hi, m)};
}

// quantize_value(x * inverse) per lane: NaN -> 0, clamped to [lo, hi], rounded to nearest
// even (VCVTPS2DQ under the default MXCSR, as nearbyint under the default rounding mode).
LSNIF_AVX512_TARGET inline __m512i quantize16(__m512 x, __m512 inverse, __m512 lo, __m512 hi) {
    __m512 t = _mm512_mul_ps(x, inverse);
    t = _mm512_maskz_mov_ps(_mm512_cmp_ps_mask(t, t, _CMP_ORD_Q), t);
    return _mm512_cvtps_epi32(_mm512_min_ps(_mm512_max_ps(t, lo), hi));
}

// The same values as quantize_rows_scalar: max is exact in any order, and x * inverse,
// clamping, NaN -> 0 and round-to-nearest-even (VCVTPS2DQ under the default MXCSR, as
// nearbyint under the default rounding mode) are the same operations lane by lane; the
// scales of 16 rows are two correctly rounded vector divisions (VDIVPS), as scale_for's
// scalar ones. In three passes over the rows (maxima, scales, quantization), so no row
// waits on its own maximum and division.
LSNIF_AVX512_TARGET void quantize_rows_avx512(const float* src, std::size_t n, std::size_t cols,
                                              std::size_t lds, bool signed_input, Int8Rows& out) {
    const QuantRange range = signed_input ? kSigned : kUnsigned;
    const __m512 lo = _mm512_set1_ps(range.lo), hi = _mm512_set1_ps(range.hi);
    const __m512i abs_mask = _mm512_set1_epi32(0x7fffffff);
    const std::size_t vectors = out.ld / 16;
    const __mmask16 tail = lane_mask16(16 * (vectors - 1), cols);  // the last vector's live lanes
    const auto load = [&](const float* x, std::size_t v) LSNIF_AVX512_TARGET {
        return v + 1 < vectors ? _mm512_loadu_ps(x + 16 * v) : _mm512_maskz_loadu_ps(tail, x + 16 * v);
    };
    float* maxima = out.scale.data();  // each row's maximum, then its scale
    thread_local std::vector<float> inverses;
    if (inverses.size() < n + 16) inverses.resize(n + 16);
    for (std::size_t r = 0; r < n; ++r) {
        const float* x = src + r * lds;
        // VMAXPS returns its second operand when either is NaN: NaN lanes keep m.
        __m512 m = _mm512_setzero_ps();
        for (std::size_t v = 0; v < vectors; ++v) {
            __m512 xv = load(x, v);
            if (signed_input) xv = _mm512_castsi512_ps(_mm512_and_si512(_mm512_castps_si512(xv), abs_mask));
            m = _mm512_max_ps(xv, m);
        }
        maxima[r] = _mm512_reduce_max_ps(m);
    }
    for (std::size_t r = 0; r < n; r += 16) {
        const __mmask16 rows = lane_mask16(r, n);
        const Scales16 s = scales16(_mm512_maskz_loadu_ps(rows, maxima + r), hi);
        _mm512_mask_storeu_ps(inverses.data() + r, rows, s.inverse);
        _mm512_mask_storeu_ps(maxima + r, rows, s.scale);
    }
    for (std::size_t r = 0; r < n; ++r) {
        const float* x = src + r * lds;
        const __m512 inverse = _mm512_set1_ps(inverses[r]);
        std::uint8_t* q = out.q.data() + r * out.ld;
        __m512i sum = _mm512_setzero_si512();
        for (std::size_t v = 0; v < vectors; ++v) {
            const __m512i qv = quantize16(load(x, v), inverse, lo, hi);
            sum = _mm512_add_epi32(sum, qv);
            _mm_storeu_si128(reinterpret_cast<__m128i*>(q + 16 * v), _mm512_cvtepi32_epi8(qv));
        }
        out.sum[r] = signed_input ? _mm512_reduce_add_epi32(sum) : 0;
    }
}

// acc += VPDPBUSD(u, s): in each int32 lane, the four products of u's unsigned bytes with
// s's signed bytes. Inline assembly rather than _mm512_dpbusd_epi32: GCC 12 keeps the
// intrinsic's accumulators of a 6 x 4 block in memory (a load and a store around every
// instruction), a store-to-load round trip on every accumulator's dependency chain; the
// instruction itself is the same.
LSNIF_VNNI_TARGET inline __m512i dpbusd(__m512i acc, __m512i u, __m512i s) {
    __asm__("vpdpbusd %2, %1, %0" : "+v"(acc) : "v"(u), "v"(s));
    return acc;
}

// The operands of one product, unpacked from Int8Rows and Int8Layer, and where it goes:
// fp32 rows of C, or (next non-null) the ReLU'd rows quantized for the next layer.
struct Int8Operands {
    const std::uint8_t* a;  // rows layout, row stride lda
    std::size_t lda;
    const float* sx;          // per row
    const std::int32_t* sum;  // per row (signed inputs)
    const std::uint8_t* b;    // VNNI4 layout, row stride ldb = 4 * np
    std::size_t ldb;
    const float* sw;    // per column
    const float* bias;  // per column
    bool relu;
    float* c;
    std::size_t ldc;
    Int8Rows* next;
};

// Row r of the next layer's input from the NV vectors of its values before the ReLU: the same
// bytes, lane by lane, as quantize_rows_avx512 on the ReLU'd values stored as fp32. The ReLU
// is in the operations already: the maximum starts from +0 (VMAXPS keeps it against NaN and
// negative lanes, so the row's maximum is that of the ReLU'd row), and max(y * inverse, +0)
// is +0 wherever the ReLU gives +0 (y <= 0, -0 or NaN; inverse >= 0). The clamp to 255 is
// VPMOVUSDB's unsigned saturation: t = max(y * inverse, +0) is in [0, +inf], and VCVTPS2DQ
// turns t > 255 into an integer above 255 or, from 2^31 on, 0x80000000 — both saturate to
// 255, as min(t, 255) would have given.
template <int NV>
LSNIF_VNNI_TARGET inline void quantize_row(const __m512 (&y)[NV], std::size_t r, Int8Rows& next) {
    __m512 m = _mm512_setzero_ps();
    for (int v = 0; v < NV; ++v) m = _mm512_max_ps(y[v], m);
    const Scale s = scale_for(_mm512_reduce_max_ps(m), kUnsigned);
    const __m512 inverse = _mm512_set1_ps(s.inverse);
    std::uint8_t* q = next.q.data() + r * next.ld;
    for (int v = 0; v < NV; ++v) {
        const __m512 t = _mm512_max_ps(_mm512_mul_ps(y[v], inverse), _mm512_setzero_ps());
        _mm_storeu_si128(reinterpret_cast<__m128i*>(q + 16 * v),
                         _mm512_cvtusepi32_epi8(_mm512_cvtps_epi32(t)));
    }
    next.scale[r] = s.scale;
    next.sum[r] = 0;
}

// One block of MB rows x NV 16-column vectors of C. VPDPBUSD multiplies the four unsigned
// bytes of each dword of its first operand by the four signed bytes of the second and adds
// the four products to the int32 lane: a broadcast dword of A (four inputs of one row)
// against a VNNI4 row of B (four inputs of 16 columns). Signed inputs swap the roles (the
// offset weights are the unsigned operand). MB x NV = 24 accumulators, NV B vectors and one
// broadcast fit the 32 registers. The block visits quads [0, head) and [tail, end) (from
// live_groups; the others are zero). Signed inputs' correction, -128 times the row's sum of
// inputs, is where the accumulators start (int32 sums are exact in any order). Quantize: the
// block spans all columns (j0 = 0, 16 NV = np) and writes o.next instead of C.
template <int MB, int NV, bool Signed, bool Quantize>
LSNIF_VNNI_TARGET void int8_block(std::size_t r0, std::size_t j0, std::size_t head, std::size_t tail,
                                  std::size_t end, const Int8Operands& o) {
    __m512i acc[MB][NV];
    for (int m = 0; m < MB; ++m) {
        const __m512i start = _mm512_set1_epi32(Signed ? -128 * o.sum[r0 + m] : 0);
        for (int v = 0; v < NV; ++v) acc[m][v] = start;
    }
    const std::uint8_t* arow = o.a + r0 * o.lda;
    const std::uint8_t* bcol = o.b + 4 * j0;
    const std::size_t lda = o.lda, ldb = o.ldb;
    const auto quad_step = [&](std::size_t p) LSNIF_VNNI_TARGET {
        __m512i bv[NV];
        for (int v = 0; v < NV; ++v) bv[v] = _mm512_loadu_si512(bcol + p * ldb + 64 * v);
        for (int m = 0; m < MB; ++m) {
            std::int32_t quad;
            std::memcpy(&quad, arow + m * lda + 4 * p, sizeof quad);
            const __m512i av = _mm512_set1_epi32(quad);
            for (int v = 0; v < NV; ++v) {
                if constexpr (Signed)
                    acc[m][v] = dpbusd(acc[m][v], bv[v], av);
                else
                    acc[m][v] = dpbusd(acc[m][v], av, bv[v]);
            }
        }
    };
    for (std::size_t p = 0; p < head; ++p) quad_step(p);
    for (std::size_t p = tail; p < end; ++p) quad_step(p);
    for (int m = 0; m < MB; ++m) {
        const std::size_t r = r0 + m;
        const __m512 sx = _mm512_set1_ps(o.sx[r]);
        __m512 y[NV];
        for (int v = 0; v < NV; ++v) {
            const std::size_t j = j0 + 16 * v;
            const __m512 x = _mm512_cvtepi32_ps(acc[m][v]);
            y[v] =
                _mm512_fmadd_ps(x, _mm512_mul_ps(sx, _mm512_loadu_ps(o.sw + j)), _mm512_loadu_ps(o.bias + j));
            if (o.relu && !Quantize)  // quantize_row applies it
                y[v] = _mm512_maskz_mov_ps(_mm512_cmp_ps_mask(y[v], _mm512_setzero_ps(), _CMP_GT_OQ), y[v]);
            if constexpr (!Quantize) _mm512_storeu_ps(o.c + r * o.ldc + j, y[v]);
        }
        if constexpr (Quantize) quantize_row<NV>(y, r, *o.next);
    }
}

// Rows [0, m) of the columns [j0, j0 + 16 NV): blocks of MB rows, then single rows.
template <int MB, int NV, bool Signed, bool Quantize>
LSNIF_VNNI_TARGET void int8_rows(std::size_t j0, std::size_t m, std::size_t quads, const Int8Operands& o,
                                 const ZeroColumns* zeros) {
    std::size_t r = 0;
    for (; r + MB <= m; r += MB) {
        const LiveGroups live = live_groups(zeros, r, MB, quads, 4);
        int8_block<MB, NV, Signed, Quantize>(r, j0, live.head, live.tail, live.end, o);
    }
    for (; r < m; ++r) {
        const LiveGroups live = live_groups(zeros, r, 1, quads, 4);
        int8_block<1, NV, Signed, Quantize>(r, j0, live.head, live.tail, live.end, o);
    }
}

// fp32 output. 80 and 96 columns (a pruned layer, docs/model.md "Inactive neurons") in one
// block of all columns (4 x 5, 4 x 6: each quad's B vectors loaded once for 4 rows); other
// widths 64 columns at a time (6 x 4 blocks), then the rest in one block of 6 rows.
template <bool Signed>
LSNIF_VNNI_TARGET void gemm_int8_vnni(std::size_t m, const Int8Operands& o, std::size_t n, std::size_t quads,
                                      const ZeroColumns* zeros) {
    if (n == 80) return int8_rows<4, 5, Signed, false>(0, m, quads, o, zeros);
    if (n == 96) return int8_rows<4, 6, Signed, false>(0, m, quads, o, zeros);
    std::size_t j = 0;
    for (; j + 64 <= n; j += 64) int8_rows<6, 4, Signed, false>(j, m, quads, o, zeros);
    switch ((n - j) / 16) {
        case 1: return int8_rows<6, 1, Signed, false>(j, m, quads, o, zeros);
        case 2: return int8_rows<6, 2, Signed, false>(j, m, quads, o, zeros);
        case 3: return int8_rows<6, 3, Signed, false>(j, m, quads, o, zeros);
    }
}

// Quantized output: all n = 16 NV columns of a row in one block (3 x 8 blocks for the
// default 128-wide layers), so each row's maximum is at hand in the epilogue.
template <bool Signed>
LSNIF_VNNI_TARGET void gemm_int8_vnni_quantized(std::size_t m, const Int8Operands& o, std::size_t n,
                                                std::size_t quads, const ZeroColumns* zeros) {
    switch (n / 16) {
        case 1: return int8_rows<6, 1, Signed, true>(0, m, quads, o, zeros);
        case 2: return int8_rows<6, 2, Signed, true>(0, m, quads, o, zeros);
        case 3: return int8_rows<6, 3, Signed, true>(0, m, quads, o, zeros);
        case 4: return int8_rows<6, 4, Signed, true>(0, m, quads, o, zeros);
        case 5: return int8_rows<4, 5, Signed, true>(0, m, quads, o, zeros);
        case 6: return int8_rows<4, 6, Signed, true>(0, m, quads, o, zeros);
        case 7: return int8_rows<2, 7, Signed, true>(0, m, quads, o, zeros);
        case 8: return int8_rows<2, 8, Signed, true>(0, m, quads, o, zeros);
    }
}

// ---- rows in vector lanes (mlp_int8_in_lanes) ----

// acc += VPDPBUSD(u, broadcast dword at s4): the weights of one column as an embedded
// broadcast operand ({1to16}), so no register holds them.
LSNIF_VNNI_TARGET inline __m512i dpbusd_broadcast(__m512i acc, __m512i u, const std::uint8_t* s4) {
    __asm__("vpdpbusd %2%{1to16%}, %1, %0"
            : "+v"(acc)
            : "v"(u), "m"(*reinterpret_cast<const std::int32_t*>(s4)));
    return acc;
}

// The activations of one block of 16 rows, lanes = rows: quad p of a layer's input at a[p]
// (four bytes of each row per dword), the rows' scales, and one layer's outputs y[j].
struct LanesBlock {
    __m512i* a;
    __m512 sx;
    __m512* y;
};

// Four columns of 16 rows (one int32 lane per row) as one dword per row holding column i in
// byte i, the quads' layout, each value saturated to a signed byte (`signed_bytes`) or an
// unsigned one. The packs narrow by 128-bit lanes (four rows each) and one byte shuffle per
// lane then gathers each row's four bytes: four instructions for four columns.
LSNIF_VNNI_TARGET inline __m512i pack_quad(__m512i q0, __m512i q1, __m512i q2, __m512i q3,
                                           bool signed_bytes) {
    const __m512i words01 = _mm512_packs_epi32(q0, q1), words23 = _mm512_packs_epi32(q2, q3);
    const __m512i bytes =
        signed_bytes ? _mm512_packs_epi16(words01, words23) : _mm512_packus_epi16(words01, words23);
    // Per lane: byte 4 * column + row -> byte 4 * row + column.
    const __m512i rows_together =
        _mm512_broadcast_i32x4(_mm_setr_epi8(0, 4, 8, 12, 1, 5, 9, 13, 2, 6, 10, 14, 3, 7, 11, 15));
    return _mm512_shuffle_epi8(bytes, rows_together);
}

// Whether a lane of 16 inverse scales is +inf (scale_for's hi / m overflowed: a maximum
// below hi / FLT_MAX), where quantizing needs its clamp.
LSNIF_AVX512_TARGET inline bool any_infinite(__m512 inverse) {
    const __m512 inf = _mm512_set1_ps(std::numeric_limits<float>::infinity());
    return _mm512_cmp_ps_mask(inverse, inf, _CMP_EQ_OQ) != 0;
}

// Rows [r0, r0 + rows) of the first layer's fp32 input (`cols` columns, row stride lda;
// rows <= 16, the others read as zero) quantized straight into lanes, with the bytes and
// scales quantize_rows_avx512 gives them: the live 16-column chunks transposed into blk.y
// (column j at y[j]) while the rows' maxima gather vertically (VMAXPS keeps the running
// maximum against NaN, as there), 16 rows' scales by one division, then per live quad four
// columns' x * inverse (NaN -> 0, clamped, rounded to nearest even) packed into a dword.
// Columns outside quads [0, head) and [tail, end) are zero in these rows and change no
// maximum. Signed rows get their bytes' top bit flipped (q + 128, unsigned), which the
// first layer takes back through its weights' quad sums.
LSNIF_VNNI_TARGET void quantize_to_lanes(const float* x, std::size_t lda, std::size_t cols, std::size_t r0,
                                         std::size_t rows, LiveGroups live, bool signed_input,
                                         LanesBlock& blk) {
    const QuantRange range = signed_input ? kSigned : kUnsigned;
    const __m512i abs_mask = _mm512_set1_epi32(signed_input ? 0x7fffffff : -1);
    const std::size_t dead_begin = 4 * live.head, dead_end = 4 * live.tail,
                      end = std::min(4 * live.end, cols);
    __m512 m = _mm512_setzero_ps();
    for (std::size_t c0 = 0; c0 < end; c0 += 16) {
        if (c0 >= dead_begin && c0 + 16 <= dead_end) continue;  // all of it zero
        const __mmask16 live_cols = lane_mask16(c0, cols);
        __m512i t[16];
        for (std::size_t i = 0; i < 16; ++i)
            t[i] = i < rows ? _mm512_castps_si512(_mm512_maskz_loadu_ps(live_cols, x + (r0 + i) * lda + c0))
                            : _mm512_setzero_si512();
        detail::transpose16(t);
        for (std::size_t j = 0; j < 16; ++j) {
            m = _mm512_max_ps(_mm512_castsi512_ps(_mm512_and_si512(t[j], abs_mask)), m);
            blk.y[c0 + j] = _mm512_castsi512_ps(t[j]);
        }
    }
    const __m512 hi = _mm512_set1_ps(range.hi), lo = _mm512_set1_ps(range.lo);
    const Scales16 scales = scales16(m, hi);
    blk.sx = scales.scale;
    const __m512 inverse = scales.inverse;
    const __m512i top = _mm512_set1_epi32(signed_input ? std::int32_t(0x80808080u) : 0);
    const bool clamp = any_infinite(inverse);
    const auto quad = [&](std::size_t p) LSNIF_VNNI_TARGET {
        const __m512* y = blk.y + 4 * p;
        // With finite inverses, |x| <= m bounds x * inverse to hi after rounding (a finite x
        // cannot make NaN), and an unsigned input's negative x converts to <= 0: the packs'
        // saturation is the clamp.
        const auto q = [&](int i) LSNIF_VNNI_TARGET {
            return clamp ? quantize16(y[i], inverse, lo, hi)
                         : _mm512_cvtps_epi32(_mm512_mul_ps(y[i], inverse));
        };
        blk.a[p] = _mm512_xor_si512(pack_quad(q(0), q(1), q(2), q(3), signed_input), top);
    };
    for (std::size_t p = 0; p < live.head; ++p) quad(p);
    for (std::size_t p = live.tail; p < live.end; ++p) quad(p);
}

// The integer sums of the N <= 16 columns [j0, j0 + N) of one int8 hidden layer on a block,
// visiting quads [0, head) and [tail, end) in one loop (two loops, or a lambda per quad, make
// GCC keep the accumulators on the stack). Signed: the inputs arrive as q + 128, so each
// column's sum starts at -128 times its weights' sum over the visited quads; the result is
// the same sum of q * w.
template <bool Signed, std::size_t N = 16>
[[gnu::always_inline]] LSNIF_VNNI_TARGET inline void lanes_sums(const Int8Layer& w, LiveGroups live,
                                                                const LanesBlock& blk, std::size_t j0,
                                                                __m512i (&acc)[16]) {
    static_assert(N >= 1 && N <= 16);
    const std::size_t np = w.out_padded, ldb = 4 * np;
    const std::uint8_t* b = Signed ? w.w_signed.data() : w.b.data();
    if constexpr (Signed) {
        // The 16 columns' weight sums over the visited quads at once (j0 + 16 <= np).
        const std::int32_t* s = w.quad_prefix.data() + j0;
        const __m512i visited = _mm512_sub_epi32(
            _mm512_add_epi32(_mm512_loadu_si512(s + live.head * np), _mm512_loadu_si512(s + live.end * np)),
            _mm512_loadu_si512(s + live.tail * np));
        alignas(64) std::int32_t start[16];
        _mm512_store_si512(start, _mm512_mullo_epi32(visited, _mm512_set1_epi32(-128)));
#pragma GCC unroll 16
        for (std::size_t j = 0; j < N; ++j) acc[j] = _mm512_set1_epi32(start[j]);
    } else {
#pragma GCC unroll 16
        for (std::size_t j = 0; j < N; ++j) acc[j] = _mm512_setzero_si512();
    }
    // Pointers stepped through A and B, not a quad index: the VPDPBUSDs address their
    // weights by base and offset, without an index register, and the loop's own work is two
    // additions and the exit test, which leaves the issue slots to the products.
    const std::size_t skip = live.tail - live.head;
    const __m512i* ap = blk.a;
    const __m512i* const a_head = blk.a + live.head;
    const __m512i* const a_end = blk.a + live.end;
    const std::uint8_t* bp = b + 4 * j0;
    for (; ap != a_end; ++ap, bp += ldb) {
        if (ap == a_head) {  // jump over the quads [head, tail)
            ap += skip;
            bp += skip * ldb;
            if (ap == a_end) break;
        }
        const __m512i a = *ap;
#pragma GCC unroll 16
        for (std::size_t j = 0; j < N; ++j) acc[j] = dpbusd_broadcast(acc[j], a, bp + 4 * j);
    }
}

// Column j's value for the block's rows before the ReLU: sx * sw[j] * sum + bias[j].
[[gnu::always_inline]] LSNIF_VNNI_TARGET inline __m512 lanes_value(const Int8Layer& w, const float* bias,
                                                                   const LanesBlock& blk, std::size_t j,
                                                                   __m512i sum) {
    return _mm512_fmadd_ps(_mm512_cvtepi32_ps(sum), _mm512_mul_ps(blk.sx, _mm512_set1_ps(w.scale[j])),
                           _mm512_set1_ps(bias[j]));
}

// A hidden layer before the last on a block: its outputs into blk.y for lanes_quantize;
// returns the rows' maxima (VMAXPS from +0, as quantize_row: those of the ReLU'd outputs).
template <bool Signed>
LSNIF_VNNI_TARGET __m512 lanes_hidden(const Int8Layer& w, const float* bias, LiveGroups live,
                                      LanesBlock& blk) {
    __m512 m = _mm512_setzero_ps();
    for (std::size_t j0 = 0; j0 < w.out_padded; j0 += 16) {
        __m512i acc[16];
        lanes_sums<Signed>(w, live, blk, j0, acc);
#pragma GCC unroll 16
        for (std::size_t j = 0; j < 16; ++j) {
            const __m512 y = lanes_value(w, bias, blk, j0 + j, acc[j]);
            m = _mm512_max_ps(y, m);
            blk.y[j0 + j] = y;
        }
    }
    return m;
}

// Columns [j0, j0 + N) of the last hidden layer into the output layer's sums `o` (N <= 16,
// j0 + N <= out_padded): their products, ReLU and FMAs, in column order.
template <bool Signed, int OUTS, std::size_t N>
[[gnu::always_inline]] LSNIF_VNNI_TARGET inline void lanes_last_columns(const Int8Layer& w, const float* bias,
                                                                        LiveGroups live,
                                                                        const LanesBlock& blk,
                                                                        const Int8OutputLayer& out,
                                                                        std::size_t j0, __m512 (&o)[OUTS]) {
    __m512i acc[16];
    lanes_sums<Signed, N>(w, live, blk, j0, acc);
#pragma GCC unroll 16
    for (std::size_t j = 0; j < N; ++j) {
        __m512 y = lanes_value(w, bias, blk, j0 + j, acc[j]);
        y = _mm512_maskz_mov_ps(_mm512_cmp_ps_mask(y, _mm512_setzero_ps(), _CMP_GT_OQ), y);
        if (j0 + j < out.in)  // a column of the rounded-up group past the live ones adds nothing
            for (int i = 0; i < OUTS; ++i)
                o[i] = _mm512_fmadd_ps(y, _mm512_set1_ps(out.wt[(j0 + j) * 16 + i]), o[i]);
    }
}

// The last hidden layer on a block with the output layer fused into its epilogue: each
// ReLU'd output goes straight into the output layer's FMAs (per row and output the bias, then
// one FMA per input in order, as dense_output_avx512), whose dependency chains then overlap
// the next column block's products. Writes rows [0, rows) of `c`, 16 columns each (those
// from OUTS on 0). The padding columns past out.in (zero weights and bias, and no output-layer weight) are
// not computed: the last column group runs on its live columns, rounded up to a multiple of
// 4 (the code for 4, 8, 12 or 16 columns), up to 7 of 16 columns' products saved per
// quad.
template <bool Signed, int OUTS>
LSNIF_VNNI_TARGET void lanes_last(const Int8Layer& w, const float* bias, LiveGroups live,
                                  const LanesBlock& blk, const Int8OutputLayer& out, std::size_t rows,
                                  float* c) {
    __m512 o[OUTS];
    for (int i = 0; i < OUTS; ++i) o[i] = _mm512_set1_ps(out.bias[i]);
    const std::size_t live_end = std::min(out.in, w.out_padded);
    std::size_t j0 = 0;
    for (; j0 + 16 <= live_end; j0 += 16)
        lanes_last_columns<Signed, OUTS, 16>(w, bias, live, blk, out, j0, o);
    switch ((live_end - j0 + 3) / 4) {
        case 1: lanes_last_columns<Signed, OUTS, 4>(w, bias, live, blk, out, j0, o); break;
        case 2: lanes_last_columns<Signed, OUTS, 8>(w, bias, live, blk, out, j0, o); break;
        case 3: lanes_last_columns<Signed, OUTS, 12>(w, bias, live, blk, out, j0, o); break;
        case 4: lanes_last_columns<Signed, OUTS, 16>(w, bias, live, blk, out, j0, o); break;
        default: break;  // no columns left
    }
    __m512i t[16];
    for (int i = 0; i < 16; ++i) t[i] = i < OUTS ? _mm512_castps_si512(o[i]) : _mm512_setzero_si512();
    detail::transpose16(t);
    for (std::size_t i = 0; i < rows; ++i) _mm512_storeu_si512(c + i * 16, t[i]);
}

// The block's np outputs before the ReLU, quantized as the next layer's unsigned input (the
// same bytes as quantize_row: scale m / 255 and inverse 255 / m by correctly rounded vector
// division, max(y * inverse, +0), conversion, unsigned saturation to 255), four columns per
// dword into blk.a; the new scales into blk.sx. With finite inverses, y <= m bounds
// y * inverse to 255 after rounding, so the conversion alone gives that byte for every y >= 0,
// and every y < 0 converts to <= 0, which the unsigned pack saturates to the ReLU's 0.
LSNIF_VNNI_TARGET void lanes_quantize(std::size_t np, __m512 m, LanesBlock& blk) {
    const Scales16 scales = scales16(m, _mm512_set1_ps(kUnsigned.hi));
    blk.sx = scales.scale;
    const __m512 inverse = scales.inverse;
    const bool clamp = any_infinite(inverse);
    const __m512i byte_max = _mm512_set1_epi32(255);
    const auto q = [&](std::size_t j) LSNIF_VNNI_TARGET {
        const __m512 t = _mm512_mul_ps(blk.y[j], inverse);
        return clamp ? _mm512_min_epu32(_mm512_cvtps_epi32(_mm512_max_ps(t, _mm512_setzero_ps())), byte_max)
                     : _mm512_cvtps_epi32(t);
    };
    for (std::size_t p = 0; p < np / 4; ++p)
        blk.a[p] = pack_quad(q(4 * p), q(4 * p + 1), q(4 * p + 2), q(4 * p + 3), false);
}

// mlp_int8_in_lanes for an output layer of OUTS columns, with the block's buffers (64-byte
// aligned, sized by the caller): `a` for the quads, `y` for the outputs, 16 lanes each.
template <int OUTS>
LSNIF_VNNI_TARGET void lanes_network(std::size_t m, const float* x, std::size_t lda, const Int8Layer* hidden,
                                     const std::vector<float>* hidden_bias, std::size_t hidden_count,
                                     const Int8OutputLayer& out, const ZeroColumns* zeros, void* a, void* y,
                                     float* c) {
    LanesBlock blk{static_cast<__m512i*>(a), _mm512_setzero_ps(), static_cast<__m512*>(y)};
    const std::size_t quads0 = (hidden[0].in + 3) / 4;
    for (std::size_t r0 = 0; r0 < m; r0 += 16) {
        const std::size_t rows = std::min<std::size_t>(16, m - r0);
        const LiveGroups live0 = live_groups(zeros, r0, rows, quads0, 4);
        quantize_to_lanes(x, lda, hidden[0].in, r0, rows, live0, hidden[0].signed_input, blk);
        for (std::size_t k = 0; k < hidden_count; ++k) {
            const Int8Layer& w = hidden[k];
            const std::size_t q = (w.in + 3) / 4;
            const LiveGroups live = k == 0 ? live0 : LiveGroups{q, q, q};
            const float* bias = hidden_bias[k].data();
            if (k + 1 < hidden_count) {
                const __m512 maxima = w.signed_input ? lanes_hidden<true>(w, bias, live, blk)
                                                     : lanes_hidden<false>(w, bias, live, blk);
                lanes_quantize(w.out_padded, maxima, blk);
            } else if (w.signed_input) {
                lanes_last<true, OUTS>(w, bias, live, blk, out, rows, c + r0 * 16);
            } else {
                lanes_last<false, OUTS>(w, bias, live, blk, out, rows, c + r0 * 16);
            }
        }
    }
}

using LanesNetwork = void (*)(std::size_t, const float*, std::size_t, const Int8Layer*,
                              const std::vector<float>*, std::size_t, const Int8OutputLayer&,
                              const ZeroColumns*, void*, void*, float*);
LanesNetwork lanes_network_for(std::size_t outs) {
    switch (outs) {
        case 1: return lanes_network<1>;  // the visibility logit alone
        case 5: return lanes_network<5>;  // no materials
        case 6: return lanes_network<6>;
        case 7: return lanes_network<7>;
        case 8: return lanes_network<8>;
    }
    return nullptr;
}

#pragma GCC diagnostic pop

#endif  // LSNIF_HAVE_X86

}  // namespace

Int8Layer make_int8_layer(const float* wt, std::size_t in, std::size_t out_padded, bool signed_input) {
    Int8Layer layer;
    layer.in = in;
    layer.out_padded = out_padded;
    layer.signed_input = signed_input;
    const std::size_t k4 = (in + 3) / 4 * 4;
    const std::uint8_t zero = signed_input ? 128 : 0;  // the stored form of a zero weight
    layer.b.assign(k4 * out_padded, zero);
    layer.scale.assign(out_padded, 0.0f);
    for (std::size_t j = 0; j < out_padded; ++j) {
        float m = 0;
        for (std::size_t k = 0; k < in; ++k) m = std::max(m, std::fabs(wt[k * out_padded + j]));
        const Scale s = scale_for(m, kSigned);
        layer.scale[j] = s.scale;
        for (std::size_t k = 0; k < in; ++k) {
            const std::int32_t q = quantize_value(wt[k * out_padded + j] * s.inverse, kSigned);
            layer.b[(k / 4) * 4 * out_padded + 4 * j + k % 4] = std::uint8_t(signed_input ? q + 128 : q);
        }
    }
    if (signed_input) {
        // XOR 0x80 turns the offset byte q + 128 into q's two's complement byte.
        layer.w_signed.resize(layer.b.size());
        for (std::size_t i = 0; i < layer.b.size(); ++i) layer.w_signed[i] = layer.b[i] ^ 0x80u;
        const std::size_t quads = k4 / 4;
        layer.quad_prefix.assign((quads + 1) * out_padded, 0);
        for (std::size_t p = 0; p < quads; ++p)
            for (std::size_t j = 0; j < out_padded; ++j) {
                std::int32_t sum = 0;
                for (std::size_t h = 0; h < 4; ++h)
                    sum += std::int32_t(layer.b[p * 4 * out_padded + 4 * j + h]) - 128;
                layer.quad_prefix[(p + 1) * out_padded + j] = layer.quad_prefix[p * out_padded + j] + sum;
            }
    }
    return layer;
}

void quantize_rows(const float* src, std::size_t n, std::size_t cols, std::size_t lds, bool signed_input,
                   Int8Rows& out) {
    out.cols = cols;
    out.ld = round_up(cols, 16);
    if (out.q.size() < n * out.ld) out.q.resize(n * out.ld);
    if (out.scale.size() < n) out.scale.resize(n), out.sum.resize(n);
#if LSNIF_HAVE_X86
    if (cpu_features().avx512) return quantize_rows_avx512(src, n, cols, lds, signed_input, out);
#endif
    quantize_rows_scalar(src, n, cols, lds, signed_input, out);
}

#if LSNIF_HAVE_X86
namespace {

Int8Operands operands(const Int8Rows& a, const Int8Layer& layer, const float* bias, bool relu, float* c,
                      std::size_t ldc, Int8Rows* next) {
    return {a.q.data(),
            a.ld,
            a.scale.data(),
            a.sum.data(),
            layer.b.data(),
            4 * layer.out_padded,
            layer.scale.data(),
            bias,
            relu,
            c,
            ldc,
            next};
}

}  // namespace
#endif

void gemm_int8(std::size_t m, const Int8Rows& a, const Int8Layer& layer, const float* bias, bool relu,
               float* c, std::size_t ldc, [[maybe_unused]] const ZeroColumns* zeros) {
#if LSNIF_HAVE_X86
    if (m && cpu_features().avx512_vnni) {
        const Int8Operands o = operands(a, layer, bias, relu, c, ldc, nullptr);
        const std::size_t quads = (layer.in + 3) / 4;
        return layer.signed_input ? gemm_int8_vnni<true>(m, o, layer.out_padded, quads, zeros)
                                  : gemm_int8_vnni<false>(m, o, layer.out_padded, quads, zeros);
    }
#endif
    gemm_int8_scalar(m, a, layer, bias, relu, c, ldc);
}

void gemm_int8_relu_quantized(std::size_t m, const Int8Rows& a, const Int8Layer& layer, const float* bias,
                              Int8Rows& next, std::vector<float>& scratch, const ZeroColumns* zeros) {
    const std::size_t np = layer.out_padded;
    next.cols = np;
    next.ld = round_up(np, 16);
    if (next.q.size() < m * next.ld) next.q.resize(m * next.ld);
    if (next.scale.size() < m) next.scale.resize(m), next.sum.resize(m);
#if LSNIF_HAVE_X86
    if (m && np <= kInt8FusedWidth && cpu_features().avx512_vnni) {
        const Int8Operands o = operands(a, layer, bias, true, nullptr, 0, &next);
        const std::size_t quads = (layer.in + 3) / 4;
        return layer.signed_input ? gemm_int8_vnni_quantized<true>(m, o, np, quads, zeros)
                                  : gemm_int8_vnni_quantized<false>(m, o, np, quads, zeros);
    }
#endif
    if (scratch.size() < m * np) scratch.resize(m * np);
    gemm_int8(m, a, layer, bias, true, scratch.data(), np, zeros);
    quantize_rows(scratch.data(), m, np, np, false, next);
}

bool mlp_int8_in_lanes(std::size_t m, const float* x, std::size_t lda, const Int8Layer* hidden,
                       const std::vector<float>* hidden_bias, std::size_t hidden_count,
                       const Int8OutputLayer& out, const ZeroColumns* zeros, float* c) {
#if LSNIF_HAVE_X86
    const LanesNetwork run = lanes_network_for(out.outs);
    if (!cpu_features().avx512_vnni || hidden_count == 0 || !run) return false;
    std::size_t width = (hidden[0].in + 15) / 16 * 16, quads = width / 4;  // the input's transposed chunks
    for (std::size_t k = 0; k < hidden_count; ++k) {
        quads = std::max(quads, (hidden[k].out_padded + 3) / 4);
        width = std::max(width, hidden[k].out_padded);
    }
    // One block's activations: quads of 16 dwords and outputs of 16 floats, 64-byte aligned.
    struct alignas(64) Lane {
        std::int32_t v[16];
    };
    thread_local std::vector<Lane> a, y;
    if (a.size() < quads) a.resize(quads);
    if (y.size() < width) y.resize(width);
    run(m, x, lda, hidden, hidden_bias, hidden_count, out, zeros, a.data(), y.data(), c);
    return true;
#else
    (void)m, (void)x, (void)lda, (void)hidden, (void)hidden_bias, (void)hidden_count, (void)out, (void)zeros,
        (void)c;
    return false;
#endif
}

}  // namespace lsnif::format
