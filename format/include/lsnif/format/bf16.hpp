// bf16 operands for MLP products: fp32 -> bf16 rounding, packing into the layouts the
// bf16 dot-product instructions read, and one product kernel on AVX-512 BF16 (VDPBF16PS).
// Shared by the reader's MLP (forward.cpp, Runtime with MlpArithmetic::bf16) and the
// trainer (which adds an AMX kernel on the same layouts). Internal C++ API, like forward.hpp.
//
// Layouts (all bf16 values are raw 16-bit patterns, the upper half of an IEEE binary32):
//  * A operand, "rows": A[r][k] at a[r * lda + k]. K is padded with zeros to a multiple of
//    32 (one AMX tile row is 32 bf16 = 64 bytes) and, for AMX, M to a multiple of 16 (a tile
//    has 16 rows), so whole tiles can be loaded without reading past the buffer.
//  * B operand, "VNNI": pairs of consecutive K rows interleaved, B[k][n] at
//    b[(k / 2) * ldb + 2 * n + (k % 2)], K padded to 32 and N to 16 with zeros. This is the
//    layout TDPBF16PS (and VDPBF16PS) reads: each 32-bit element of a B row holds
//    (B[2p][n], B[2p+1][n]).
//  * C: fp32 row-major, C[r][n] at c[r * ldc + n]; only the logical m x n region is read or
//    written.
//
// Functions that need AVX-512 BF16 check for it at run time (cpu_features().avx512_bf16);
// without it they take scalar paths with the same results (packers) or the same products
// in another summation order (gemm_bf16_dp).
#pragma once

#include <cstddef>
#include <cstdint>

namespace lsnif::format {

using Bf16 = std::uint16_t;

// fp32 -> bf16, round to nearest even. Matches VCVTNEPS2BF16 exactly, which is what the
// vectorized packers use: NaN stays a (quiet) NaN with its sign, and fp32 subnormals become
// a signed zero (the instruction treats denormal inputs as zero; TDPBF16PS would anyway).
inline Bf16 to_bf16(float x) {
    std::uint32_t u;
    __builtin_memcpy(&u, &x, 4);
    if ((u & 0x7fffffffu) > 0x7f800000u) return Bf16((u >> 16) | 0x40u);  // NaN -> quiet NaN
    if ((u & 0x7f800000u) == 0) return Bf16((u >> 16) & 0x8000u);         // zero / subnormal
    u += 0x7fffu + ((u >> 16) & 1u);
    return Bf16(u >> 16);
}
inline float from_bf16(Bf16 h) {
    const std::uint32_t u = std::uint32_t(h) << 16;
    float x;
    __builtin_memcpy(&x, &u, 4);
    return x;
}

inline constexpr std::size_t round_up(std::size_t n, std::size_t m) {
    return (n + m - 1) / m * m;
}

// Rows layout (A operand): dst[r * ldd + c] = bf16(src[r * lds + c]) for r < rows, c < cols;
// zero for cols <= c < ldd and for rows <= r < rows_pad.
void pack_rows(const float* src, std::size_t rows, std::size_t cols, std::size_t lds, Bf16* dst,
               std::size_t ldd, std::size_t rows_pad);

// Rows layout of the transpose (A operand = src^T): dst[c * ldd + r] = bf16(src[r * lds + c])
// for r < rows, c < cols; zero for rows <= r < ldd and for cols <= c < cols_pad.
void pack_transposed(const float* src, std::size_t rows, std::size_t cols, std::size_t lds, Bf16* dst,
                     std::size_t ldd, std::size_t cols_pad);

// VNNI layout (B operand) of src as a k x n matrix: element (kk, nn) = bf16(src[kk * lds + nn])
// goes to dst[(kk / 2) * ldd + 2 * nn + kk % 2]; zero for k <= kk < k_pad and n <= nn < ldd / 2.
// k_pad must be even.
void pack_vnni(const float* src, std::size_t k, std::size_t n, std::size_t lds, Bf16* dst, std::size_t ldd,
               std::size_t k_pad);

// What happens to each fp32 result of gemm_bf16_dp: start from C (accumulate), else from
// bias[j] (bias non-null, at least round_up(n, 16) readable values), else from zero; then
// max(x, 0) when relu.
struct Epilogue {
    const float* bias = nullptr;
    bool relu = false;
    bool accumulate = false;
};

// Columns of A that hold zeros, which a product may skip: row r of A is zero in columns
// [lead[r], tail) (lead: m values) and, when `rest` is given (m values), from column
// rest_start + rest[r] to the end of the row, padding included (tail <= rest_start). The
// inference input has both: the empty slots' features after a ray's points, and its entry
// offsets after its point count. The kernel skips them per block of rows up to the block's
// largest lead and rest, so callers put rows with alike ones next to each other. Skipping
// changes nothing but the sign of an exactly zero sum (+0 instead of -0): each skipped term
// is a product of zeros with finite weights.
struct ZeroColumns {
    const std::uint32_t* lead;
    std::size_t tail;
    const std::uint32_t* rest = nullptr;
    std::size_t rest_start = 0;
};

// What a product over groups of `width` consecutive columns (pairs for bf16, quads for int8)
// must visit for rows [r, r + rows): groups [0, head) and [tail, end); the others are zero
// in every one of these rows (a group straddling a row's lead, the tail or a row's rest
// stays in). Without `zeros`: every group (head = tail = end = groups).
struct LiveGroups {
    std::size_t head, tail, end;
};
inline LiveGroups live_groups(const ZeroColumns* zeros, std::size_t r, std::size_t rows, std::size_t groups,
                              std::size_t width) {
    if (!zeros) return {groups, groups, groups};
    std::uint32_t lead = 0, rest = 0;
    for (std::size_t i = r; i < r + rows; ++i) {
        lead = lead > zeros->lead[i] ? lead : zeros->lead[i];
        if (zeros->rest) rest = rest > zeros->rest[i] ? rest : zeros->rest[i];
    }
    const std::size_t tail = zeros->tail / width < groups ? zeros->tail / width : groups;
    const std::size_t up = (std::size_t(lead) + width - 1) / width;
    const std::size_t head = up < tail ? up : tail;
    std::size_t end = groups;
    if (zeros->rest) {
        const std::size_t live = (zeros->rest_start + rest + width - 1) / width;
        end = live < tail ? tail : live < groups ? live : groups;
    }
    return head == tail ? LiveGroups{end, end, end} : LiveGroups{head, tail, end};
}

// C[m x n] = epilogue(A[m x k] B[k x n]) with fp32 accumulation of bf16 products, A in the
// rows layout, B in the VNNI layout. Contract: k even (packers pad K to 32; k may stop
// short of the padding, which is zero); `a` readable for m rows of lda >= k elements; `b`
// readable for k / 2 rows of ldb >= 2 * round_up(n, 16) elements with finite padding (the
// packers write zeros); `zeros`, if given, true of A (tail <= k). Only the m x n region of
// C is written. Thread-safe (no shared state).
void gemm_bf16_dp(std::size_t m, std::size_t n, std::size_t k, const Bf16* a, std::size_t lda, const Bf16* b,
                  std::size_t ldb, float* c, std::size_t ldc, const Epilogue& e,
                  const ZeroColumns* zeros = nullptr);

}  // namespace lsnif::format
