#include "amx.hpp"

#include <lsnif/format/cpu.hpp>

#include <algorithm>
#include <cstring>

#if defined(__x86_64__) && defined(__GNUC__)
#define LSNIF_HAVE_X86 1
#include <immintrin.h>
#endif
#if defined(__linux__)
#include <sys/syscall.h>
#include <unistd.h>
#endif

namespace lsnif::trainer::detail {

namespace {

#if LSNIF_HAVE_X86

// Asks Linux for the AMX tile data state. Without it the first tile instruction raises
// SIGILL (the kernel arms XFD for XTILEDATA until a process opts in).
bool request_tile_permission() {
#if defined(__linux__) && defined(SYS_arch_prctl)
    constexpr int kArchGetXcompPerm = 0x1022, kArchReqXcompPerm = 0x1023;
    constexpr unsigned long kXfeatureXtiledata = 18;
    if (syscall(SYS_arch_prctl, kArchReqXcompPerm, kXfeatureXtiledata) != 0) return false;
    unsigned long granted = 0;
    if (syscall(SYS_arch_prctl, kArchGetXcompPerm, &granted) != 0) return false;
    return (granted >> kXfeatureXtiledata) & 1u;
#else
    return false;  // no known way to obtain the permission: stay on the fp32 path
#endif
}

// AMX-TILE + AMX-BF16 usable and permitted for this process (AVX-512 BF16 is required too).
bool detect_amx() {
    return format::cpu_features().amx_bf16 && request_tile_permission();
}

#else

bool detect_amx() {
    return false;
}

#endif

bool has_amx() {
    static const bool yes = detect_amx();  // thread-safe one-time initialization
    return yes;
}

#if LSNIF_HAVE_X86

#define LSNIF_AMX_TARGET __attribute__((target("amx-tile,amx-bf16,avx512f,avx512bw,avx512vl,avx512bf16")))

// ---- AMX GEMM ---------------------------------------------------------------------------

// Palette 1, all eight tiles 16 rows x 64 bytes: A tiles 16 x 32 bf16, B tiles 16 pair-rows
// x 16 columns, C tiles 16 x 16 fp32. Constant data, so no store to it can be elided
// (GCC 12's _tile_loadconfig asm only declares the first 8 bytes as read).
struct alignas(64) TileConfig {
    std::uint8_t palette_id;
    std::uint8_t start_row;
    std::uint8_t reserved[14];
    std::uint16_t colsb[16];
    std::uint8_t rows[16];
};
constexpr TileConfig make_tile_config() {
    TileConfig t{};
    t.palette_id = 1;
    for (int i = 0; i < 8; ++i) t.colsb[i] = 64, t.rows[i] = 16;
    return t;
}
constexpr TileConfig kTileConfig = make_tile_config();

// GCC 12's tile intrinsics are asm statements without memory operands: the compiler does
// not know that tileloadd reads and tilestored writes memory. A barrier around them keeps
// ordinary loads and stores of the same buffers in program order.
inline void compiler_barrier() {
    __asm__ volatile("" ::: "memory");
}

// One block of MT x NT C tiles (MT, NT in {1, 2}) at rows i0, columns j0. Tiles 0..3 hold
// C (0: (0,0), 1: (0,1), 2: (1,0), 3: (1,1)), 4..5 the A row tiles, 6..7 the B column tiles.
// Tile indices must be literals (GCC's macros paste them into the asm text), hence the
// explicit if-constexpr branches. Over 80 lines on purpose: C lives in tile registers from
// its load through the k loop to its store, and no call preserves them (GCC does not
// track tile registers), so load, loop and store stay in one function.
template <int MT, int NT>
LSNIF_AMX_TARGET void gemm_block(std::size_t i0, std::size_t j0, std::size_t m, std::size_t n, std::size_t k,
                                 const Bf16* a, std::size_t lda, const Bf16* b, std::size_t ldb, float* c,
                                 std::size_t ldc, bool accumulate) {
    alignas(64) float stage[16 * 16];
    const long sa = long(lda * sizeof(Bf16)), sb = long(ldb * sizeof(Bf16)), sc = long(ldc * sizeof(float));
    auto full = [&](int ti, int tj) { return i0 + 16 * ti + 16 <= m && j0 + 16 * tj + 16 <= n; };
    auto cptr = [&](int ti, int tj) { return c + (i0 + 16 * ti) * ldc + j0 + 16 * tj; };
    // Copies the valid part of a ragged C tile into `stage` (zeros elsewhere), and back.
    auto stage_in = [&](int ti, int tj) {
        std::memset(stage, 0, sizeof stage);
        const std::size_t rr = std::min<std::size_t>(16, m - (i0 + 16 * ti)),
                          cc = std::min<std::size_t>(16, n - (j0 + 16 * tj));
        for (std::size_t r = 0; r < rr; ++r)
            std::memcpy(stage + r * 16, cptr(ti, tj) + r * ldc, cc * sizeof(float));
        compiler_barrier();
    };
    auto stage_out = [&](int ti, int tj) {
        compiler_barrier();
        const std::size_t rr = std::min<std::size_t>(16, m - (i0 + 16 * ti)),
                          cc = std::min<std::size_t>(16, n - (j0 + 16 * tj));
        for (std::size_t r = 0; r < rr; ++r)
            std::memcpy(cptr(ti, tj) + r * ldc, stage + r * 16, cc * sizeof(float));
    };
#define LSNIF_LOAD_C(T, TI, TJ)           \
    if (!accumulate) {                    \
        _tile_zero(T);                    \
    } else if (full(TI, TJ)) {            \
        _tile_loadd(T, cptr(TI, TJ), sc); \
    } else {                              \
        stage_in(TI, TJ);                 \
        _tile_loadd(T, stage, 64);        \
    }
#define LSNIF_STORE_C(T, TI, TJ)           \
    if (full(TI, TJ)) {                    \
        _tile_stored(T, cptr(TI, TJ), sc); \
    } else {                               \
        _tile_stored(T, stage, 64);        \
        stage_out(TI, TJ);                 \
    }
    LSNIF_LOAD_C(0, 0, 0)
    if constexpr (NT == 2) {
        LSNIF_LOAD_C(1, 0, 1)
    }
    if constexpr (MT == 2) {
        LSNIF_LOAD_C(2, 1, 0)
    }
    if constexpr (MT == 2 && NT == 2) {
        LSNIF_LOAD_C(3, 1, 1)
    }
    const Bf16* a0 = a + i0 * lda;
    const Bf16* b0 = b + 2 * j0;
    for (std::size_t kk = 0; kk < k; kk += 32) {
        const Bf16* ak = a0 + kk;
        const Bf16* bk = b0 + (kk / 2) * ldb;
        _tile_loadd(4, ak, sa);
        _tile_loadd(6, bk, sb);
        if constexpr (NT == 2) _tile_loadd(7, bk + 32, sb);
        if constexpr (MT == 2) _tile_loadd(5, ak + 16 * lda, sa);
        _tile_dpbf16ps(0, 4, 6);
        if constexpr (NT == 2) _tile_dpbf16ps(1, 4, 7);
        if constexpr (MT == 2) _tile_dpbf16ps(2, 5, 6);
        if constexpr (MT == 2 && NT == 2) _tile_dpbf16ps(3, 5, 7);
    }
    LSNIF_STORE_C(0, 0, 0)
    if constexpr (NT == 2) {
        LSNIF_STORE_C(1, 0, 1)
    }
    if constexpr (MT == 2) {
        LSNIF_STORE_C(2, 1, 0)
    }
    if constexpr (MT == 2 && NT == 2) {
        LSNIF_STORE_C(3, 1, 1)
    }
#undef LSNIF_LOAD_C
#undef LSNIF_STORE_C
}

LSNIF_AMX_TARGET void gemm_amx(std::size_t m, std::size_t n, std::size_t k, const Bf16* a, std::size_t lda,
                               const Bf16* b, std::size_t ldb, float* c, std::size_t ldc, bool accumulate) {
    // Tile configuration is per thread and cheap next to one product (>= 16 x 16 x 32);
    // releasing afterwards returns the thread to the init state, so context switches do
    // not save 8 KiB of tile data for threads that finished their products.
    _tile_loadconfig(&kTileConfig);
    compiler_barrier();
    const std::size_t mt = (m + 15) / 16, nt = (n + 15) / 16;
    for (std::size_t ti = 0; ti < mt; ti += 2)
        for (std::size_t tj = 0; tj < nt; tj += 2) {
            const bool two_m = ti + 1 < mt, two_n = tj + 1 < nt;
            const std::size_t i0 = 16 * ti, j0 = 16 * tj;
            if (two_m && two_n)
                gemm_block<2, 2>(i0, j0, m, n, k, a, lda, b, ldb, c, ldc, accumulate);
            else if (two_m)
                gemm_block<2, 1>(i0, j0, m, n, k, a, lda, b, ldb, c, ldc, accumulate);
            else if (two_n)
                gemm_block<1, 2>(i0, j0, m, n, k, a, lda, b, ldb, c, ldc, accumulate);
            else
                gemm_block<1, 1>(i0, j0, m, n, k, a, lda, b, ldb, c, ldc, accumulate);
        }
    compiler_barrier();
    _tile_release();
}

#endif  // LSNIF_HAVE_X86

}  // namespace

Bf16Backend bf16_backend() {
    if (has_amx()) return Bf16Backend::amx;
    if (format::cpu_features().avx512_bf16) return Bf16Backend::avx512_bf16;
    return Bf16Backend::none;
}

const char* bf16_backend_name(Bf16Backend b) {
    switch (b) {
        case Bf16Backend::amx: return "amx";
        case Bf16Backend::avx512_bf16: return "avx512-bf16";
        case Bf16Backend::none: return "none";
    }
    return "?";
}

bool amx_available() {
    return has_amx();
}

void gemm_bf16(std::size_t m, std::size_t n, std::size_t k, const Bf16* a, std::size_t lda, const Bf16* b,
               std::size_t ldb, float* c, std::size_t ldc, bool accumulate) {
    gemm_bf16_on(bf16_backend(), m, n, k, a, lda, b, ldb, c, ldc, accumulate);
}

void gemm_bf16_on(Bf16Backend backend, std::size_t m, std::size_t n, std::size_t k, const Bf16* a,
                  std::size_t lda, const Bf16* b, std::size_t ldb, float* c, std::size_t ldc,
                  bool accumulate) {
#if LSNIF_HAVE_X86
    if (m && n && backend == Bf16Backend::amx && has_amx())
        return gemm_amx(m, n, k, a, lda, b, ldb, c, ldc, accumulate);
    if (m && n && backend == Bf16Backend::avx512_bf16 && format::cpu_features().avx512_bf16)
        return format::gemm_bf16_dp(m, n, k, a, lda, b, ldb, c, ldc, {nullptr, false, accumulate});
#endif
    // No bf16 instructions: the same product in plain loops (fp32 accumulation of exact bf16
    // products; summation order differs from the kernels'). Far too slow to train with; it
    // exists so a contract violation degrades to slowness instead of SIGILL.
    for (std::size_t r = 0; r < m; ++r)
        for (std::size_t j = 0; j < n; ++j) {
            float s = accumulate ? c[r * ldc + j] : 0.0f;
            for (std::size_t kk = 0; kk < k; ++kk)
                s += from_bf16(a[r * lda + kk]) * from_bf16(b[(kk / 2) * ldb + 2 * j + kk % 2]);
            c[r * ldc + j] = s;
        }
}

}  // namespace lsnif::trainer::detail
