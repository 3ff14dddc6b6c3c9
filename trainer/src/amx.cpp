#include "amx.hpp"

#include <algorithm>
#include <cstring>

#if defined(__x86_64__) && defined(__GNUC__)
#define LSNIF_HAVE_X86 1
#include <cpuid.h>
#include <immintrin.h>
#endif
#if defined(__linux__)
#include <sys/syscall.h>
#include <unistd.h>
#endif

namespace lsnif::trainer::detail {

namespace {

struct Features {
    bool avx512_bf16 = false;  // AVX-512 F/BW/VL/BF16 usable (CPU and OS)
    bool amx = false;          // AMX-TILE + AMX-BF16 usable and permitted for this process
};

#if LSNIF_HAVE_X86

std::uint64_t read_xcr0() {
    std::uint32_t lo, hi;
    __asm__ volatile("xgetbv" : "=a"(lo), "=d"(hi) : "c"(0));
    return (std::uint64_t(hi) << 32) | lo;
}

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

Features detect() {
    Features f;
    unsigned a, b, c, d;
    if (!__get_cpuid(1, &a, &b, &c, &d) || !(c & (1u << 27))) return f;  // OSXSAVE: xgetbv allowed
    const std::uint64_t xcr0 = read_xcr0();
    constexpr std::uint64_t kZmmState = (1u << 1) | (1u << 2) | (1u << 5) | (1u << 6) | (1u << 7);
    constexpr std::uint64_t kTileState = (1u << 17) | (1u << 18);
    if ((xcr0 & kZmmState) != kZmmState) return f;
    if (!__get_cpuid_count(7, 0, &a, &b, &c, &d)) return f;
    const bool avx512 = (b & (1u << 16)) && (b & (1u << 30)) && (b & (1u << 31));  // F, BW, VL
    const bool amx_bf16 = d & (1u << 22), amx_tile = d & (1u << 24);
    const unsigned max_subleaf = a;
    bool bf16 = false;
    if (max_subleaf >= 1 && __get_cpuid_count(7, 1, &a, &b, &c, &d)) bf16 = a & (1u << 5);
    f.avx512_bf16 = avx512 && bf16;
    f.amx = f.avx512_bf16 && amx_bf16 && amx_tile && (xcr0 & kTileState) == kTileState &&
            request_tile_permission();
    return f;
}

#else

Features detect() {
    return {};
}

#endif

const Features& features() {
    static const Features f = detect();  // thread-safe one-time initialization
    return f;
}

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
#define LSNIF_AMX_TARGET __attribute__((target("amx-tile,amx-bf16,avx512f,avx512bw,avx512vl,avx512bf16")))

// ---- AVX-512 BF16 packers: VCVTNEPS2BF16 rounds exactly like to_bf16 --------------------

LSNIF_BF16_TARGET inline __mmask16 lane_mask16(std::size_t begin, std::size_t end) {
    return begin >= end        ? __mmask16(0)
           : end - begin >= 16 ? __mmask16(0xffff)
                               : __mmask16((1u << (end - begin)) - 1u);
}

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

// In-register transpose of a 16 x 16 matrix of dwords (rows r[0..15] -> columns).
// GCC 12's unpack/shuffle intrinsics pass a self-initialized _mm512_undefined_epi32() as the
// (unused) merge source, which -Wmaybe-uninitialized reports once inlined; a false positive.
#pragma GCC diagnostic push
#pragma GCC diagnostic ignored "-Wmaybe-uninitialized"
LSNIF_BF16_TARGET inline void transpose16(__m512i r[16]) {
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
#pragma GCC diagnostic pop

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
            transpose16(d);
            for (std::size_t j = 0; j < 16; ++j) _mm512_storeu_si512(dst + (c0 + j) * ldd + r0, d[j]);
        }
}

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
// explicit if-constexpr branches.
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

// ---- AVX-512 BF16 GEMM (machines without AMX) ------------------------------------------

// One block of MB rows x NV 16-column vectors of C. VDPBF16PS multiplies a broadcast dword
// of A (the bf16 pair A[r][2p], A[r][2p+1]) with B's VNNI row p (16 such pairs) and adds
// both products to each fp32 lane: the VNNI layout the AMX path uses serves here unchanged.
// With MB = 6, NV = 4: 24 accumulators, 4 B vectors and one broadcast in 29 of 32 registers.
template <int MB, int NV>
LSNIF_BF16_TARGET void dp_block(std::size_t r0, std::size_t j0, std::size_t n, std::size_t pairs,
                                const Bf16* a, std::size_t lda, const Bf16* b, std::size_t ldb, float* c,
                                std::size_t ldc, bool accumulate) {
    __m512 acc[MB][NV];
    __mmask16 mask[NV];
    for (int v = 0; v < NV; ++v) mask[v] = lane_mask16(j0 + 16 * v, n);
    for (int m = 0; m < MB; ++m)
        for (int v = 0; v < NV; ++v)
            acc[m][v] = accumulate ? _mm512_maskz_loadu_ps(mask[v], c + (r0 + m) * ldc + j0 + 16 * v)
                                   : _mm512_setzero_ps();
    const Bf16* arow = a + r0 * lda;
    const Bf16* bcol = b + 2 * j0;
    for (std::size_t p = 0; p < pairs; ++p) {
        __m512bh bv[NV];
        for (int v = 0; v < NV; ++v) bv[v] = (__m512bh)_mm512_loadu_si512(bcol + p * ldb + 32 * v);
        for (int m = 0; m < MB; ++m) {
            std::int32_t pair;
            std::memcpy(&pair, arow + m * lda + 2 * p, sizeof pair);
            const __m512bh av = (__m512bh)_mm512_set1_epi32(pair);
            for (int v = 0; v < NV; ++v) acc[m][v] = _mm512_dpbf16_ps(acc[m][v], av, bv[v]);
        }
    }
    for (int m = 0; m < MB; ++m)
        for (int v = 0; v < NV; ++v)
            _mm512_mask_storeu_ps(c + (r0 + m) * ldc + j0 + 16 * v, mask[v], acc[m][v]);
}

template <int NV>
LSNIF_BF16_TARGET void dp_columns(std::size_t j0, std::size_t m, std::size_t n, std::size_t pairs,
                                  const Bf16* a, std::size_t lda, const Bf16* b, std::size_t ldb, float* c,
                                  std::size_t ldc, bool accumulate) {
    constexpr std::size_t MB = 6;
    std::size_t r = 0;
    for (; r + MB <= m; r += MB) dp_block<MB, NV>(r, j0, n, pairs, a, lda, b, ldb, c, ldc, accumulate);
    for (; r < m; ++r) dp_block<1, NV>(r, j0, n, pairs, a, lda, b, ldb, c, ldc, accumulate);
}

// Same contract as gemm_amx (A rows, B VNNI, K a multiple of 32), but only the logical m rows
// of A and round_up(n, 16) columns of B are read.
LSNIF_BF16_TARGET void gemm_avx512bf16(std::size_t m, std::size_t n, std::size_t k, const Bf16* a,
                                       std::size_t lda, const Bf16* b, std::size_t ldb, float* c,
                                       std::size_t ldc, bool accumulate) {
    const std::size_t pairs = k / 2;
    std::size_t j = 0;
    for (; j + 64 <= n; j += 64) dp_columns<4>(j, m, n, pairs, a, lda, b, ldb, c, ldc, accumulate);
    for (; j < n; j += 16) dp_columns<1>(j, m, n, pairs, a, lda, b, ldb, c, ldc, accumulate);
}

#endif  // LSNIF_HAVE_X86

}  // namespace

Bf16Backend bf16_backend() {
    if (features().amx) return Bf16Backend::amx;
    if (features().avx512_bf16) return Bf16Backend::avx512_bf16;
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
    return features().amx;
}

void pack_rows(const float* src, std::size_t rows, std::size_t cols, std::size_t lds, Bf16* dst,
               std::size_t ldd, std::size_t rows_pad) {
#if LSNIF_HAVE_X86
    if (features().avx512_bf16) return pack_rows_avx512(src, rows, cols, lds, dst, ldd, rows_pad);
#endif
    pack_rows_scalar(src, rows, cols, lds, dst, ldd, rows_pad);
}

void pack_transposed(const float* src, std::size_t rows, std::size_t cols, std::size_t lds, Bf16* dst,
                     std::size_t ldd, std::size_t cols_pad) {
#if LSNIF_HAVE_X86
    if (features().avx512_bf16 && ldd % 32 == 0 && cols_pad % 16 == 0)
        return pack_transposed_avx512(src, rows, cols, lds, dst, ldd, cols_pad);
#endif
    pack_transposed_scalar(src, rows, cols, lds, dst, ldd, cols_pad);
}

void pack_vnni(const float* src, std::size_t k, std::size_t n, std::size_t lds, Bf16* dst, std::size_t ldd,
               std::size_t k_pad) {
#if LSNIF_HAVE_X86
    if (features().avx512_bf16 && ldd % 2 == 0) return pack_vnni_avx512(src, k, n, lds, dst, ldd, k_pad);
#endif
    pack_vnni_scalar(src, k, n, lds, dst, ldd, k_pad);
}

void gemm_bf16(std::size_t m, std::size_t n, std::size_t k, const Bf16* a, std::size_t lda, const Bf16* b,
               std::size_t ldb, float* c, std::size_t ldc, bool accumulate) {
    gemm_bf16_on(bf16_backend(), m, n, k, a, lda, b, ldb, c, ldc, accumulate);
}

void gemm_bf16_on(Bf16Backend backend, std::size_t m, std::size_t n, std::size_t k, const Bf16* a,
                  std::size_t lda, const Bf16* b, std::size_t ldb, float* c, std::size_t ldc,
                  bool accumulate) {
#if LSNIF_HAVE_X86
    if (m && n && backend == Bf16Backend::amx && features().amx)
        return gemm_amx(m, n, k, a, lda, b, ldb, c, ldc, accumulate);
    if (m && n && backend == Bf16Backend::avx512_bf16 && features().avx512_bf16)
        return gemm_avx512bf16(m, n, k, a, lda, b, ldb, c, ldc, accumulate);
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
