#include "kernels.hpp"

#include <lsnif/format/cpu.hpp>
#include <lsnif/format/simd.hpp>

#include <algorithm>

namespace lsnif::trainer::detail {

namespace {

// Blocks of IB rows of dWt x NV vectors: the NV gradient vectors of one sample are
// reused across IB inputs, inputs broadcast (same register blocking as format's
// dense_layer, transposed access to X). Every element of dWt adds its rows' products in row
// order, one fused multiply-add each (simd::fma), in every variant: the same bits on every ISA.
// A block of inputs visits the rows up to its largest live_rows (all n without).
#define LSNIF_OUTER_KERNEL(NAME, TARGET, W)                                                          \
    TARGET void NAME(const float* X, std::size_t n, std::size_t in, std::size_t ldx, const float* G, \
                     std::size_t outp, float* dWt, const std::uint32_t* live_rows) {                 \
        using vec = format::simd::Vec<W>;                                                            \
        constexpr std::size_t IB = 6, NV = 4;                                                        \
        for (std::size_t o = 0; o < outp; o += NV * W) {                                             \
            const std::size_t nv = std::min<std::size_t>(NV, (outp - o) / W);                        \
            for (std::size_t i = 0; i < in; i += IB) {                                               \
                const std::size_t ib = std::min(IB, in - i);                                         \
                std::size_t rows = live_rows ? 0 : n;                                                \
                if (live_rows)                                                                       \
                    for (std::size_t m = 0; m < ib; ++m)                                             \
                        rows = std::max<std::size_t>(rows, live_rows[i + m]);                        \
                vec acc[IB][NV];                                                                     \
                for (std::size_t m = 0; m < ib; ++m)                                                 \
                    for (std::size_t v = 0; v < nv; ++v)                                             \
                        acc[m][v] = *reinterpret_cast<const vec*>(dWt + (i + m) * outp + o + v * W); \
                if (ib == IB && nv == NV) {                                                          \
                    for (std::size_t r = 0; r < rows; ++r) {                                         \
                        const float* g = G + r * outp + o;                                           \
                        const vec g0 = *reinterpret_cast<const vec*>(g);                             \
                        const vec g1 = *reinterpret_cast<const vec*>(g + W);                         \
                        const vec g2 = *reinterpret_cast<const vec*>(g + 2 * W);                     \
                        const vec g3 = *reinterpret_cast<const vec*>(g + 3 * W);                     \
                        const float* x = X + r * ldx + i;                                            \
                        for (std::size_t m = 0; m < IB; ++m) {                                       \
                            const float a = x[m];                                                    \
                            acc[m][0] = format::simd::fma(a, g0, acc[m][0]);                         \
                            acc[m][1] = format::simd::fma(a, g1, acc[m][1]);                         \
                            acc[m][2] = format::simd::fma(a, g2, acc[m][2]);                         \
                            acc[m][3] = format::simd::fma(a, g3, acc[m][3]);                         \
                        }                                                                            \
                    }                                                                                \
                } else {                                                                             \
                    for (std::size_t r = 0; r < rows; ++r)                                           \
                        for (std::size_t v = 0; v < nv; ++v) {                                       \
                            const vec g = *reinterpret_cast<const vec*>(G + r * outp + o + v * W);   \
                            for (std::size_t m = 0; m < ib; ++m)                                     \
                                acc[m][v] = format::simd::fma(X[r * ldx + i + m], g, acc[m][v]);     \
                        }                                                                            \
                }                                                                                    \
                for (std::size_t m = 0; m < ib; ++m)                                                 \
                    for (std::size_t v = 0; v < nv; ++v)                                             \
                        *reinterpret_cast<vec*>(dWt + (i + m) * outp + o + v * W) = acc[m][v];       \
            }                                                                                        \
        }                                                                                            \
    }

LSNIF_OUTER_KERNEL(outer_avx512, __attribute__((target("avx512f,avx512vl,avx2,fma"))), 16)
LSNIF_OUTER_KERNEL(outer_avx2, __attribute__((target("avx2,fma"))), 8)
LSNIF_OUTER_KERNEL(outer_generic, , 4)
#undef LSNIF_OUTER_KERNEL

using OuterFn = void (*)(const float*, std::size_t, std::size_t, std::size_t, const float*, std::size_t,
                         float*, const std::uint32_t*);

OuterFn pick() {
    if (format::cpu_features().avx512) return outer_avx512;
    if (format::cpu_features().avx2_fma) return outer_avx2;
    return outer_generic;
}

}  // namespace

void outer_accumulate(const float* X, std::size_t n, std::size_t in, std::size_t ldx, const float* G,
                      std::size_t outp, float* dWt, const std::uint32_t* live_rows) {
    static const OuterFn fn = pick();
    fn(X, n, in, ldx, G, outp, dWt, live_rows);
}

}  // namespace lsnif::trainer::detail
