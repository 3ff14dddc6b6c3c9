// Forward pass; see forward.hpp for the contracts. References: 3D-DDA after Amanatides &
// Woo, "A Fast Voxel Traversal Algorithm for Ray Tracing" (1987); multiresolution hash
// encoding after Müller et al., "Instant Neural Graphics Primitives" (2022); LSNIF after
// Fujieda et al. (I3D 2025).
#include <lsnif/format/cpu.hpp>
#include <lsnif/format/forward.hpp>
#include <lsnif/format/half.hpp>
#include <lsnif/format/quantize.hpp>
#include <lsnif/format/simd.hpp>

#include <algorithm>
#include <bit>
#include <cmath>
#include <cstring>
#include <limits>
#include <type_traits>

#include "heap_bytes.hpp"
#include "x86.hpp"
#if LSNIF_HAVE_X86
#include "avx512_transpose.hpp"
// GCC 12's AVX-512 intrinsics start from _mm*_undefined_*(), which -Wmaybe-uninitialized
// reports as a use of an uninitialized value (a false positive).
#pragma GCC diagnostic ignored "-Wmaybe-uninitialized"
#pragma GCC diagnostic ignored "-Wuninitialized"
#elif defined(__F16C__)
#include <immintrin.h>
#endif

namespace lsnif::format {

namespace {
constexpr float kInf = std::numeric_limits<float>::infinity();
}

Geometry make_geometry(const ModelDesc& d) {
    Geometry g{};
    g.V = d.grid_resolution;
    g.H = d.max_points;
    g.L = d.level_count();
    g.F = d.features_per_level;
    double diag2 = 0;
    for (int a = 0; a < 3; ++a) {
        g.box_min[a] = d.box_min[a];
        g.box_max[a] = d.box_max[a];
        diag2 += (double(d.box_max[a]) - d.box_min[a]) * (double(d.box_max[a]) - d.box_min[a]);
    }
    g.diagonal = float(std::sqrt(diag2));
    g.primes = d.hash_primes;
    for (std::uint32_t l = 0; l < g.L; ++l) {
        LevelInfo lv;
        lv.res = d.level_resolution[l];
        lv.dense = d.level_dense(l);
        lv.stride = lv.res + 1;
        lv.mask = std::uint32_t(d.table_size() - 1);
        lv.scale = float(double(lv.res) / g.V);
        lv.aligned = lv.res % g.V == 0;
        g.levels.push_back(lv);
    }
    g.distance_encoding = d.distance_encoding;
    g.point_width = d.point_feature_width();
    g.direction_width = d.direction_width();
    g.offset_width = d.offset_width();
    for (int a = 0; a < 3; ++a) g.cell[a] = (d.box_max[a] - d.box_min[a]) / float(d.grid_resolution);
    g.input_width = d.input_width();
    g.output_count = d.output_count();
    g.material_count = d.material_count;
    return g;
}

// ---- encoding -------------------------------------------------------------------------

namespace {

void level_corners_scalar(const Geometry& geo, const LevelInfo& lv, const float g[3], Corners& out) {
    std::uint32_t ci[3][2];
    float cw[3][2];
    int cn[3];
    for (int a = 0; a < 3; ++a) {
        const float s = g[a] * lv.scale;
        float fl = std::floor(s);
        if (fl >= float(lv.res)) fl = float(lv.res - 1);  // s == res: last cell, weight on top corner
        if (fl < 0) fl = 0;
        const float f = std::clamp(s - fl, 0.0f, 1.0f);
        const std::uint32_t i0 = std::uint32_t(fl);
        if (f == 0.0f) {
            cn[a] = 1, ci[a][0] = i0, cw[a][0] = 1.0f;
        } else if (f == 1.0f) {
            cn[a] = 1, ci[a][0] = i0 + 1, cw[a][0] = 1.0f;
        } else {
            cn[a] = 2, ci[a][0] = i0, ci[a][1] = i0 + 1, cw[a][0] = 1.0f - f, cw[a][1] = f;
        }
    }
    out.n = 0;
    for (int z = 0; z < cn[2]; ++z)
        for (int y = 0; y < cn[1]; ++y)
            for (int x = 0; x < cn[0]; ++x) {
                const std::uint32_t X = ci[0][x], Y = ci[1][y], Z = ci[2][z];
                const std::uint32_t idx =
                    lv.dense ? X + lv.stride * (Y + lv.stride * Z)
                             : ((X * geo.primes[0]) ^ (Y * geo.primes[1]) ^ (Z * geo.primes[2])) & lv.mask;
                out.index[out.n] = idx;
                out.weight[out.n] = cw[0][x] * cw[1][y] * cw[2][z];
                ++out.n;
            }
}

#if LSNIF_HAVE_X86

// level_corners_scalar with the three axes in one SSE vector and the eight corners in one
// AVX vector, compressed to the corners that carry weight. Same IEEE operations in the
// same order (the weight is (w_x * w_y) * w_z), so bit-identical results: std::max(v, lo)
// is MAXPS(lo, v) and std::min(v, hi) is MINPS(hi, v). A zero-weight corner is one whose
// axis factor is 0 (f == 0 drops the upper corner, f == 1 the lower one); a product of
// non-zero factors cannot underflow, each being at least 2^-24.
__attribute__((target("avx512f,avx512vl,avx512bw,avx512dq,fma"))) void level_corners_avx512(
    const Geometry& geo, const LevelInfo& lv, const float g[3], Corners& out) {
    const __m128 s = _mm_mul_ps(_mm_maskz_loadu_ps(0x7, g), _mm_set1_ps(lv.scale));
    __m128 fl = _mm_floor_ps(s);
    fl = _mm_mask_blend_ps(_mm_cmp_ps_mask(fl, _mm_set1_ps(float(lv.res)), _CMP_GE_OQ), fl,
                           _mm_set1_ps(float(lv.res - 1)));  // s == res: last cell
    fl = _mm_mask_blend_ps(_mm_cmp_ps_mask(fl, _mm_setzero_ps(), _CMP_LT_OQ), fl, _mm_setzero_ps());
    const __m128 f = _mm_min_ps(_mm_set1_ps(1.0f), _mm_max_ps(_mm_setzero_ps(), _mm_sub_ps(s, fl)));
    const __m128i i0 = _mm_cvttps_epi32(fl);
    // Lanes 0-2: lower corner per axis; lanes 4-6: upper corner.
    const __m256i ci =
        _mm256_inserti128_si256(_mm256_castsi128_si256(i0), _mm_add_epi32(i0, _mm_set1_epi32(1)), 1);
    const __m256 cw = _mm256_insertf128_ps(_mm256_castps128_ps256(_mm_sub_ps(_mm_set1_ps(1.0f), f)), f, 1);
    // Corner c = x + 2y + 4z, the scalar loops' order (x fastest).
    const __m256i sel_x = _mm256_setr_epi32(0, 4, 0, 4, 0, 4, 0, 4);
    const __m256i sel_y = _mm256_setr_epi32(1, 1, 5, 5, 1, 1, 5, 5);
    const __m256i sel_z = _mm256_setr_epi32(2, 2, 2, 2, 6, 6, 6, 6);
    const __m256i X = _mm256_permutexvar_epi32(sel_x, ci), Y = _mm256_permutexvar_epi32(sel_y, ci),
                  Z = _mm256_permutexvar_epi32(sel_z, ci);
    const __m256 wx = _mm256_permutexvar_ps(sel_x, cw), wy = _mm256_permutexvar_ps(sel_y, cw),
                 wz = _mm256_permutexvar_ps(sel_z, cw);
    __m256i idx;
    if (lv.dense) {
        const __m256i stride = _mm256_set1_epi32(int(lv.stride));
        idx = _mm256_add_epi32(
            X, _mm256_mullo_epi32(stride, _mm256_add_epi32(Y, _mm256_mullo_epi32(stride, Z))));
    } else {
        idx = _mm256_xor_si256(_mm256_xor_si256(_mm256_mullo_epi32(X, _mm256_set1_epi32(int(geo.primes[0]))),
                                                _mm256_mullo_epi32(Y, _mm256_set1_epi32(int(geo.primes[1])))),
                               _mm256_mullo_epi32(Z, _mm256_set1_epi32(int(geo.primes[2]))));
        idx = _mm256_and_si256(idx, _mm256_set1_epi32(int(lv.mask)));
    }
    const __m256 w = _mm256_mul_ps(_mm256_mul_ps(wx, wy), wz);
    const __m256 zero = _mm256_setzero_ps();
    const __mmask8 keep = _mm256_cmp_ps_mask(wx, zero, _CMP_NEQ_OQ) &
                          _mm256_cmp_ps_mask(wy, zero, _CMP_NEQ_OQ) &
                          _mm256_cmp_ps_mask(wz, zero, _CMP_NEQ_OQ);
    _mm256_storeu_si256(reinterpret_cast<__m256i*>(out.index), _mm256_maskz_compress_epi32(keep, idx));
    _mm256_storeu_ps(out.weight, _mm256_maskz_compress_ps(keep, w));
    out.n = std::uint32_t(__builtin_popcount(keep));
}

#endif

}  // namespace

void level_corners(const Geometry& geo, const LevelInfo& lv, const float g[3], Corners& out) {
#if LSNIF_HAVE_X86
    static const bool avx512 = cpu_features().avx512;  // called per point: no call into cpu.cpp each time
    if (avx512) return level_corners_avx512(geo, lv, g, out);
#endif
    level_corners_scalar(geo, lv, g, out);
}

void level_corners_reference(const Geometry& geo, const LevelInfo& lv, const float g[3], Corners& out) {
    level_corners_scalar(geo, lv, g, out);
}

namespace {

inline float load_feature(const float* p) {
    return *p;
}
inline float load_feature(const std::uint16_t* p) {
#if defined(__F16C__)
    return _cvtsh_ss(*p);
#else
    return half_to_float(*p);
#endif
}

// u8 features: the normative fma of FORMAT.md §6.4.1, so this scalar code, any
// vectorization the compiler makes of it, and the f32 table a test dequantizes up front
// all see the same floats.
struct U8Loader {
    float scale, offset;
    float operator()(const std::uint8_t* p) const { return dequantize_u8(*p, scale, offset); }
};
struct PlainLoader {
    template <class T>
    float operator()(const T* p) const {
        return load_feature(p);
    }
};

// Interpolates one level from precomputed corners: per feature, starting from 0, one
// explicitly fused multiply-add per corner in corner order, so every build and the
// 16-point encoder (encode_batch) round it the same way.
template <class T, class Load>
void accumulate_level(const Corners& c, const T* table, std::uint32_t stride, std::uint32_t F, Load load,
                      float* dst) {
    if (F == 3) {  // the v1 layout, unrolled
        float a0 = 0, a1 = 0, a2 = 0;
        for (std::uint32_t k = 0; k < c.n; ++k) {
            const T* src = table + std::size_t(c.index[k]) * stride;
            a0 = std::fma(c.weight[k], load(src), a0);
            a1 = std::fma(c.weight[k], load(src + 1), a1);
            a2 = std::fma(c.weight[k], load(src + 2), a2);
        }
        dst[0] = a0, dst[1] = a1, dst[2] = a2;
        return;
    }
    for (std::uint32_t f = 0; f < F; ++f) dst[f] = 0.0f;
    for (std::uint32_t k = 0; k < c.n; ++k) {
        const T* src = table + std::size_t(c.index[k]) * stride;
        for (std::uint32_t f = 0; f < F; ++f) dst[f] = std::fma(c.weight[k], load(src + f), dst[f]);
    }
}

// entry_offsets' signature: the batch encoder passes a vector version with the same bits.
using EntryOffsets = void (*)(const Geometry&, const RayPoints&, float*);

// What encode_points writes besides the occupied slots' features: zeros for the empty
// slots, then the ray inputs the model has (the entry offsets by `offsets`).
void encode_ray_inputs(const Geometry& geo, const RayPoints& pts, float* row,
                       EntryOffsets offsets = entry_offsets) {
    const std::size_t slot = std::size_t(geo.L) * geo.F;
    std::memset(row + pts.count * slot, 0, sizeof(float) * (geo.H - pts.count) * slot);
    if (geo.direction_width) std::memcpy(row + geo.point_width, pts.dir, sizeof(pts.dir));
    if (geo.offset_width) offsets(geo, pts, row + geo.point_width + geo.direction_width);
}

std::size_t element_size(GridElement e) {
    return e == GridElement::f32 ? 4 : e == GridElement::f16 ? 2 : 1;
}

}  // namespace

void encode_points(const Geometry& geo, const GridView* grid, const RayPoints& pts, float* row) {
    const std::uint32_t F = geo.F, L = geo.L;
    // Two passes: all corner indices first (prefetching their table rows), then the
    // interpolation. The tables are larger than L1/L2, so the reads are latency-bound;
    // issuing them all up front lets them overlap instead of stalling point by point.
    thread_local std::vector<Corners> corners;
    corners.resize(std::size_t(geo.H) * L);
    for (std::uint32_t h = 0; h < pts.count; ++h)
        for (std::uint32_t l = 0; l < L; ++l) {
            Corners& c = corners[std::size_t(h) * L + l];
            level_corners(geo, geo.levels[l], pts.g[h], c);
            const std::size_t elem = element_size(grid[l].element);
            const char* base = static_cast<const char*>(grid[l].data);
            for (std::uint32_t k = 0; k < c.n; ++k)
                __builtin_prefetch(base + std::size_t(c.index[k]) * grid[l].stride * elem);
        }
    for (std::uint32_t h = 0; h < pts.count; ++h)
        for (std::uint32_t l = 0; l < L; ++l) {
            const Corners& c = corners[std::size_t(h) * L + l];
            float* dst = row + (std::size_t(h) * L + l) * F;
            const GridView& g = grid[l];
            switch (g.element) {
                case GridElement::f16:
                    accumulate_level(c, static_cast<const std::uint16_t*>(g.data), g.stride, F, PlainLoader{},
                                     dst);
                    break;
                case GridElement::f32:
                    accumulate_level(c, static_cast<const float*>(g.data), g.stride, F, PlainLoader{}, dst);
                    break;
                case GridElement::u8:
                    accumulate_level(c, static_cast<const std::uint8_t*>(g.data), g.stride, F,
                                     U8Loader{g.scale, g.offset}, dst);
                    break;
            }
        }
    encode_ray_inputs(geo, pts, row);
}

namespace {

#if LSNIF_HAVE_X86

#define LSNIF_AVX512 __attribute__((target("avx512f,avx512vl,avx512bw,avx512dq,fma")))

// The points of a batch of rays as structure-of-arrays, one entry per occupied slot:
// its grid coordinates and where its level features go (float offset into the rows).
struct PointList {
    std::vector<float> g[3];
    std::vector<std::int32_t> out;
    std::size_t n = 0;
};

// Per axis of 16 points at one level: the lower and upper lattice corner's term of the
// index (prime product for a hashed level, stride power for a dense one), trilinear
// factor and whether the factor is non-zero. The operations are level_corners_avx512's,
// lane by lane.
struct AxisCorners {
    __m512i term[2];
    __m512 weight[2];
    __mmask16 nonzero[2];
};

LSNIF_AVX512 inline AxisCorners axis_corners(const LevelInfo& lv, __m512 g, std::uint32_t multiplier) {
    const __m512 s = _mm512_mul_ps(g, _mm512_set1_ps(lv.scale));
    __m512 fl = _mm512_roundscale_ps(s, _MM_FROUND_TO_NEG_INF | _MM_FROUND_NO_EXC);
    fl = _mm512_mask_blend_ps(_mm512_cmp_ps_mask(fl, _mm512_set1_ps(float(lv.res)), _CMP_GE_OQ), fl,
                              _mm512_set1_ps(float(lv.res - 1)));  // s == res: last cell
    fl = _mm512_mask_blend_ps(_mm512_cmp_ps_mask(fl, _mm512_setzero_ps(), _CMP_LT_OQ), fl,
                              _mm512_setzero_ps());
    const __m512 f =
        _mm512_min_ps(_mm512_set1_ps(1.0f), _mm512_max_ps(_mm512_setzero_ps(), _mm512_sub_ps(s, fl)));
    const __m512i i0 = _mm512_cvttps_epi32(fl);
    const __m512i m = _mm512_set1_epi32(int(multiplier));
    AxisCorners c;
    c.term[0] = _mm512_mullo_epi32(i0, m);
    c.term[1] = _mm512_mullo_epi32(_mm512_add_epi32(i0, _mm512_set1_epi32(1)), m);
    c.weight[0] = _mm512_sub_ps(_mm512_set1_ps(1.0f), f);
    c.weight[1] = f;
    for (int b = 0; b < 2; ++b)
        c.nonzero[b] = _mm512_cmp_ps_mask(c.weight[b], _mm512_setzero_ps(), _CMP_NEQ_OQ);
    return c;
}

// The live corners of 16 points at one level: per axis the corner terms and factors, the
// lanes with both sides live, the lanes whose one live side is the upper one, and each
// lane's count n of live corners (the product of its axes' live sides).
struct LaneCorners {
    AxisCorners ax[3];
    __mmask16 both[3], upper[3];
    __m512i n;
};

// `g` holds the points' grid coordinates per axis (lanes past the points are ignored by
// the callers' masks).
LSNIF_AVX512 inline LaneCorners lane_corners(const Geometry& geo, const LevelInfo& lv, const __m512 (&g)[3]) {
    const std::uint32_t mult[3] = {lv.dense ? 1u : geo.primes[0], lv.dense ? lv.stride : geo.primes[1],
                                   lv.dense ? lv.stride * lv.stride : geo.primes[2]};
    LaneCorners c;
    const __m512i one = _mm512_set1_epi32(1);
    c.n = one;
    for (int a = 0; a < 3; ++a) {
        c.ax[a] = axis_corners(lv, g[a], mult[a]);
        c.both[a] = c.ax[a].nonzero[0] & c.ax[a].nonzero[1];
        c.upper[a] = __mmask16(~c.ax[a].nonzero[0]);
        c.n = _mm512_mask_slli_epi32(c.n, c.both[a], c.n, 1);
    }
    return c;
}

// The corner terms and factors of slot s of every lane on axes first..2: the digits of s are
// one bit per axis with both sides live (the upper side where set), in axis order; an axis
// with one live side takes that side.
LSNIF_AVX512 inline void slot_sides(const LaneCorners& c, std::uint32_t s, int first, __m512i (&term)[3],
                                    __m512 (&weight)[3]) {
    const __m512i one = _mm512_set1_epi32(1);
    __m512i digits = _mm512_set1_epi32(int(s));
    for (int a = first; a < 3; ++a) {
        const __mmask16 up = (c.both[a] & _mm512_test_epi32_mask(digits, one)) | (~c.both[a] & c.upper[a]);
        digits = _mm512_mask_srli_epi32(digits, c.both[a], digits, 1);
        term[a] = _mm512_mask_blend_epi32(up, c.ax[a].term[0], c.ax[a].term[1]);
        weight[a] = _mm512_mask_blend_ps(up, c.ax[a].weight[0], c.ax[a].weight[1]);
    }
}

// Slot s of every lane: its s-th live corner in corner order c = x + 2y + 4z (x fastest),
// the digits of s taken x first (slot_sides); level_corners' order and values (the weight
// is (w_x * w_y) * w_z). Meaningful in lanes with s < n.
LSNIF_AVX512 inline void slot_corner(const LaneCorners& c, const LevelInfo& lv, std::uint32_t s, __m512i& idx,
                                     __m512& w) {
    __m512i term[3];
    __m512 weight[3];
    slot_sides(c, s, 0, term, weight);
    idx = lv.dense ? _mm512_add_epi32(_mm512_add_epi32(term[0], term[1]), term[2])
                   : _mm512_and_si512(_mm512_xor_si512(_mm512_xor_si512(term[0], term[1]), term[2]),
                                      _mm512_set1_epi32(int(lv.mask)));
    w = _mm512_mul_ps(_mm512_mul_ps(weight[0], weight[1]), weight[2]);
}

// Feature f (< F <= 4) of the rows at element offsets `off` (row * stride) of a table of
// element type E, for the lanes in k (0 elsewhere), converted to f32 exactly as the scalar
// loaders do.
template <GridElement E>
LSNIF_AVX512 inline void load_features(const GridView& g, __m512i off, __mmask16 k, std::uint32_t F,
                                       __m512 (&v)[4]) {
    const __m512i zero = _mm512_setzero_si512();
    if constexpr (E == GridElement::u8) {  // one dword from the entry: its features, then what follows
        const __m512i q = _mm512_mask_i32gather_epi32(zero, k, off, g.data, 1);
        const __m512i byte = _mm512_set1_epi32(0xFF);
        for (std::uint32_t f = 0; f < F; ++f) {
            const __m512 x = _mm512_cvtepi32_ps(_mm512_and_si512(_mm512_srli_epi32(q, int(8 * f)), byte));
            v[f] = _mm512_fmadd_ps(x, _mm512_set1_ps(g.scale), _mm512_set1_ps(g.offset));
        }
    } else if constexpr (E == GridElement::f16) {  // two dwords from the entry: halves 0-1 and 2-3
        for (std::uint32_t f = 0; f < F; f += 2) {
            const __m512i h = _mm512_mask_i32gather_epi32(
                zero, k, _mm512_add_epi32(off, _mm512_set1_epi32(int(f))), g.data, 2);
            v[f] = _mm512_cvtph_ps(_mm512_cvtepi32_epi16(h));
            if (f + 1 < F) v[f + 1] = _mm512_cvtph_ps(_mm512_cvtepi32_epi16(_mm512_srli_epi32(h, 16)));
        }
    } else {
        for (std::uint32_t f = 0; f < F; ++f)
            v[f] = _mm512_mask_i32gather_ps(_mm512_setzero_ps(), k,
                                            _mm512_add_epi32(off, _mm512_set1_epi32(int(f))), g.data, 4);
    }
}

// One level's F features of 16 points (grid coordinates `points`, the lanes in `lanes`),
// written to feature rows f of `tmp` (16 floats each, one lane per point): encode_points'
// per-point arithmetic, 16 points per vector. Each lane walks its own live corners (those
// level_corners keeps: no zero factor) in level_corners' order, so a point on a voxel face
// of an aligned level costs 4 gathers, not 8. kF = geo.F known at compile time (0: read at
// run time) and the table's element type E let the accumulators stay in registers: with a
// run-time F and a switch on the element type per corner they lived on the stack, each
// corner's masked store waiting for the last.
template <std::uint32_t kF, GridElement E>
LSNIF_AVX512 void level_features16(const Geometry& geo, const LevelInfo& lv, const GridView& g,
                                   const __m512 (&points)[3], __mmask16 lanes, float* tmp) {
    const std::uint32_t F = kF ? kF : geo.F;
    const LaneCorners c = lane_corners(geo, lv, points);
    const std::uint32_t slots = _mm512_mask_reduce_max_epu32(lanes, c.n);
    const __m512i stride = _mm512_set1_epi32(int(g.stride));
    __m512 acc[4] = {_mm512_setzero_ps(), _mm512_setzero_ps(), _mm512_setzero_ps(), _mm512_setzero_ps()};
    for (std::uint32_t s = 0; s < slots; ++s) {
        const __mmask16 k = lanes & _mm512_cmpgt_epu32_mask(c.n, _mm512_set1_epi32(int(s)));
        __m512i idx;
        __m512 w;
        slot_corner(c, lv, s, idx, w);
        __m512 v[4];
        load_features<E>(g, _mm512_mullo_epi32(idx, stride), k, F, v);
        for (std::uint32_t f = 0; f < F; ++f) acc[f] = _mm512_mask3_fmadd_ps(w, v[f], acc[f], k);
    }
    for (std::uint32_t f = 0; f < F; ++f) _mm512_store_ps(tmp + 16 * f, acc[f]);
}

LSNIF_AVX512 void level_corners16_avx512(const Geometry& geo, const LevelInfo& lv, const float* x,
                                         const float* y, const float* z, std::uint32_t count,
                                         Corners16& out) {
    const __mmask16 lanes = detail::lane_mask16(0, count);
    const __m512 points[3] = {_mm512_maskz_loadu_ps(lanes, x), _mm512_maskz_loadu_ps(lanes, y),
                              _mm512_maskz_loadu_ps(lanes, z)};
    const LaneCorners c = lane_corners(geo, lv, points);
    _mm512_store_si512(out.n, _mm512_maskz_mov_epi32(lanes, c.n));
    const std::uint32_t slots = _mm512_mask_reduce_max_epu32(lanes, c.n);
    for (std::uint32_t s = 0; s < slots; ++s) {
        __m512i idx;
        __m512 w;
        slot_corner(c, lv, s, idx, w);
        _mm512_store_si512(out.index[s], idx);
        _mm512_store_ps(out.weight[s], w);
    }
}

// level_features16 for a u8 table of a dense level with F = 3 features (stride 3): a
// lattice cell's two corners along x are neighbouring entries, 6 bytes, so one 64-bit
// gather lane reads both. Each lane walks its live (y, z) corner pairs in level_corners'
// order, and per pair its lower x corner, then its upper one, each only where its factor is
// non-zero: the corners, weights ((w_x * w_y) * w_z) and fused multiply-adds of
// level_features16, in the same order, from half as many gathered elements.
LSNIF_AVX512 void level_features16_pairs(const Geometry& geo, const LevelInfo& lv, const GridView& g,
                                         const __m512 (&points)[3], __mmask16 lanes, float* tmp) {
    constexpr std::uint32_t F = 3;
    const LaneCorners c = lane_corners(geo, lv, points);
    // (y, z) pairs per lane: its live corners over the x sides it has.
    const __m512i pairs = _mm512_mask_srli_epi32(c.n, c.both[0], c.n, 1);
    const std::uint32_t slots = _mm512_mask_reduce_max_epu32(lanes, pairs);
    const __m512i stride = _mm512_set1_epi32(int(g.stride));
    const __m512i one = _mm512_set1_epi32(1);
    // The 64 bits read start a byte before the lower corner's entry (the table's tail pad
    // holds one byte after the last entry), or at the entry itself for entry 0.
    const __m512i even = _mm512_setr_epi32(0, 2, 4, 6, 8, 10, 12, 14, 16, 18, 20, 22, 24, 26, 28, 30);
    const __m512i odd = _mm512_add_epi32(even, one);
    const __m512i byte = _mm512_set1_epi32(0xFF);
    const __m512 scale = _mm512_set1_ps(g.scale), offset = _mm512_set1_ps(g.offset);
    const auto* table = static_cast<const std::uint8_t*>(g.data);
    __m512 acc[3] = {_mm512_setzero_ps(), _mm512_setzero_ps(), _mm512_setzero_ps()};
    for (std::uint32_t s = 0; s < slots; ++s) {
        const __mmask16 k = lanes & _mm512_cmpgt_epu32_mask(pairs, _mm512_set1_epi32(int(s)));
        // The (y, z) pair's sides; x's lower corner starts the pair.
        __m512i term[3];
        __m512 weight[3];
        slot_sides(c, s, 1, term, weight);
        const __m512i lower = _mm512_add_epi32(_mm512_add_epi32(c.ax[0].term[0], term[1]), term[2]);
        const __m512i entry = _mm512_mullo_epi32(lower, stride);
        const __m512i start = _mm512_max_epi32(_mm512_sub_epi32(entry, one), _mm512_setzero_si512());
        const __m512i skip = _mm512_slli_epi32(_mm512_sub_epi32(entry, start), 3);  // 0 or 8 bits
        const auto half = [&](int h) LSNIF_AVX512 {
            const __m256i at = h ? _mm512_extracti64x4_epi64(start, 1) : _mm512_castsi512_si256(start);
            const __m256i bits = h ? _mm512_extracti64x4_epi64(skip, 1) : _mm512_castsi512_si256(skip);
            const __m512i q =
                _mm512_mask_i32gather_epi64(_mm512_setzero_si512(), __mmask8(k >> (8 * h)), at, table, 1);
            return _mm512_srlv_epi64(q, _mm512_cvtepu32_epi64(bits));
        };
        const __m512i lo = half(0), hi = half(1);
        const __m512i bytes0_3 = _mm512_permutex2var_epi32(lo, even, hi);
        const __m512i bytes4_7 = _mm512_permutex2var_epi32(lo, odd, hi);
        const auto feature = [&](std::uint32_t b) LSNIF_AVX512 {  // byte b of the 2F, dequantized
            const __m512i word = b < 4 ? bytes0_3 : bytes4_7;
            const __m512 x =
                _mm512_cvtepi32_ps(_mm512_and_si512(_mm512_srli_epi32(word, int(8 * (b % 4))), byte));
            return _mm512_fmadd_ps(x, scale, offset);
        };
        for (int side = 0; side < 2; ++side) {
            const __mmask16 live = k & c.ax[0].nonzero[side];
            const __m512 w = _mm512_mul_ps(_mm512_mul_ps(c.ax[0].weight[side], weight[1]), weight[2]);
            for (std::uint32_t f = 0; f < F; ++f)
                acc[f] = _mm512_mask3_fmadd_ps(w, feature(side * F + f), acc[f], live);
        }
    }
    for (std::uint32_t f = 0; f < F; ++f) _mm512_store_ps(tmp + 16 * f, acc[f]);
}

// level_features16 for a model's F and a table's element type: every preset's F = 3
// compiled as a constant, any other F read at run time; level_features16_pairs where it
// applies.
using LevelFeatures16 = void (*)(const Geometry&, const LevelInfo&, const GridView&, const __m512 (&)[3],
                                 __mmask16, float*);
template <std::uint32_t kF>
LevelFeatures16 level_features16_of(GridElement e) {
    switch (e) {
        case GridElement::u8: return level_features16<kF, GridElement::u8>;
        case GridElement::f16: return level_features16<kF, GridElement::f16>;
        case GridElement::f32: break;
    }
    return level_features16<kF, GridElement::f32>;
}
LevelFeatures16 level_features16_for(const Geometry& geo, const LevelInfo& lv, const GridView& g) {
    if (lv.dense && g.element == GridElement::u8 && g.stride == 3 && geo.F == 3)
        return level_features16_pairs;
    return geo.F == 3 ? level_features16_of<3>(g.element) : level_features16_of<0>(g.element);
}

// Every level's features of points [i, i + 16) of `pl` (lanes past pl.n masked off), written
// to the rows at the points' offsets: the L * F columns of a point are contiguous in its row,
// so the 16 points' columns, computed one column per vector, are transposed in registers and
// stored a point at a time.
LSNIF_AVX512 void encode_block16(const Geometry& geo, const GridView* grid, const LevelFeatures16* level,
                                 const PointList& pl, std::size_t i, float* rows) {
    alignas(64) float tmp[LSNIF_MAX_LEVELS * 4 * 16];
    const __mmask16 lanes = detail::lane_mask16(i, pl.n);
    const __m512 points[3] = {_mm512_maskz_loadu_ps(lanes, pl.g[0].data() + i),
                              _mm512_maskz_loadu_ps(lanes, pl.g[1].data() + i),
                              _mm512_maskz_loadu_ps(lanes, pl.g[2].data() + i)};
    for (std::uint32_t l = 0; l < geo.L; ++l)
        level[l](geo, geo.levels[l], grid[l], points, lanes, tmp + std::size_t(16) * geo.F * l);
    const std::uint32_t columns = geo.L * geo.F;
    const std::int32_t* out = pl.out.data() + i;
    const std::uint32_t n = std::uint32_t(std::popcount(std::uint32_t(lanes)));
    for (std::uint32_t c0 = 0; c0 < columns; c0 += 16) {
        const std::uint32_t width = std::min(16u, columns - c0);
        __m512i r[16];
        for (std::uint32_t j = 0; j < 16; ++j)
            r[j] = j < width ? _mm512_load_si512(tmp + std::size_t(16) * (c0 + j)) : _mm512_setzero_si512();
        detail::transpose16(r);  // r[p]: columns c0.. of point p
        const __mmask16 keep = detail::lane_mask16(0, width);
        for (std::uint32_t p = 0; p < n; ++p) _mm512_mask_storeu_epi32(rows + out[p] + c0, keep, r[p]);
    }
}

// The vector encoder reads an entry's features with dword gathers: up to 4 of them (GridView's
// contract keeps 4 elements readable from every entry).
bool encode_batch_supported(const Geometry& geo) {
    return geo.F <= 4;
}

// A first point whose features another row's first point already gets: copied after
// encoding, from float offset `from` of the rows to `to`.
struct SharedPoint {
    std::int32_t from, to;
};

// Calls add(j, 0) for the first point of every row j of `which` that has points, except
// where another row already gets the same features: the same ray listed twice, or the ray
// just before it (which[j] - 1) in the batch with a first point of the same grid
// coordinates bit for bit — rays leaving one surface point one after the other, as a
// renderer's ambient-occlusion and shadow rays from one shading point do. Features are a
// function of the coordinates alone, so such a row copies the other row's instead of
// encoding them again: the same bits. Returns the copies to make (float offsets of the
// rows' first slots, each source encoded; valid until the thread's next call).
template <class Add>
const std::vector<SharedPoint>& shared_first_points(const Geometry& geo, const RayPoints* pts,
                                                    std::span<const std::uint32_t> which, Add&& add) {
    constexpr std::uint32_t kNone = ~0u;
    thread_local std::vector<SharedPoint> shared;
    thread_local std::vector<std::uint32_t> row_of, root;  // per ray: its first row, the row it copies
    shared.clear();
    std::uint32_t top = 0;
    for (const std::uint32_t r : which) top = std::max(top, r);
    row_of.assign(std::size_t(top) + 1, kNone);
    root.resize(std::size_t(top) + 1);
    for (std::uint32_t j = 0; j < which.size(); ++j)
        if (row_of[which[j]] == kNone) row_of[which[j]] = j;
    for (std::uint32_t r = 0; r <= top; ++r) {
        root[r] = kNone;
        if (row_of[r] == kNone || !pts[r].count) continue;
        const bool same = r > 0 && root[r - 1] != kNone &&
                          std::memcmp(pts[r].g[0], pts[r - 1].g[0], sizeof(pts[r].g[0])) == 0;
        root[r] = same ? root[r - 1] : row_of[r];
    }
    for (std::uint32_t j = 0; j < which.size(); ++j) {
        const std::uint32_t r = which[j];
        if (!pts[r].count) continue;
        if (root[r] == j)
            add(j, 0);
        else
            shared.push_back({std::int32_t(root[r] * geo.input_width), std::int32_t(j * geo.input_width)});
    }
    return shared;
}

// entry_offsets for models with H <= 16: every slot's offset in one vector, with
// entry_offsets' subtractions, products, fused multiply-adds, square root and division per
// slot (each correctly rounded at any width), so the same bits. A scalar square root and
// division per slot cost more than a ray's encoding of a level on some cores.
LSNIF_AVX512 void entry_offsets16(const Geometry& geo, const RayPoints& pts, float* out) {
    // The first 16 slots' coordinates, one vector per axis.
    static_assert(kMaxPoints >= 16);
    const float* g = &pts.g[0][0];
    __m512 x[3], d[3];
    detail::point_axes16(g, x);
    for (int a = 0; a < 3; ++a)
        d[a] = _mm512_mul_ps(_mm512_sub_ps(x[a], _mm512_set1_ps(g[a])), _mm512_set1_ps(geo.cell[a]));
    const __m512 squared =
        _mm512_fmadd_ps(d[2], d[2], _mm512_fmadd_ps(d[1], d[1], _mm512_mul_ps(d[0], d[0])));
    const __m512 offset = _mm512_div_ps(_mm512_sqrt_ps(squared), _mm512_set1_ps(geo.diagonal));
    // Slot 0 (entry_offsets writes +0) and the slots past the count up to H: zero.
    const __mmask16 points = __mmask16(((1u << std::min(pts.count, geo.H)) - 1u) & ~1u);
    _mm512_mask_storeu_ps(out, __mmask16((1u << geo.H) - 1u), _mm512_maskz_mov_ps(points, offset));
}

LSNIF_AVX512 void encode_batch_avx512(const Geometry& geo, const GridView* grid, const RayPoints* pts,
                                      std::span<const std::uint32_t> which, float* rows) {
    thread_local PointList pl;
    std::size_t total = 0;
    for (const std::uint32_t r : which) total += pts[r].count;
    for (auto& v : pl.g) v.resize(total);
    pl.out.resize(total);
    const std::size_t slot = std::size_t(geo.L) * geo.F;
    std::size_t i = 0;
    // The rays' first points last: a ray that starts inside a voxel has one there with 8
    // live corners, and a group of 16 points runs to its largest count of live corners.
    const auto add = [&](std::size_t j, std::uint32_t h) {
        const RayPoints& p = pts[which[j]];
        for (int a = 0; a < 3; ++a) pl.g[a][i] = p.g[h][a];
        pl.out[i++] = std::int32_t(j * geo.input_width + h * slot);
    };
    const EntryOffsets offsets = geo.H <= 16 ? entry_offsets16 : entry_offsets;
    for (std::size_t j = 0; j < which.size(); ++j) {
        const RayPoints& p = pts[which[j]];
        for (std::uint32_t h = 1; h < p.count; ++h) add(j, h);
        encode_ray_inputs(geo, p, rows + j * geo.input_width, offsets);
    }
    const std::vector<SharedPoint>& shared = shared_first_points(geo, pts, which, add);
    pl.n = i;  // at most total: shared first points are copied, not listed
    LevelFeatures16 level[LSNIF_MAX_LEVELS];
    for (std::uint32_t l = 0; l < geo.L; ++l) level[l] = level_features16_for(geo, geo.levels[l], grid[l]);
    for (std::size_t b = 0; b < pl.n; b += 16) encode_block16(geo, grid, level, pl, b, rows);
    for (const SharedPoint& c : shared) std::memcpy(rows + c.to, rows + c.from, slot * sizeof(float));
}

#undef LSNIF_AVX512

#endif

}  // namespace

void level_corners16(const Geometry& geo, const LevelInfo& lv, const float* x, const float* y, const float* z,
                     std::uint32_t count, Corners16& out) {
    count = std::min(count, 16u);
#if LSNIF_HAVE_X86
    static const bool avx512 = cpu_features().avx512;  // called per 16 points
    if (avx512) return level_corners16_avx512(geo, lv, x, y, z, count, out);
#endif
    for (std::uint32_t j = 0; j < 16; ++j) out.n[j] = 0;
    for (std::uint32_t j = 0; j < count; ++j) {
        const float g[3] = {x[j], y[j], z[j]};
        Corners c;
        level_corners(geo, lv, g, c);
        out.n[j] = c.n;
        for (std::uint32_t s = 0; s < c.n; ++s) {
            out.index[s][j] = c.index[s];
            out.weight[s][j] = c.weight[s];
        }
    }
}

void encode_batch(const Geometry& geo, const GridView* grid, const RayPoints* pts,
                  std::span<const std::uint32_t> which, float* rows) {
#if LSNIF_HAVE_X86
    if (cpu_features().avx512 && encode_batch_supported(geo) &&
        which.size() * geo.input_width <= std::size_t(std::numeric_limits<std::int32_t>::max()))
        return encode_batch_avx512(geo, grid, pts, which, rows);
#endif
    for (std::size_t j = 0; j < which.size(); ++j)
        encode_points(geo, grid, pts[which[j]], rows + j * geo.input_width);
}

void entry_offsets(const Geometry& geo, const RayPoints& pts, float* out) {
    // Slot 0's offset, from the first entry to itself, is sqrt(+0) / diagonal = +0 for the
    // walk's finite coordinates: written, not computed.
    const std::uint32_t n = std::min(pts.count, geo.H);
    out[0] = 0.0f;
    for (std::uint32_t k = 1; k < n; ++k) {
        float d[3];
        for (int a = 0; a < 3; ++a) d[a] = (pts.g[k][a] - pts.g[0][a]) * geo.cell[a];
        out[k] = std::sqrt(std::fma(d[2], d[2], std::fma(d[1], d[1], d[0] * d[0]))) / geo.diagonal;
    }
    std::fill(out + std::max(n, 1u), out + geo.H, 0.0f);
}

// ---- MLP --------------------------------------------------------------------------------

namespace {

std::uint32_t pad16(std::uint32_t n) {
    return (n + 15u) & ~15u;
}

// W^T [in][pad16(out)] of weights [out][in] row-major, the padding columns zero.
template <class T>
std::vector<T> transpose_padded(const T* w_row_major, std::uint32_t in, std::uint32_t out) {
    const std::uint32_t op = pad16(out);
    std::vector<T> wt(std::size_t(in) * op, T(0));
    for (std::uint32_t o = 0; o < out; ++o)
        for (std::uint32_t i = 0; i < in; ++i)
            wt[std::size_t(i) * op + o] = w_row_major[std::size_t(o) * in + i];
    return wt;
}

// Appends a layer of `in` inputs and `out` outputs: its fp32 W^T (transpose_padded; empty for
// a model network's hidden layer) and its `out` biases, padded.
void add_layer(Network& net, std::uint32_t in, std::uint32_t out, std::vector<float> wt, const float* b) {
    const std::uint32_t op = pad16(out);
    std::vector<float> bias(op, 0.0f);
    std::copy(b, b + out, bias.begin());
    net.in.push_back(in);
    net.out.push_back(out);
    net.out_padded.push_back(op);
    net.wt.push_back(std::move(wt));
    net.bias.push_back(std::move(bias));
    net.max_width_padded = std::max<std::size_t>(net.max_width_padded, op);
}

// Register-blocked kernel: MB rows x (NV vectors of W floats) accumulators, the weight
// vectors of one input index reused across MB rows, inputs broadcast. The same source is
// compiled for several ISAs; vector width W is the native SIMD width of each. Every output
// is its bias, then one fused multiply-add per input in input order (simd::fma), in every
// variant: the same bits on every ISA. Inputs that `zeros` names as zero in a whole block of
// rows are skipped (live_groups, one column per group): exact under ReLU, which the caller
// guarantees (dense_layer_strided). Weights have row stride ldw, C row stride ldc.
#define LSNIF_DENSE_KERNEL(NAME, TARGET, W)                                                        \
    template <class WT>                                                                            \
    TARGET void NAME(const float* A, std::size_t n, std::size_t in, std::size_t lda, const WT* wt, \
                     std::size_t ldw, const float* bias, std::size_t outp, bool relu, float* C,    \
                     std::size_t ldc, const ZeroColumns* zeros) {                                  \
        using vec = simd::Vec<W>;                                                                  \
        constexpr std::size_t MB = 6;                                                              \
        constexpr std::size_t NV = 4;                                                              \
        std::size_t o = 0;                                                                         \
        for (; o < outp; o += NV * W) {                                                            \
            const std::size_t nv = std::min<std::size_t>(NV, (outp - o) / W);                      \
            std::size_t r = 0;                                                                     \
            for (; r < n; r += MB) {                                                               \
                const std::size_t mb = std::min(MB, n - r);                                        \
                const LiveGroups live = live_groups(zeros, r, mb, in, 1);                          \
                vec acc[MB][NV];                                                                   \
                for (std::size_t v = 0; v < nv; ++v) {                                             \
                    vec b0 = *reinterpret_cast<const vec*>(bias + o + v * W);                      \
                    for (std::size_t m = 0; m < MB; ++m) acc[m][v] = b0;                           \
                }                                                                                  \
                if (mb == MB && nv == NV) {                                                        \
                    const auto input = [&](std::size_t i) TARGET {                                 \
                        const WT* wrow = wt + i * ldw + o;                                         \
                        const vec w0 = simd::load(wrow, vec{});                                    \
                        const vec w1 = simd::load(wrow + W, vec{});                                \
                        const vec w2 = simd::load(wrow + 2 * W, vec{});                            \
                        const vec w3 = simd::load(wrow + 3 * W, vec{});                            \
                        for (std::size_t m = 0; m < MB; ++m) {                                     \
                            const float a = A[(r + m) * lda + i];                                  \
                            acc[m][0] = simd::fma(a, w0, acc[m][0]);                               \
                            acc[m][1] = simd::fma(a, w1, acc[m][1]);                               \
                            acc[m][2] = simd::fma(a, w2, acc[m][2]);                               \
                            acc[m][3] = simd::fma(a, w3, acc[m][3]);                               \
                        }                                                                          \
                    };                                                                             \
                    for (std::size_t i = 0; i < live.head; ++i) input(i);                          \
                    for (std::size_t i = live.tail; i < live.end; ++i) input(i);                   \
                } else {                                                                           \
                    const auto input = [&](std::size_t i) TARGET {                                 \
                        const WT* wrow = wt + i * ldw + o;                                         \
                        for (std::size_t v = 0; v < nv; ++v) {                                     \
                            const vec w = simd::load(wrow + v * W, vec{});                         \
                            for (std::size_t m = 0; m < mb; ++m)                                   \
                                acc[m][v] = simd::fma(A[(r + m) * lda + i], w, acc[m][v]);         \
                        }                                                                          \
                    };                                                                             \
                    for (std::size_t i = 0; i < live.head; ++i) input(i);                          \
                    for (std::size_t i = live.tail; i < live.end; ++i) input(i);                   \
                }                                                                                  \
                for (std::size_t m = 0; m < mb; ++m)                                               \
                    for (std::size_t v = 0; v < nv; ++v) {                                         \
                        vec x = acc[m][v];                                                         \
                        if (relu) x = x > 0.0f ? x : 0.0f;                                         \
                        *reinterpret_cast<vec*>(C + (r + m) * ldc + o + v * W) = x;                \
                    }                                                                              \
            }                                                                                      \
        }                                                                                          \
    }

LSNIF_DENSE_KERNEL(dense_generic, , 4)
#if LSNIF_HAVE_X86
LSNIF_DENSE_KERNEL(dense_avx512, __attribute__((target("avx512f,avx512vl,avx2,fma"))), 16)
LSNIF_DENSE_KERNEL(dense_avx2, __attribute__((target("avx2,fma,f16c"))), 8)
#endif
#undef LSNIF_DENSE_KERNEL

#if LSNIF_HAVE_X86

// Narrow layers (outputs padded to 16, 32 or 48, e.g. the output layer), where the kernel
// above would fall back to its generic loop: one weight vector per input feeds 8 rows, the
// 8 independent FMA chains that cover the FMA latency. Same operations per output in the
// same order (bias, then input 0, 1, ...), so the same results bit for bit.
template <class WT>
__attribute__((target("avx512f,avx512vl,avx2,fma"))) void dense_narrow_avx512(
    const float* A, std::size_t n, std::size_t in, std::size_t lda, const WT* wt, std::size_t ldw,
    const float* bias, std::size_t outp, bool relu, float* C, std::size_t ldc, const ZeroColumns* zeros) {
    using vec = simd::F16;
    constexpr std::size_t MB = 8;
    for (std::size_t o = 0; o < outp; o += 16) {
        const vec b = *reinterpret_cast<const vec*>(bias + o);
        for (std::size_t r = 0; r < n; r += MB) {
            const std::size_t mb = std::min(MB, n - r);
            const LiveGroups live = live_groups(zeros, r, mb, in, 1);
            vec acc[MB];
            for (std::size_t m = 0; m < MB; ++m) acc[m] = b;
            if (mb == MB) {
                const auto input = [&](std::size_t i) __attribute__((target("avx512f,avx512vl,avx2,fma"))) {
                    const vec w = simd::load(wt + i * ldw + o, vec{});
                    for (std::size_t m = 0; m < MB; ++m) acc[m] = simd::fma(A[(r + m) * lda + i], w, acc[m]);
                };
                for (std::size_t i = 0; i < live.head; ++i) input(i);
                for (std::size_t i = live.tail; i < live.end; ++i) input(i);
            } else {
                const auto input = [&](std::size_t i) __attribute__((target("avx512f,avx512vl,avx2,fma"))) {
                    const vec w = simd::load(wt + i * ldw + o, vec{});
                    for (std::size_t m = 0; m < mb; ++m) acc[m] = simd::fma(A[(r + m) * lda + i], w, acc[m]);
                };
                for (std::size_t i = 0; i < live.head; ++i) input(i);
                for (std::size_t i = live.tail; i < live.end; ++i) input(i);
            }
            for (std::size_t m = 0; m < mb; ++m) {
                vec x = acc[m];
                if (relu) x = x > 0.0f ? x : 0.0f;
                *reinterpret_cast<vec*>(C + (r + m) * ldc + o) = x;
            }
        }
    }
}

// The output layer with rows in lanes: 16 rows at a time, their inputs transposed in
// registers 16 at a time, so each FMA computes one output of 16 rows and only the OUTS real
// outputs cost anything (the kernels above spend a 16-wide FMA per input on 5 real outputs).
// Per row and output: bias, then fma over inputs 0, 1, ..., as dense_narrow_avx512, so the
// real columns are the same bit for bit; padding columns are written as zeros. Requires
// outp == 16; rows beyond the last full block of 16 go to dense_narrow_avx512. One group of
// 16 rows at a time: the transposed inputs of two groups would not fit the registers.
template <int OUTS>
__attribute__((target("avx512f,avx512vl,avx2,fma"))) void dense_output_avx512(const float* A, std::size_t n,
                                                                              std::size_t in, std::size_t lda,
                                                                              const float* wt,
                                                                              const float* bias, float* C) {
    constexpr std::size_t kOutp = 16;
    std::size_t r0 = 0;
    for (; r0 + 16 <= n; r0 += 16) {
        __m512 acc[OUTS];
        for (int o = 0; o < OUTS; ++o) acc[o] = _mm512_set1_ps(bias[o]);
        // Inputs k0 .. k0 + kn - 1 of the 16 rows, one FMA per input and output.
        const auto block = [&](std::size_t k0, std::size_t kn)
            __attribute__((target("avx512f,avx512vl,avx2,fma"))) {
            const __mmask16 live = __mmask16((1u << kn) - 1u);
            __m512i t[16];
            for (std::size_t i = 0; i < 16; ++i)
                t[i] = _mm512_castps_si512(_mm512_maskz_loadu_ps(live, A + (r0 + i) * lda + k0));
            detail::transpose16(t);  // t[j]: input k0 + j of the 16 rows
            for (std::size_t j = 0; j < kn; ++j)
                for (int o = 0; o < OUTS; ++o)
                    acc[o] = _mm512_fmadd_ps(_mm512_castsi512_ps(t[j]),
                                             _mm512_set1_ps(wt[(k0 + j) * kOutp + o]), acc[o]);
        };
        std::size_t k0 = 0;
        for (; k0 + 16 <= in; k0 += 16) block(k0, 16);
        if (k0 < in) block(k0, in - k0);
        __m512i rows[16];
        for (int o = 0; o < 16; ++o)
            rows[o] = o < OUTS ? _mm512_castps_si512(acc[o]) : _mm512_setzero_si512();
        detail::transpose16(rows);  // rows[i]: the 16 outputs of row r0 + i
        for (std::size_t i = 0; i < 16; ++i) _mm512_storeu_si512(C + (r0 + i) * kOutp, rows[i]);
    }
    if (r0 < n)
        dense_narrow_avx512(A + r0 * lda, n - r0, in, lda, wt, kOutp, bias, kOutp, false, C + r0 * kOutp,
                            kOutp, nullptr);
}

#endif  // LSNIF_HAVE_X86

template <class WT>
using DenseFn = void (*)(const float*, std::size_t, std::size_t, std::size_t, const WT*, std::size_t,
                         const float*, std::size_t, bool, float*, std::size_t, const ZeroColumns*);

template <class WT>
DenseFn<WT> pick_dense() {
#if LSNIF_HAVE_X86
    if (cpu_features().avx512) return dense_avx512<WT>;
    if (cpu_features().avx2_fma) return dense_avx2<WT>;
#endif
    return dense_generic<WT>;
}

template <class WT>
void dense_strided(const float* A, std::size_t n, std::size_t in, std::size_t lda, const WT* wt,
                   std::size_t ldw, const float* bias, std::size_t out, bool relu, float* C, std::size_t ldc,
                   const ZeroColumns* zeros) {
    static const DenseFn<WT> fn = pick_dense<WT>();
    if (!relu) zeros = nullptr;  // skipping is exact only where ReLU makes a zero sum's sign moot
#if LSNIF_HAVE_X86
    if (out < 64 && fn == dense_avx512<WT>)
        return dense_narrow_avx512(A, n, in, lda, wt, ldw, bias, out, relu, C, ldc, zeros);
#endif
    fn(A, n, in, lda, wt, ldw, bias, out, relu, C, ldc, zeros);
}

}  // namespace

void dense_layer_strided(const float* A, std::size_t n, std::size_t in, std::size_t lda, const float* wt,
                         std::size_t ldw, const float* bias, std::size_t out, bool relu, float* C,
                         std::size_t ldc, const ZeroColumns* zeros) {
    dense_strided(A, n, in, lda, wt, ldw, bias, out, relu, C, ldc, zeros);
}

void dense_layer_strided(const float* A, std::size_t n, std::size_t in, std::size_t lda,
                         const std::uint16_t* wt, std::size_t ldw, const float* bias, std::size_t out,
                         bool relu, float* C, std::size_t ldc, const ZeroColumns* zeros) {
    dense_strided(A, n, in, lda, wt, ldw, bias, out, relu, C, ldc, zeros);
}

void dense_layer(const float* A, std::size_t n, std::size_t in, std::size_t lda, const float* wt,
                 const float* bias, std::size_t out_padded, bool relu, float* C) {
    dense_layer_strided(A, n, in, lda, wt, out_padded, bias, out_padded, relu, C, out_padded, nullptr);
}

void dense_output_layer(const float* A, std::size_t n, std::size_t in, std::size_t lda, const float* wt,
                        const float* bias, std::size_t out_padded, [[maybe_unused]] std::size_t outs,
                        float* C) {
#if LSNIF_HAVE_X86
    if (out_padded == 16 && cpu_features().avx512) switch (outs) {
            case 1: return dense_output_avx512<1>(A, n, in, lda, wt, bias, C);  // the visibility logit alone
            case 5: return dense_output_avx512<5>(A, n, in, lda, wt, bias, C);  // no materials
            case 6: return dense_output_avx512<6>(A, n, in, lda, wt, bias, C);
            case 7: return dense_output_avx512<7>(A, n, in, lda, wt, bias, C);
            case 8: return dense_output_avx512<8>(A, n, in, lda, wt, bias, C);
        }
#endif
    dense_layer(A, n, in, lda, wt, bias, out_padded, false, C);
}

Network make_network(const ModelData& m) {
    Network net;
    for (std::uint32_t k = 0; k < m.desc.layer_count(); ++k) {
        const auto [out, in] = m.desc.layer_shape(k);
        std::vector<std::uint16_t> wt = transpose_padded(m.weights[k].data(), in, out);
        // Only the output layer's kernel reads fp32 weights.
        const bool output = k + 1 == m.desc.layer_count();
        add_layer(net, in, out, output ? halves_to_floats(wt) : std::vector<float>{},
                  halves_to_floats(m.biases[k]).data());
        net.wt_f16.push_back(std::move(wt));
    }
    return net;
}

Network make_network(const ModelDesc& desc, const std::vector<std::vector<float>>& weights,
                     const std::vector<std::vector<float>>& biases) {
    Network net;
    for (std::uint32_t k = 0; k < desc.layer_count(); ++k) {
        const auto [o, i] = desc.layer_shape(k);
        add_layer(net, i, o, transpose_padded(weights[k].data(), i, o), biases[k].data());
    }
    return net;
}

std::vector<std::uint16_t> model_layer_weights(const Network& net, std::size_t k) {
    const std::size_t in = net.in[k], out = net.out[k], op = net.out_padded[k];
    std::vector<std::uint16_t> w(out * in);
    for (std::size_t o = 0; o < out; ++o)
        for (std::size_t i = 0; i < in; ++i) w[o * in + i] = net.wt_f16[k][i * op + o];
    return w;
}

std::vector<std::uint16_t> model_layer_bias(const Network& net, std::size_t k) {
    std::vector<std::uint16_t> b(net.out[k]);
    // Exact: each bias is a binary16 value widened by make_network.
    for (std::size_t o = 0; o < b.size(); ++o) b[o] = float_to_half(net.bias[k][o]);
    return b;
}

void hidden_layer_fp32(const Network& net, std::size_t k, const float* A, std::size_t n, std::size_t lda,
                       float* C, const ZeroColumns* zeros) {
    const std::size_t op = net.out_padded[k];
    if (!net.wt[k].empty())
        dense_layer_strided(A, n, net.in[k], lda, net.wt[k].data(), op, net.bias[k].data(), op, true, C, op,
                            zeros);
    else
        dense_layer_strided(A, n, net.in[k], lda, net.wt_f16[k].data(), op, net.bias[k].data(), op, true, C,
                            op, zeros);
}

MlpArithmetic best_mlp_arithmetic() {
    return cpu_features().avx512_vnni   ? MlpArithmetic::int8
           : cpu_features().avx512_bf16 ? MlpArithmetic::bf16
                                        : MlpArithmetic::fp32;
}

namespace {

bool int8_fits(const Network& net) {
    for (std::size_t k = 0; k + 1 < net.wt.size(); ++k)
        if (net.in[k] > kInt8MaxInputs) return false;
    return true;
}

// The hidden layers' fp32 W^T, which neither reduced arithmetic reads once packed.
void release_hidden_fp32(Network& net) {
    for (std::size_t k = 0; k + 1 < net.wt.size(); ++k) std::vector<float>().swap(net.wt[k]);
}

// Hidden layer k's W^T in fp32, from whichever storage the network has.
std::vector<float> hidden_wt_fp32(const Network& net, std::size_t k) {
    return net.wt[k].empty() ? halves_to_floats(net.wt_f16[k]) : net.wt[k];
}

}  // namespace

MlpArithmetic set_mlp_arithmetic(Network& net, MlpArithmetic a) {
    if (net.wt.empty()) return MlpArithmetic::fp32;
    if (mlp_arithmetic(net) != MlpArithmetic::fp32) {
        if (net.wt_f16.empty()) return mlp_arithmetic(net);
        // A model network repacks from its fp16 weights of record.
        decltype(net.wt_vnni)().swap(net.wt_vnni);
        decltype(net.wt_int8)().swap(net.wt_int8);
    }
    if (a == MlpArithmetic::int8 && cpu_features().avx512_vnni && int8_fits(net)) {
        // The first layer's inputs (encoded features) may be negative; later ones are ReLU outputs.
        for (std::size_t k = 0; k + 1 < net.wt.size(); ++k)
            net.wt_int8.push_back(
                make_int8_layer(hidden_wt_fp32(net, k).data(), net.in[k], net.out_padded[k], k == 0));
        release_hidden_fp32(net);
        return MlpArithmetic::int8;
    }
    if (a == MlpArithmetic::fp32 || !cpu_features().avx512_bf16) return MlpArithmetic::fp32;
    for (std::size_t k = 0; k + 1 < net.wt.size(); ++k) {
        const std::size_t in = net.in[k], op = net.out_padded[k];
        net.wt_vnni.emplace_back(round_up(in, 32) * op);
        pack_vnni(hidden_wt_fp32(net, k).data(), in, op, op, net.wt_vnni.back().data(), 2 * op,
                  round_up(in, 32));
    }
    release_hidden_fp32(net);
    return MlpArithmetic::bf16;
}

MlpArithmetic mlp_arithmetic(const Network& net) {
    return !net.wt_int8.empty()   ? MlpArithmetic::int8
           : !net.wt_vnni.empty() ? MlpArithmetic::bf16
                                  : MlpArithmetic::fp32;
}

namespace {

// The int8 network from its fp32 input (row stride lda), by mlp_int8_in_lanes into `c` (n
// rows of 16), where the output layer is 16 wide; null where that path does not apply.
const float* mlp_int8_forward_in_lanes(const Network& net, const float* input, std::size_t lda, std::size_t n,
                                       const ZeroColumns* zeros, std::size_t outputs, float* c) {
    const std::size_t last = net.wt.size() - 1;
    if (net.out_padded[last] != 16) return nullptr;
    const Int8OutputLayer out{net.wt[last].data(), net.bias[last].data(), net.in[last],
                              outputs ? std::min<std::size_t>(outputs, net.out[last]) : net.out[last]};
    return mlp_int8_in_lanes(n, input, lda, net.wt_int8.data(), net.bias.data(), last, out, zeros, c)
               ? c
               : nullptr;
}

}  // namespace

const float* mlp_forward(const Network& net, const float* input, std::size_t n, std::vector<float>& scratch,
                         const ZeroColumns* input_zeros, std::size_t outputs) {
    const std::size_t w = net.max_width_padded;
    if (scratch.size() < 2 * n * w) scratch.resize(2 * n * w);
    const MlpArithmetic arithmetic = mlp_arithmetic(net);
    thread_local std::vector<Bf16> rows;      // bf16: the current layer's input, K padded to 32
    thread_local Int8Rows rows8[2];           // int8: the current and the next layer's input, quantized
    thread_local std::vector<float> unfused;  // int8: fp32 rows where a layer is too wide to fuse
    const float* src = input;
    std::size_t lda = net.in[0];
    const std::size_t layers = net.wt.size();
    for (std::size_t k = 0; k < layers; ++k) {
        float* dst = scratch.data() + (k % 2) * n * w;
        const bool hidden = k + 1 < layers;
        const ZeroColumns* zeros = k == 0 ? input_zeros : nullptr;
        if (hidden && arithmetic == MlpArithmetic::int8) {
            // The input is quantized once; each hidden layer but the last hands the next one
            // its output already quantized, and the last writes fp32 for the output layer.
            const Int8Layer& layer = net.wt_int8[k];
            Int8Rows &in8 = rows8[k % 2], &out8 = rows8[(k + 1) % 2];
            // Rows in lanes need a block of 16 rows to pay: with fewer, most of each
            // instruction's lanes are empty and the layer-by-layer path (the same bits) does
            // less work.
            if (k == 0 && n >= 16)
                if (const float* c =
                        mlp_int8_forward_in_lanes(net, src, lda, n, zeros, outputs, scratch.data()))
                    return c;
            if (k == 0) quantize_rows(src, n, net.in[k], lda, layer.signed_input, in8);
            if (k + 2 < layers)
                gemm_int8_relu_quantized(n, in8, layer, net.bias[k].data(), out8, unfused, zeros);
            else
                gemm_int8(n, in8, layer, net.bias[k].data(), true, dst, net.out_padded[k], zeros);
        } else if (hidden && arithmetic == MlpArithmetic::bf16) {
            const std::size_t kp = round_up(net.in[k], 32);
            if (rows.size() < n * kp) rows.resize(n * kp);
            pack_rows(src, n, net.in[k], lda, rows.data(), kp, n);
            // K stops at the inputs rounded to a pair: the padding beyond holds zeros.
            gemm_bf16_dp(n, net.out_padded[k], round_up(net.in[k], 2), rows.data(), kp, net.wt_vnni[k].data(),
                         2 * net.out_padded[k], dst, net.out_padded[k], {net.bias[k].data(), true, false},
                         zeros);
        } else if (hidden) {
            hidden_layer_fp32(net, k, src, n, lda, dst, zeros);
        } else {
            dense_output_layer(src, n, net.in[k], lda, net.wt[k].data(), net.bias[k].data(),
                               net.out_padded[k],
                               outputs ? std::min<std::size_t>(outputs, net.out[k]) : net.out[k], dst);
        }
        src = dst;
        lda = net.out_padded[k];
    }
    return src;
}

// ---- decode -------------------------------------------------------------------------------

Hit decode_output(const Geometry& geo, const RayPoints& pts, const Ray& ray, const float* o) {
    using Out = OutputLayout;
    Hit h{};
    h.hit = hit_decision(pts, o) ? 1u : 0u;
    const float dlen = std::sqrt(ray.dir[0] * ray.dir[0] + ray.dir[1] * ray.dir[1] + ray.dir[2] * ray.dir[2]);
    const float t = decode_distance(geo, pts, dlen, o[Out::distance]);
    h.t = h.hit ? std::clamp(t, pts.t_near, pts.t_far) : kInf;
    const float* n = o + Out::normal;
    const float nl = std::sqrt(n[0] * n[0] + n[1] * n[1] + n[2] * n[2]);
    for (int a = 0; a < 3; ++a) h.normal[a] = nl > 0 ? n[a] / nl : -ray.dir[a] / dlen;
    const float* logit = o + Out::material;
    h.material = 0;
    for (std::uint32_t m = 1; m < geo.material_count; ++m)
        if (logit[m] > logit[h.material]) h.material = m;
    return h;
}

// ---- the whole pass ------------------------------------------------------------------------

Runtime make_runtime(const ModelData& m, MlpArithmetic arithmetic) {
    ModelData copy = m;
    return make_runtime(std::move(copy), arithmetic);
}

namespace {

// A stored table with its tail pad (grid_tail_pad) appended, held in an allocation of
// exactly that size.
template <class T>
std::vector<T> padded_table(std::vector<T>&& stored, std::uint32_t F) {
    const std::size_t pad = grid_tail_pad(F);
    if (stored.capacity() == stored.size() + pad) {
        stored.resize(stored.size() + pad, T(0));
        return std::move(stored);
    }
    std::vector<T> out;
    out.reserve(stored.size() + pad);
    out.assign(stored.begin(), stored.end());
    out.resize(stored.size() + pad, T(0));
    std::vector<T>().swap(stored);
    return out;
}

}  // namespace

Runtime make_runtime(ModelData&& m, MlpArithmetic arithmetic) {
    Runtime rt;
    rt.geo = make_geometry(m.desc);
    rt.occupancy = OccupancyGrid(m.desc.grid_resolution, m.occupancy);
    decltype(m.occupancy)().swap(m.occupancy);
    const std::uint32_t F = m.desc.features_per_level;
    for (auto& level : m.grid) rt.grid.push_back(padded_table(std::move(level), F));
    for (auto& level : m.grid_u8) rt.grid_u8.push_back(padded_table(std::move(level), F));
    decltype(m.grid)().swap(m.grid);
    decltype(m.grid_u8)().swap(m.grid_u8);
    rt.grid_affine.swap(m.grid_affine);
    rt.net = make_network(m);
    decltype(m.weights)().swap(m.weights);
    decltype(m.biases)().swap(m.biases);
    set_mlp_arithmetic(rt.net, arithmetic);
    return rt;
}

std::vector<GridView> Runtime::grid_views() const {
    std::vector<GridView> v;
    for (const auto& g : grid) v.push_back({g.data(), geo.F, GridElement::f16});
    for (std::size_t l = 0; l < grid_u8.size(); ++l)
        v.push_back({grid_u8[l].data(), geo.F, GridElement::u8, grid_affine[l].scale, grid_affine[l].offset});
    return v;
}

std::uint64_t Runtime::heap_bytes() const {
    using detail::heap_bytes;
    std::uint64_t n = heap_bytes(geo.levels) + heap_bytes(occupancy.blocks) + heap_bytes(grid) +
                      heap_bytes(grid_u8) + heap_bytes(grid_affine);
    n += heap_bytes(net.in) + heap_bytes(net.out) + heap_bytes(net.out_padded) + heap_bytes(net.wt) +
         heap_bytes(net.wt_f16) + heap_bytes(net.bias) + heap_bytes(net.wt_vnni) + heap_bytes(net.wt_int8);
    for (const Int8Layer& l : net.wt_int8)
        n += heap_bytes(l.b) + heap_bytes(l.scale) + heap_bytes(l.w_signed) + heap_bytes(l.quad_prefix);
    return n;
}

namespace {

// Reorders `which` by decreasing pts[which[j]].count (<= H), stably (a counting sort).
void sort_by_count(const RayPoints* pts, std::span<std::uint32_t> which, std::uint32_t H) {
    thread_local std::vector<std::uint32_t> start, sorted;
    start.assign(H + 2, 0);
    for (const std::uint32_t r : which) ++start[H - pts[r].count + 1];
    for (std::uint32_t c = 1; c <= H + 1; ++c) start[c] += start[c - 1];
    sorted.resize(which.size());
    for (const std::uint32_t r : which) sorted[start[H - pts[r].count]++] = r;
    std::copy(sorted.begin(), sorted.end(), which.begin());
}

}  // namespace

namespace {

// The pass intersect() and occluded() share: walk, encode and evaluate the network on chunks
// of 256 rays. `miss(i)` is called for each ray that never reaches the network (invalid or
// culled), `finish(i, pts, row)` for each other one with its trace and output row, and
// returns whether it hit. `outputs`: the leading output columns the caller reads (0 = all).
// Rays the escape rule answers (escapes()) are misses and never reach the network. With
// `occluded_hit` (the any-hit query) and the enclosed rule on, the rays whose walk stops in
// an enclosed voxel (TraceStatus::enclosed) are passed to occluded_hit(i) instead, first.
template <class Miss, class Finish, class Hit = std::nullptr_t>
IntersectStats run_pass(const Runtime& rt, std::span<const Ray> rays, std::size_t outputs, Miss&& miss,
                        Finish&& finish, Hit&& occluded_hit = nullptr) {
    constexpr bool any_hit = !std::is_same_v<std::decay_t<Hit>, std::nullptr_t>;
    const bool stop_at_enclosed = any_hit && rt.enclosed_rule;
    constexpr std::size_t kChunk = 256;
    thread_local std::vector<RayPoints> pts;
    thread_local std::vector<TraceStatus> status;
    thread_local std::vector<float> input, scratch;
    thread_local std::vector<std::uint32_t> which, lead, rest;
    const Geometry& geo = rt.geo;
    pts.resize(kChunk);
    status.resize(kChunk);
    input.resize(kChunk * geo.input_width);
    which.resize(kChunk);
    lead.resize(kChunk);
    rest.resize(kChunk);
    const auto grid = rt.grid_views();
    const std::size_t outp = rt.net.out_padded.back();
    IntersectStats st;
    st.rays = rays.size();
    for (std::size_t base = 0; base < rays.size(); base += kChunk) {
        const std::size_t n = std::min(kChunk, rays.size() - base);
        trace_points_batch(geo, rt.occupancy, rays.subspan(base, n), pts.data(), status.data(),
                           stop_at_enclosed);
        std::size_t k = 0;
        for (std::size_t i = 0; i < n; ++i) {
            if constexpr (any_hit)
                if (status[i] == TraceStatus::enclosed) {
                    occluded_hit(base + i);
                    ++st.enclosed;
                    ++st.hits;
                    continue;
                }
            if (status[i] != TraceStatus::ok) {
                miss(base + i);
                if (status[i] == TraceStatus::invalid)
                    ++st.invalid;
                else
                    ++st.culled;
                continue;
            }
            if (escapes(geo, pts[i], rays[base + i], rt.escape_points)) {
                miss(base + i);
                ++st.escaped;
                continue;
            }
            which[k++] = std::uint32_t(i);
        }
        if (!k) continue;
        // Rows in decreasing point count, so the first layer's blocks of rows skip alike
        // runs of empty slots.
        sort_by_count(pts.data(), std::span(which.data(), k), geo.H);
        encode_batch(geo, grid.data(), pts.data(), std::span(which.data(), k), input.data());
        for (std::size_t j = 0; j < k; ++j) {
            lead[j] = pts[which[j]].count * geo.L * geo.F;
            rest[j] = pts[which[j]].count;
        }
        // Zero: the empty slots' features and, where the model has entry offsets (the last
        // inputs), the empty slots' offsets.
        const ZeroColumns empty_slots{lead.data(), geo.point_width, geo.offset_width ? rest.data() : nullptr,
                                      std::size_t(geo.point_width) + geo.direction_width};
        st.inferred += k;
        const float* out = mlp_forward(rt.net, input.data(), k, scratch, &empty_slots, outputs);
        for (std::size_t j = 0; j < k; ++j)
            st.hits += finish(base + which[j], pts[which[j]], out + j * outp) ? 1 : 0;
    }
    return st;
}

}  // namespace

void set_enclosed_rule(Runtime& rt, bool on) {
    rt.enclosed_rule = false;
    rt.occupancy.mark_enclosed(on);
    rt.enclosed_rule = on;
}

IntersectStats intersect(const Runtime& rt, std::span<const Ray> rays, std::span<Hit> hits) {
    return run_pass(
        rt, rays, 0,
        [&](std::size_t i) {
            hits[i] = Hit{kInf, {0, 0, 0}, 0, 0};
        },
        [&](std::size_t i, const RayPoints& p, const float* row) {
            hits[i] = decode_output(rt.geo, p, rays[i], row);
            return hits[i].hit != 0;
        });
}

IntersectStats occluded(const Runtime& rt, std::span<const Ray> rays, std::span<std::uint8_t> occluded) {
    return run_pass(
        rt, rays, OutputLayout::visibility + 1, [&](std::size_t i) { occluded[i] = 0; },
        [&](std::size_t i, const RayPoints& p, const float* row) {
            occluded[i] = hit_decision(p, row) ? 1 : 0;
            return occluded[i] != 0;
        },
        [&](std::size_t i) { occluded[i] = 1; });
}

}  // namespace lsnif::format
