// bf16 matrix products for the trainer's MLP (internal to trainer/): Intel AMX tiles, or
// AVX-512 BF16 dot products on machines without AMX.
//
// Operand layouts and packers: lsnif/format/bf16.hpp (shared with the reader's bf16 MLP).
//
// Everything that needs AMX or AVX-512 BF16 is compiled with function-level target
// attributes, so this file builds without -mamx-*; callers must check bf16_backend() !=
// none before calling gemm_bf16 (the packing helpers work everywhere).
#pragma once

#include <lsnif/format/bf16.hpp>

#include <cstddef>
#include <cstdint>
#include <cstdlib>
#include <new>
#include <vector>

namespace lsnif::trainer::detail {

using format::Bf16;
using format::from_bf16;
using format::pack_rows;
using format::pack_transposed;
using format::pack_vnni;
using format::round_up;
using format::to_bf16;

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
