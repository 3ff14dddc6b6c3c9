// bf16 matrix products for the trainer's MLP (internal to trainer/): Intel AMX tiles, or
// AVX-512 BF16 dot products on machines without AMX.
//
// Layouts (all bf16 values are raw 16-bit patterns, the upper half of an IEEE binary32):
//  * A operand, "rows": A[r][k] at a[r * lda + k]. K is padded with zeros to a multiple of
//    32 (one tile row is 32 bf16 = 64 bytes) and M to a multiple of 16 (a tile has 16 rows),
//    so whole tiles can be loaded without reading past the buffer.
//  * B operand, "VNNI": pairs of consecutive K rows interleaved, B[k][n] at
//    b[(k / 2) * ldb + 2 * n + (k % 2)], K padded to 32 and N to 16 with zeros. This is the
//    layout TDPBF16PS (and VDPBF16PS) reads: each 32-bit element of a B row holds
//    (B[2p][n], B[2p+1][n]).
//  * C: fp32 row-major, C[r][n] at c[r * ldc + n]; only the logical m x n region is read or
//    written (ragged edges go through a 16 x 16 staging tile).
//
// Everything that needs AMX or AVX-512 BF16 is compiled with function-level target
// attributes, so this file builds without -mamx-*; callers must check bf16_backend() !=
// none before calling gemm_bf16 (the packing helpers work everywhere).
#pragma once

#include <cstddef>
#include <cstdint>
#include <cstdlib>
#include <new>
#include <vector>

namespace lsnif::trainer::detail {

using Bf16 = std::uint16_t;

// True when the CPU has AMX-TILE, AMX-BF16 and AVX-512 BF16, the OS enables the tile state
// in XCR0, and (Linux) the process was granted XTILEDATA with arch_prctl. Evaluated once
// (thread-safe static initialization); never faults on machines without AMX.
bool amx_available();

// Which instructions gemm_bf16 uses: AMX tiles where available, else AVX-512 BF16
// (VDPBF16PS, e.g. AMD Zen 4), else none (bf16 training is not offered: resolve_precision
// picks fp32). Evaluated once.
enum class Bf16Backend { none, avx512_bf16, amx };
Bf16Backend bf16_backend();
const char* bf16_backend_name(Bf16Backend b);

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

// C[m x n] = A[m x k] B[k x n] (accumulate == false) or C += A B, fp32 accumulation, on
// bf16_backend().
// Contract: k a multiple of 32; `a` readable for round_up(m, 16) rows of lda >= k elements;
// `b` readable for k / 2 rows of ldb >= 2 * round_up(n, 16) elements; padding entries of A
// and B that fall inside those regions are finite (the packers write zeros). Strides in
// elements. Configures the tiles of the calling thread and releases them on return, so it
// may be called from any thread, including short-lived ones. Meant for machines with a
// bf16 backend; elsewhere it falls back to a (slow) scalar loop.
void gemm_bf16(std::size_t m, std::size_t n, std::size_t k, const Bf16* a, std::size_t lda, const Bf16* b,
               std::size_t ldb, float* c, std::size_t ldc, bool accumulate);

// gemm_bf16 on a given backend (tests compare the two kernels on AMX machines). A backend
// this machine lacks falls back to the scalar loop.
void gemm_bf16_on(Bf16Backend backend, std::size_t m, std::size_t n, std::size_t k, const Bf16* a,
                  std::size_t lda, const Bf16* b, std::size_t ldb, float* c, std::size_t ldc,
                  bool accumulate);

// Cache-line aligned storage for tile operands: a tile row is 64 bytes, so aligned rows
// load from one line instead of two.
template <class T>
struct AlignedAllocator {
    using value_type = T;
    AlignedAllocator() = default;
    template <class U>
    AlignedAllocator(const AlignedAllocator<U>&) {}
    T* allocate(std::size_t n) {
        return static_cast<T*>(::operator new(n * sizeof(T), std::align_val_t(64)));
    }
    void deallocate(T* p, std::size_t) { ::operator delete(p, std::align_val_t(64)); }
    template <class U>
    bool operator==(const AlignedAllocator<U>&) const {
        return true;
    }
};
using Bf16Buffer = std::vector<Bf16, AlignedAllocator<Bf16>>;

}  // namespace lsnif::trainer::detail
