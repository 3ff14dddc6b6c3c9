// Ray -> voxel entry points (the 3D-DDA of forward.hpp), after Amanatides & Woo, "A Fast
// Voxel Traversal Algorithm for Ray Tracing" (1987): one ray at a time, and 16 rays at a
// time with AVX-512 where the CPU has it. Both walks run the same state machine on the same
// IEEE operations, so they return bit-identical points (tests/format/test_walk.cpp); the
// model was trained on these points, so any difference would be an input the network never saw.
#include <lsnif/format/cpu.hpp>
#include <lsnif/format/forward.hpp>

#include <algorithm>
#include <bit>
#include <cmath>
#include <cstddef>
#include <limits>

#include "x86.hpp"
#if LSNIF_HAVE_X86
#include "avx512_transpose.hpp"
// GCC 12's AVX-512 intrinsics start from _mm512_undefined_*(), which its
// -W(maybe-)uninitialized reports as a use of an uninitialized value (a false positive).
#pragma GCC diagnostic ignored "-Wmaybe-uninitialized"
#pragma GCC diagnostic ignored "-Wuninitialized"
#endif

namespace lsnif::format {

namespace {
constexpr float kInf = std::numeric_limits<float>::infinity();
}

TraceStatus make_ray_grid(const Geometry& geo, const Ray& ray, RayGrid& rg, float& t_near, float& t_far) {
    for (int a = 0; a < 3; ++a)
        if (!std::isfinite(ray.org[a]) || !std::isfinite(ray.dir[a])) return TraceStatus::invalid;
    if (!normalizable(ray.dir) || std::isnan(ray.tmin) || std::isnan(ray.tmax)) return TraceStatus::invalid;
    bool moves = false;
    for (int a = 0; a < 3; ++a) {
        // Grid-space origin/direction computed in double, stored rounded once.
        const double cell = (double(geo.box_max[a]) - geo.box_min[a]) / geo.V;
        rg.go[a] = float((double(ray.org[a]) - geo.box_min[a]) / cell);
        rg.gd[a] = float(double(ray.dir[a]) / cell);
        rg.inv_gd[a] = rg.gd[a] == 0.0f ? kInf : 1.0f / rg.gd[a];
        // A subnormal gd whose reciprocal overflows would make plane_t NaN on the plane
        // through the origin: such a direction is invalid (FORMAT.md §8.2).
        if (rg.gd[a] != 0.0f && std::isinf(rg.inv_gd[a])) return TraceStatus::invalid;
        moves = moves || rg.gd[a] != 0.0f;
    }
    if (!moves) return TraceStatus::invalid;  // no step of the grid is ever reached
    t_near = ray.tmin;
    t_far = ray.tmax;
    const float V = float(geo.V);
    for (int a = 0; a < 3; ++a) {
        if (rg.gd[a] == 0.0f) {
            if (rg.go[a] < 0.0f || rg.go[a] > V) return TraceStatus::miss;
            continue;
        }
        float t0 = rg.plane_t(a, 0.0f), t1 = rg.plane_t(a, V);
        if (t0 > t1) std::swap(t0, t1);
        t_near = std::max(t_near, t0);
        t_far = std::min(t_far, t1);
    }
    if (!(t_near <= t_far)) return TraceStatus::miss;
    return TraceStatus::ok;
}

namespace {

// A walk's state: the ray in grid space, the clipped segment, the current cell, and per
// axis the parameters at which the ray enters and leaves the cell's slab.
struct WalkState {
    RayGrid rg;
    float t_near, t_far;
    int cell[3], step[3];
    float enter_a[3], exit_a[3];
};

// The walk's first cell: the one containing t_near under the half-open rule of forward.hpp,
// found from the shared plane_t so it agrees with every later step. Returns what
// make_ray_grid returns; `w` is complete only for ok.
TraceStatus start_walk(const Geometry& geo, const Ray& ray, WalkState& w) {
    RayGrid& rg = w.rg;
    const TraceStatus st = make_ray_grid(geo, ray, rg, w.t_near, w.t_far);
    if (st != TraceStatus::ok) return st;
    const int V = int(geo.V);
    for (int a = 0; a < 3; ++a) {
        const float gpos = rg.go[a] + w.t_near * rg.gd[a];  // a guess, corrected by the loops
        int& x = w.cell[a];
        if (rg.gd[a] > 0) {
            w.step[a] = 1;
            x = std::clamp(int(std::floor(gpos)), 0, V - 1);
            while (x > 0 && rg.plane_t(a, x) > w.t_near) --x;
            while (x < V - 1 && rg.plane_t(a, x + 1) <= w.t_near) ++x;
        } else if (rg.gd[a] < 0) {
            w.step[a] = -1;
            x = std::clamp(int(std::ceil(gpos)) - 1, 0, V - 1);
            while (x < V - 1 && rg.plane_t(a, x + 1) > w.t_near) ++x;
            while (x > 0 && rg.plane_t(a, x) <= w.t_near) --x;
        } else {
            w.step[a] = 0;
            x = std::clamp(int(std::floor(rg.go[a])), 0, V - 1);
        }
        // When an axis steps, its new entry plane is its old exit plane (same value); only
        // the new exit is computed.
        if (w.step[a] == 0) {
            w.enter_a[a] = -kInf;
            w.exit_a[a] = kInf;
        } else {
            w.enter_a[a] = rg.plane_t(a, float(w.step[a] > 0 ? x : x + 1));
            w.exit_a[a] = rg.plane_t(a, float(w.step[a] > 0 ? x + 1 : x));
        }
    }
    return TraceStatus::ok;
}

// Grid coordinate of the entry point on axis a: exact plane when the ray entered the cell
// through this axis's face, else the ray's position clamped into the cell. One fused
// multiply-add (std::fma, _mm512_fmadd_ps in the 16-lane walk) so every build and both
// walks round it the same way.
inline float entry_coordinate(const WalkState& w, int a, float lo) {
    if (w.step[a] != 0 && w.enter_a[a] == lo) return float(w.step[a] > 0 ? w.cell[a] : w.cell[a] + 1);
    return std::clamp(std::fma(lo, w.rg.gd[a], w.rg.go[a]), float(w.cell[a]), float(w.cell[a] + 1));
}

// Walks the crossed voxels in order, calling visit(voxel_index, entry_t, g_entry) for
// each voxel that `want(voxel_index, cell)` accepts (cell: its x, y, z) and pass(cell) for
// each other crossed voxel the walk steps into; visit and pass return false to stop early.
// Implements exactly the definition in forward.hpp. With `blocks` (OccupancyGrid), whole
// empty blocks are skipped: the walk jumps to the block's exit parameter and resumes in
// the cell the plain walk would be in at that parameter, so every accepted (occupied)
// voxel is still reported with the same entry; of a skipped block pass() sees the cell the
// walk enters it by.
// `w` is a state start_walk returned ok for; the walk consumes it.
template <class Want, class Visit, class Pass>
void walk(const Geometry& geo, WalkState& w, const OccupancyGrid* blocks, Want&& want, Visit&& visit,
          Pass&& pass) {
    const RayGrid& rg = w.rg;
    const int V = int(geo.V);
    int* cell = w.cell;
    const int* step = w.step;
    float* enter_a = w.enter_a;
    float* exit_a = w.exit_a;
    const int B = int(OccupancyGrid::kBlock);
    while (true) {
        const std::uint32_t idx =
            std::uint32_t(cell[0]) + geo.V * (std::uint32_t(cell[1]) + geo.V * std::uint32_t(cell[2]));
        const float enter = std::max(enter_a[0], std::max(enter_a[1], enter_a[2]));
        const float exit = std::min(exit_a[0], std::min(exit_a[1], exit_a[2]));
        const float lo = std::max(w.t_near, enter);
        const bool crossed = lo <= w.t_far && lo < exit;
        if (blocks &&
            !blocks->block_occupied(std::uint32_t(cell[0]), std::uint32_t(cell[1]), std::uint32_t(cell[2]))) {
            if (crossed && !pass(cell)) return;
            // Leave the empty block: its exit is the first of its boundary planes reached.
            float block_exit = kInf;
            for (int a = 0; a < 3; ++a) {
                if (step[a] == 0) continue;
                const int b0 = cell[a] / B * B;
                const int plane = step[a] > 0 ? std::min(b0 + B, V) : b0;
                block_exit = std::min(block_exit, rg.plane_t(a, float(plane)));
            }
            if (block_exit > w.t_far) return;
            // Advance each axis past every plane reached by block_exit (ties step together).
            for (int a = 0; a < 3; ++a) {
                if (step[a] == 0) continue;
                while (exit_a[a] <= block_exit) {
                    cell[a] += step[a];
                    if (cell[a] < 0 || cell[a] >= V) return;
                    enter_a[a] = exit_a[a];
                    exit_a[a] = rg.plane_t(a, float(step[a] > 0 ? cell[a] + 1 : cell[a]));
                }
            }
            continue;
        }
        if (crossed) {
            if (want(idx, cell)) {
                const float g[3] = {entry_coordinate(w, 0, lo), entry_coordinate(w, 1, lo),
                                    entry_coordinate(w, 2, lo)};
                if (!visit(idx, lo, g)) return;
            } else if (!pass(cell)) {
                return;
            }
        }
        if (exit > w.t_far) return;
        // Step every axis whose boundary is reached at `exit` (edges and corners at once).
        for (int a = 0; a < 3; ++a) {
            if (exit_a[a] != exit) continue;
            cell[a] += step[a];
            if (cell[a] < 0 || cell[a] >= V) return;
            enter_a[a] = exit_a[a];
            exit_a[a] = rg.plane_t(a, float(step[a] > 0 ? cell[a] + 1 : cell[a]));
        }
    }
}

// The walk of trace_points() into `out`; pass(cell) as in walk().
template <class Want, class Pass>
TraceStatus trace_points_impl(const Geometry& geo, const OccupancyGrid* blocks, const Ray& ray,
                              RayPoints& out, Want&& want, Pass&& pass) {
    out.count = 0;
    WalkState w;
    const TraceStatus st = start_walk(geo, ray, w);
    if (st != TraceStatus::invalid) {  // the clipped segment, also for a miss; not for an invalid ray
        out.t_near = w.t_near;
        out.t_far = w.t_far;
        unit_direction(ray, out.dir);
    }
    if (st != TraceStatus::ok) return st;
    walk(
        geo, w, blocks, want,
        [&](std::uint32_t idx, float t, const float g[3]) {
            const std::uint32_t k = out.count++;
            out.t[k] = t;
            out.g[k][0] = g[0];
            out.g[k][1] = g[1];
            out.g[k][2] = g[2];
            out.voxel[k] = idx;
            return out.count < geo.H;
        },
        pass);
    return out.count ? TraceStatus::ok : TraceStatus::miss;
}

constexpr auto kPassAll = [](const int*) { return true; };

}  // namespace

float squared_length(const float d[3]) {
    return std::fma(d[2], d[2], std::fma(d[1], d[1], d[0] * d[0]));
}

bool normalizable(const float d[3]) {
    const float s = squared_length(d);
    return s > 0.0f && s < kInf;
}

void unit_direction(const Ray& ray, float out[3]) {
    const float x = ray.dir[0], y = ray.dir[1], z = ray.dir[2];
    const float length = std::sqrt(squared_length(ray.dir));
    out[0] = x / length;
    out[1] = y / length;
    out[2] = z / length;
}

TraceStatus trace_points(const Geometry& geo, const std::uint8_t* occupancy, const Ray& ray, RayPoints& out) {
    return trace_points_impl(
        geo, nullptr, ray, out,
        [&](std::uint32_t idx, const int*) { return ((occupancy[idx >> 3] >> (idx & 7)) & 1u) != 0; },
        kPassAll);
}

TraceStatus trace_points(const Geometry& geo, const OccupancyGrid& occ, const Ray& ray, RayPoints& out,
                         bool stop_at_enclosed) {
    const auto occupied = [&](std::uint32_t, const int* cell) {
        return occ.occupied(std::uint32_t(cell[0]), std::uint32_t(cell[1]), std::uint32_t(cell[2]));
    };
    if (!stop_at_enclosed) return trace_points_impl(geo, &occ, ray, out, occupied, kPassAll);
    bool unarmed = false, stopped = false;  // crossed an enclosed voxel before any occupied one
    const TraceStatus st = trace_points_impl(geo, &occ, ray, out, occupied, [&](const int* cell) {
        if (!occ.enclosed(std::uint32_t(cell[0]), std::uint32_t(cell[1]), std::uint32_t(cell[2])))
            return true;
        unarmed |= out.count == 0;
        stopped = !unarmed;
        return unarmed;
    });
    return stopped ? TraceStatus::enclosed : st;
}

OccupancyGrid::OccupancyGrid(std::uint32_t V, const std::vector<std::uint8_t>& bits)
    : V(V), S((V + kSubBlock - 1) / kSubBlock) {
    // Whether each kBlock^3 and kSuperBlock^3 block has an occupied voxel.
    const std::uint32_t nb = (V + kBlock - 1) / kBlock, ns = (V + kSuperBlock - 1) / kSuperBlock;
    std::vector<std::uint8_t> block(std::size_t(nb) * nb * nb, 0), super(std::size_t(ns) * ns * ns, 0);
    const auto block_of = [](std::uint32_t n, std::uint32_t size, std::uint32_t x, std::uint32_t y,
                             std::uint32_t z) {
        return x / size + n * (y / size + std::size_t(n) * (z / size));
    };
    blocks.assign(std::size_t(S) * S * S + 1, 0);  // + the entry read past the last
    for (std::uint32_t z = 0; z < V; ++z)
        for (std::uint32_t y = 0; y < V; ++y)
            for (std::uint32_t x = 0; x < V; ++x) {
                const std::uint64_t i = x + std::uint64_t(V) * (y + std::uint64_t(V) * z);
                if (!((bits[i >> 3] >> (i & 7)) & 1u)) continue;
                blocks[sub_block(x, y, z)] |= std::uint16_t(1u << sub_voxel(x, y, z));
                block[block_of(nb, kBlock, x, y, z)] = 1;
                super[block_of(ns, kSuperBlock, x, y, z)] = 1;
            }
    for (std::uint32_t z = 0; z < S; ++z)
        for (std::uint32_t y = 0; y < S; ++y)
            for (std::uint32_t x = 0; x < S; ++x) {
                const std::uint32_t vx = x * kSubBlock, vy = y * kSubBlock, vz = z * kSubBlock;
                std::uint16_t& e = blocks[x + S * (y + std::size_t(S) * z)];
                e |= std::uint16_t(block[block_of(nb, kBlock, vx, vy, vz)] << kBlockBit);
                e |= std::uint16_t(super[block_of(ns, kSuperBlock, vx, vy, vz)] << kSuperBlockBit);
            }
}

std::vector<std::uint64_t> enclosed_voxels(const OccupancyGrid& occ) {
    const std::uint32_t V = occ.V;
    const std::uint64_t n = std::uint64_t(V) * V * V;
    // Flood the empty voxels from the boundary's; what stays unreached is enclosed.
    std::vector<std::uint64_t> reached((n + 63) / 64, 0), enclosed((n + 63) / 64, 0);
    std::vector<std::uint32_t> todo;
    const auto reach = [&](std::uint32_t x, std::uint32_t y, std::uint32_t z) {
        const std::uint32_t i = x + V * (y + V * z);
        if (voxel_bit(reached.data(), i) || occ.occupied(x, y, z)) return;
        set_voxel_bit(reached.data(), i);
        todo.push_back(i);
    };
    for (std::uint32_t z = 0; z < V; ++z)
        for (std::uint32_t y = 0; y < V; ++y)
            for (std::uint32_t x = 0; x < V; ++x)
                if (x == 0 || y == 0 || z == 0 || x == V - 1 || y == V - 1 || z == V - 1) reach(x, y, z);
    while (!todo.empty()) {
        const std::uint32_t i = todo.back();
        todo.pop_back();
        const std::uint32_t x = i % V, y = i / V % V, z = i / V / V;
        if (x > 0) reach(x - 1, y, z);
        if (x + 1 < V) reach(x + 1, y, z);
        if (y > 0) reach(x, y - 1, z);
        if (y + 1 < V) reach(x, y + 1, z);
        if (z > 0) reach(x, y, z - 1);
        if (z + 1 < V) reach(x, y, z + 1);
    }
    for (std::uint32_t z = 0; z < V; ++z)
        for (std::uint32_t y = 0; y < V; ++y)
            for (std::uint32_t x = 0; x < V; ++x) {
                const std::uint32_t i = x + V * (y + V * z);
                if (!occ.occupied(x, y, z) && !voxel_bit(reached.data(), i))
                    set_voxel_bit(enclosed.data(), i);
            }
    return enclosed;
}

void OccupancyGrid::mark_enclosed(bool on) {
    const std::uint16_t bit = std::uint16_t(1u << kEnclosedBit);
    for (std::uint16_t& e : blocks) e &= std::uint16_t(~bit);
    if (!on) return;
    // A block is marked when it has an empty voxel and no empty voxel of it is unenclosed.
    const std::vector<std::uint64_t> inside = enclosed_voxels(*this);
    std::vector<std::uint8_t> empty(blocks.size(), 0), open(blocks.size(), 0);
    for (std::uint32_t z = 0; z < V; ++z)
        for (std::uint32_t y = 0; y < V; ++y)
            for (std::uint32_t x = 0; x < V; ++x) {
                if (occupied(x, y, z)) continue;
                const std::uint32_t b = sub_block(x, y, z);
                empty[b] = 1;
                open[b] |= !voxel_bit(inside.data(), x + V * (y + V * z));
            }
    for (std::size_t b = 0; b + 1 < blocks.size(); ++b)
        if (empty[b] && !open[b]) blocks[b] |= bit;
}

std::vector<std::uint8_t> OccupancyGrid::voxel_bits() const {
    std::vector<std::uint8_t> bits((std::uint64_t(V) * V * V + 7) / 8, 0);
    for (std::uint32_t z = 0; z < V; ++z)
        for (std::uint32_t y = 0; y < V; ++y)
            for (std::uint32_t x = 0; x < V; ++x) {
                const std::uint64_t i = x + std::uint64_t(V) * (y + std::uint64_t(V) * z);
                if (occupied(x, y, z)) bits[i >> 3] |= std::uint8_t(1u << (i & 7));
            }
    return bits;
}

std::uint64_t OccupancyGrid::occupied_voxels() const {
    std::uint64_t n = 0;
    for (const std::uint16_t e : blocks) n += std::uint64_t(__builtin_popcount(e & 0xFFu));
    return n;
}

TraceStatus trace_all_voxels(const Geometry& geo, const Ray& ray, std::vector<std::uint32_t>& voxels,
                             std::vector<float>& entry_t) {
    voxels.clear();
    entry_t.clear();
    WalkState w;
    const TraceStatus st = start_walk(geo, ray, w);
    if (st != TraceStatus::ok) return st;
    walk(
        geo, w, nullptr, [](std::uint32_t, const int*) { return true; },
        [&](std::uint32_t idx, float t, const float*) {
            voxels.push_back(idx);
            entry_t.push_back(t);
            return true;
        },
        kPassAll);
    return TraceStatus::ok;
}

// ---- 16 walks at once ------------------------------------------------------------------

namespace {

#if LSNIF_HAVE_X86

#define LSNIF_AVX512 __attribute__((target("avx512f,avx512vl,avx512bw,avx512dq,fma")))

constexpr int kLanes = 16;
static_assert(OccupancyGrid::kSuperBlock == 8 && OccupancyGrid::kBlock == 4 && OccupancyGrid::kSubBlock == 2,
              "the 16-lane walk divides cells by a block's size with a shift of 3, 2 or 1");

// The state of 16 walks as structure-of-arrays, and which ray each lane walks. Held in
// registers across iterations; written back here only when lanes are refilled.
struct Lanes {
    alignas(64) float go[3][kLanes], gd[3][kLanes], inv[3][kLanes];
    alignas(64) float enter[3][kLanes], exit[3][kLanes], t_near[kLanes], t_far[kLanes];
    alignas(64) std::int32_t cell[3][kLanes], step[3][kLanes];
    alignas(64) std::uint32_t ray[kLanes];
    alignas(64) std::uint32_t count[kLanes];  // the points the lane's walk has recorded
    // Nonzero once the walk crossed an enclosed voxel before its first occupied one: the
    // enclosed rule never stops it (trace_points).
    alignas(64) std::uint32_t unarmed[kLanes];
};

// The n <= 16 rays' eight floats (org, tmin, dir, tmax) as eight vectors, field k of ray j
// in lane j of field[k] (0 past n): the rays loaded whole and transposed in registers.
LSNIF_AVX512 inline void ray_fields(const Ray* rays, int n, __m512 (&field)[8]) {
    static_assert(sizeof(Ray) == 8 * sizeof(float) && offsetof(Ray, tmin) == 12 && offsetof(Ray, dir) == 16 &&
                  offsetof(Ray, tmax) == 28);
    const float* f = reinterpret_cast<const float*>(rays);
    __m512i r[16];
    for (int j = 0; j < 16; ++j)
        r[j] = j < n ? _mm512_castsi256_si512(_mm256_loadu_si256(reinterpret_cast<const __m256i*>(f + 8 * j)))
                     : _mm512_setzero_si512();
    detail::transpose16(r);
    for (int k = 0; k < 8; ++k) field[k] = _mm512_castsi512_ps(r[k]);
}

// make_ray_grid's grid mapping, (x - box_min) / cell (shift) or x / cell, in double and
// rounded to float once.
LSNIF_AVX512 inline __m512 to_grid(__m512 x, __m512d vmin, __m512d vcell, bool shift) {
    const __m512d lo = _mm512_cvtps_pd(_mm512_castps512_ps256(x));
    const __m512d hi = _mm512_cvtps_pd(_mm256_castpd_ps(_mm512_extractf64x4_pd(_mm512_castps_pd(x), 1)));
    const __m256 l = _mm512_cvtpd_ps(_mm512_div_pd(shift ? _mm512_sub_pd(lo, vmin) : lo, vcell));
    const __m256 h = _mm512_cvtpd_ps(_mm512_div_pd(shift ? _mm512_sub_pd(hi, vmin) : hi, vcell));
    return _mm512_insertf32x8(_mm512_castps256_ps512(l), h, 1);
}

// RayGrid::plane_t for 16 lanes: (k - go) * inv.
LSNIF_AVX512 inline __m512 plane_at(__m512 go, __m512 inv, __m512i k) {
    return _mm512_mul_ps(_mm512_sub_ps(_mm512_cvtepi32_ps(k), go), inv);
}

// start_walk's cell-search loops for the lanes in m: step x by `delta` (+1 or -1, staying
// in [0, V - 1]) while plane(x + offset) compares `Cmp` against t_near.
template <int Cmp>
LSNIF_AVX512 inline __m512i move_while(__m512i x, __mmask16 m, int delta, int offset, __m512 go, __m512 inv,
                                       __m512 t_near, __m512i vV1) {
    const __m512i d = _mm512_set1_epi32(delta), off = _mm512_set1_epi32(offset);
    while (true) {
        // The lanes that may still move: x > 0 going down, x < V - 1 going up.
        const __mmask16 movable =
            delta < 0 ? _mm512_cmpgt_epi32_mask(x, _mm512_setzero_si512()) : _mm512_cmplt_epi32_mask(x, vV1);
        m &= movable & _mm512_cmp_ps_mask(plane_at(go, inv, _mm512_add_epi32(x, off)), t_near, Cmp);
        if (!m) return x;
        x = _mm512_mask_add_epi32(x, m, x, d);
    }
}

// start_walk() for up to 16 rays (rays[0..n)), lane j for ray first + j: the same
// operations lane by lane (make_ray_grid's double-precision grid mapping, its axis order
// for a miss's partial t_near / t_far, the cell search from the shared plane_t). Writes
// each ray's RayPoints count and clipped segment (not for an invalid ray) and its status:
// ok for a ray that starts a walk, until trace_batch_avx512 sees it found no point.
// Returns the lanes that start one, filled in Q. Over 80 lines on purpose: one pass over
// 16 lanes whose masks, t_near and t_far stay in registers throughout; splitting it would
// move that live vector state through calls or memory.
LSNIF_AVX512 std::uint32_t start_walks(const Geometry& geo, const Ray* rays, int n, std::uint32_t first,
                                       RayPoints* out, TraceStatus* status, Lanes& Q) {
    const __mmask16 lanes = __mmask16((1u << n) - 1);
    __m512 field[8];
    ray_fields(rays, n, field);
    __m512 org[3], dir[3];
    __mmask16 nonfinite = 0;
    for (int a = 0; a < 3; ++a) {
        org[a] = field[a];
        dir[a] = field[4 + a];
        nonfinite |=
            _mm512_fpclass_ps_mask(org[a], 0x99) | _mm512_fpclass_ps_mask(dir[a], 0x99);  // NaN, +-inf
    }
    // normalizable(): squared_length's fused multiply-adds, positive and finite.
    const __m512 squared =
        _mm512_fmadd_ps(dir[2], dir[2], _mm512_fmadd_ps(dir[1], dir[1], _mm512_mul_ps(dir[0], dir[0])));
    const __mmask16 normalizable = _mm512_cmp_ps_mask(squared, _mm512_setzero_ps(), _CMP_GT_OQ) &
                                   _mm512_cmp_ps_mask(squared, _mm512_set1_ps(kInf), _CMP_LT_OQ);
    __m512 go[3], gd[3], inv[3];
    __mmask16 moves = 0, overflow = 0;
    for (int a = 0; a < 3; ++a) {
        const double cell = (double(geo.box_max[a]) - geo.box_min[a]) / geo.V;
        const __m512d vmin = _mm512_set1_pd(double(geo.box_min[a])), vcell = _mm512_set1_pd(cell);
        go[a] = to_grid(org[a], vmin, vcell, true);
        gd[a] = to_grid(dir[a], vmin, vcell, false);
        const __mmask16 zero = _mm512_cmp_ps_mask(gd[a], _mm512_setzero_ps(), _CMP_EQ_OQ);
        inv[a] = _mm512_mask_mov_ps(_mm512_div_ps(_mm512_set1_ps(1.0f), gd[a]), zero, _mm512_set1_ps(kInf));
        moves |= __mmask16(~zero);
        overflow |= __mmask16(~zero) & _mm512_fpclass_ps_mask(inv[a], 0x18);  // +-inf
        _mm512_store_ps(Q.go[a], go[a]);
        _mm512_store_ps(Q.gd[a], gd[a]);
        _mm512_store_ps(Q.inv[a], inv[a]);
    }
    __m512 t_near = field[3], t_far = field[7];
    const __mmask16 invalid = lanes & (nonfinite | ~normalizable | ~moves | overflow |
                                       _mm512_cmp_ps_mask(t_near, t_near, _CMP_UNORD_Q) |
                                       _mm512_cmp_ps_mask(t_far, t_far, _CMP_UNORD_Q));
    __mmask16 live = lanes & ~invalid, miss = 0;
    const float V = float(geo.V);
    const __m512 vV = _mm512_set1_ps(V);
    for (int a = 0; a < 3; ++a) {
        const __mmask16 zero = _mm512_cmp_ps_mask(gd[a], _mm512_setzero_ps(), _CMP_EQ_OQ);
        const __mmask16 outside = live & zero &
                                  (_mm512_cmp_ps_mask(go[a], _mm512_setzero_ps(), _CMP_LT_OQ) |
                                   _mm512_cmp_ps_mask(go[a], vV, _CMP_GT_OQ));
        miss |= outside;
        live &= ~outside;
        const __mmask16 slab = live & ~zero;
        const __m512 t0 = _mm512_mul_ps(_mm512_sub_ps(_mm512_setzero_ps(), go[a]), inv[a]);
        const __m512 t1 = _mm512_mul_ps(_mm512_sub_ps(vV, go[a]), inv[a]);
        const __mmask16 swap = _mm512_cmp_ps_mask(t0, t1, _CMP_GT_OQ);
        const __m512 lo = _mm512_mask_mov_ps(t0, swap, t1), hi = _mm512_mask_mov_ps(t1, swap, t0);
        t_near = _mm512_mask_max_ps(t_near, slab, lo, t_near);  // std::max(t_near, lo)
        t_far = _mm512_mask_min_ps(t_far, slab, hi, t_far);     // std::min(t_far, hi)
    }
    const __mmask16 empty = live & ~_mm512_cmp_ps_mask(t_near, t_far, _CMP_LE_OQ);
    miss |= empty;
    live &= ~empty;
    alignas(64) float tn[kLanes], tf[kLanes];
    _mm512_store_ps(tn, t_near);
    _mm512_store_ps(tf, t_far);
    _mm512_store_ps(Q.t_near, t_near);
    _mm512_store_ps(Q.t_far, t_far);
    for (int j = 0; j < n; ++j) {
        RayPoints& p = out[j];
        p.count = 0;
        if (invalid & (1u << j)) {
            status[j] = TraceStatus::invalid;
            continue;
        }
        p.t_near = tn[j];
        p.t_far = tf[j];
        unit_direction(rays[j], p.dir);
        status[j] = (miss & (1u << j)) ? TraceStatus::miss : TraceStatus::ok;
        Q.ray[j] = first + std::uint32_t(j);
        Q.count[j] = 0;
        Q.unarmed[j] = 0;
    }
    if (!live) return 0;
    // The first cell: the largest x whose entry plane is at or before t_near (forward), the
    // smallest whose exit plane is (backward); the guess from floor/ceil is corrected by
    // the same comparisons as start_walk's loops, so the guess's rounding does not matter.
    const __m512i vV1 = _mm512_set1_epi32(int(geo.V) - 1), one = _mm512_set1_epi32(1),
                  zero_i = _mm512_setzero_si512();
    for (int a = 0; a < 3; ++a) {
        const __m512 go = _mm512_load_ps(Q.go[a]), gd = _mm512_load_ps(Q.gd[a]),
                     inv = _mm512_load_ps(Q.inv[a]);
        const __mmask16 fwd = live & _mm512_cmp_ps_mask(gd, _mm512_setzero_ps(), _CMP_GT_OQ);
        const __mmask16 bwd = live & _mm512_cmp_ps_mask(gd, _mm512_setzero_ps(), _CMP_LT_OQ);
        const __mmask16 still = live & ~fwd & ~bwd;
        const __m512 gpos = _mm512_add_ps(go, _mm512_mul_ps(t_near, gd));
        __m512i x =
            _mm512_cvttps_epi32(_mm512_roundscale_ps(gpos, _MM_FROUND_TO_NEG_INF | _MM_FROUND_NO_EXC));
        x = _mm512_mask_sub_epi32(
            x, bwd,
            _mm512_cvttps_epi32(_mm512_roundscale_ps(gpos, _MM_FROUND_TO_POS_INF | _MM_FROUND_NO_EXC)), one);
        x = _mm512_mask_mov_epi32(
            x, still,
            _mm512_cvttps_epi32(_mm512_roundscale_ps(go, _MM_FROUND_TO_NEG_INF | _MM_FROUND_NO_EXC)));
        x = _mm512_min_epi32(_mm512_max_epi32(x, zero_i), vV1);
        // forward: down while plane(x) > t_near, then up while plane(x + 1) <= t_near;
        // backward: up while plane(x + 1) > t_near, then down while plane(x) <= t_near.
        x = move_while<_CMP_GT_OQ>(x, fwd, -1, 0, go, inv, t_near, vV1);
        x = move_while<_CMP_LE_OQ>(x, fwd, +1, 1, go, inv, t_near, vV1);
        x = move_while<_CMP_GT_OQ>(x, bwd, +1, 1, go, inv, t_near, vV1);
        x = move_while<_CMP_LE_OQ>(x, bwd, -1, 0, go, inv, t_near, vV1);
        const __m512i x1 = _mm512_add_epi32(x, one);
        const __m512i step =
            _mm512_mask_mov_epi32(_mm512_mask_mov_epi32(zero_i, fwd, one), bwd, _mm512_set1_epi32(-1));
        const __m512 enter = _mm512_mask_mov_ps(
            _mm512_mask_mov_ps(_mm512_set1_ps(-kInf), fwd, plane_at(go, inv, x)), bwd, plane_at(go, inv, x1));
        const __m512 exit = _mm512_mask_mov_ps(
            _mm512_mask_mov_ps(_mm512_set1_ps(kInf), fwd, plane_at(go, inv, x1)), bwd, plane_at(go, inv, x));
        _mm512_store_si512(Q.cell[a], x);
        _mm512_store_si512(Q.step[a], step);
        _mm512_store_ps(Q.enter[a], enter);
        _mm512_store_ps(Q.exit[a], exit);
    }
    return live;
}

// The `count` lowest set bits of m.
inline std::uint32_t lowest_bits(std::uint32_t m, int count) {
    std::uint32_t r = 0;
    for (int i = 0; i < count; ++i) {
        r |= m & (0u - m);
        m &= m - 1;
    }
    return r;
}

// The lanes `to` of L take the walks in the lanes `from` of Q, in order (the i-th lowest of
// `from` into the i-th lowest of `to`; as many of each): one masked permutation per field,
// 16 lanes at a time, instead of a scalar copy of 23 fields per lane.
LSNIF_AVX512 inline void move_lanes(Lanes& L, __mmask16 to, const Lanes& Q, __mmask16 from) {
    // Each lane of `to` reads the lane of `from` of the same rank, for every field.
    const __m512i iota = _mm512_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15);
    const __m512i source = _mm512_maskz_expand_epi32(to, _mm512_maskz_compress_epi32(from, iota));
    const auto move = [&](void* dst, const void* src) LSNIF_AVX512 {
        _mm512_storeu_si512(
            dst, _mm512_mask_permutexvar_epi32(_mm512_loadu_si512(dst), to, source, _mm512_loadu_si512(src)));
    };
    for (int a = 0; a < 3; ++a) {
        move(L.go[a], Q.go[a]);
        move(L.gd[a], Q.gd[a]);
        move(L.inv[a], Q.inv[a]);
        move(L.enter[a], Q.enter[a]);
        move(L.exit[a], Q.exit[a]);
        move(L.cell[a], Q.cell[a]);
        move(L.step[a], Q.step[a]);
    }
    move(L.t_near, Q.t_near);
    move(L.t_far, Q.t_far);
    move(L.ray, Q.ray);
    move(L.count, Q.count);
    move(L.unarmed, Q.unarmed);
}

// Walks started 16 rays at a time (start_walks), handed to lanes as they free up.
struct StartQueue {
    Lanes started;
    std::uint32_t ready = 0;  // lanes of `started` not yet handed out
};

// Puts started walks into the free lanes of L (not in `live`), the lowest free lane taking
// the lowest started walk, starting rays[next..] 16 at a time as the queue runs dry, until
// every lane is busy or the rays run out. Returns the new live mask.
LSNIF_AVX512 std::uint32_t refill(const Geometry& geo, std::span<const Ray> rays, std::size_t& next,
                                  RayPoints* out, TraceStatus* status, StartQueue& q, Lanes& L,
                                  std::uint32_t live) {
    std::uint32_t free = ~live & ((1u << kLanes) - 1u);
    while (free) {
        if (!q.ready) {
            if (next >= rays.size()) break;
            const int n = int(std::min<std::size_t>(kLanes, rays.size() - next));
            q.ready = start_walks(geo, rays.data() + next, n, std::uint32_t(next), out + next, status + next,
                                  q.started);
            next += std::size_t(n);
            continue;
        }
        const int count = std::min(std::popcount(free), std::popcount(q.ready));
        const std::uint32_t to = lowest_bits(free, count), from = lowest_bits(q.ready, count);
        move_lanes(L, __mmask16(to), q.started, __mmask16(from));
        q.ready &= ~from;
        free &= ~to;
        live |= to;
    }
    return live;
}

// One axis of the 16 walks in registers.
struct Axis {
    __m512 go, gd, inv, enter, exit;
    __m512i cell, step;
    __mmask16 moves, forward;  // step != 0, step > 0
};

LSNIF_AVX512 inline __m512 plane_t(const Axis& x, __m512i k) {
    return plane_at(x.go, x.inv, k);
}

// The plane the walk leaves cell k through (k + 1 forward, k backward), as in the scalar
// walk's exit_a update.
LSNIF_AVX512 inline __m512i exit_plane(const Axis& x, __m512i k) {
    return _mm512_mask_add_epi32(k, x.forward, k, _mm512_set1_epi32(1));
}

// x + n * (y + n * z) per lane, for coordinates in [0, n): with shifts where n = 2^log2n
// (log2n >= 0), one cycle each where a 16-lane multiplication takes up to ten on some
// cores, on the walk's critical path; else with multiplications.
LSNIF_AVX512 inline __m512i linear_index(__m512i x, __m512i y, __m512i z, __m512i n, int log2n) {
    if (log2n >= 0) {
        const __m128i s = _mm_cvtsi32_si128(log2n);
        return _mm512_add_epi32(x, _mm512_sll_epi32(_mm512_add_epi32(y, _mm512_sll_epi32(z, s)), s));
    }
    return _mm512_add_epi32(x, _mm512_mullo_epi32(n, _mm512_add_epi32(y, _mm512_mullo_epi32(n, z))));
}

// Linear voxel index x + V * (y + V * z) of each lane's cell.
LSNIF_AVX512 inline __m512i voxel_index(const Axis (&ax)[3], __m512i vV, int log2V) {
    return linear_index(ax[0].cell, ax[1].cell, ax[2].cell, vV, log2V);
}

// Entry points recorded by the 16-lane walk, in the order recorded, before they reach their
// rays' RayPoints: appending the lanes' points with vector compressions costs no branch on
// how many lanes record, which writing each lane's point to its own ray would.
struct Recorded {
    static constexpr std::size_t kCapacity = 1024;
    alignas(64) float t[kCapacity + kLanes], g[3][kCapacity + kLanes];
    alignas(64) std::uint32_t voxel[kCapacity + kLanes], ray[kCapacity + kLanes], slot[kCapacity + kLanes];
    std::size_t n = 0;
};

// Writes the recorded points to slot `slot` of their rays' RayPoints, whose count becomes
// slot + 1 (a ray's points are recorded in slot order), and empties `r`.
void flush(Recorded& r, RayPoints* out) {
    for (std::size_t e = 0; e < r.n; ++e) {
        RayPoints& p = out[r.ray[e]];
        const std::uint32_t k = r.slot[e];
        p.t[k] = r.t[e];
        p.g[k][0] = r.g[0][e];
        p.g[k][1] = r.g[1][e];
        p.g[k][2] = r.g[2][e];
        p.voxel[k] = r.voxel[e];
        p.count = k + 1;
    }
    r.n = 0;
}

// The scalar walk's visit of an occupied voxel for the lanes in `occupied` (their cell is
// an occupied voxel): record the entry point where the ray crosses the cell inside its
// segment (lo <= t_far, lo < exit) in slot `count` of the lane's ray (`ray`), appended to
// `r`, which has room for 16 more. Sets `crossed` to the lanes of `live` whose ray crosses
// its cell so. Returns the lanes that have recorded their H points (their walk is over).
LSNIF_AVX512 inline __mmask16 record_entries(const Axis (&ax)[3], __mmask16 live, __mmask16 occupied,
                                             __m512i idx, __m512 t_near, __m512 t_far, __m512i ray,
                                             __m512i& count, std::uint32_t H, Recorded& r,
                                             __mmask16& crossed) {
    const __m512 enter = _mm512_max_ps(_mm512_max_ps(ax[2].enter, ax[1].enter), ax[0].enter);
    const __m512 exit = _mm512_min_ps(_mm512_min_ps(ax[2].exit, ax[1].exit), ax[0].exit);
    const __m512 lo = _mm512_max_ps(enter, t_near);
    crossed = _mm512_mask_cmp_ps_mask(live, lo, t_far, _CMP_LE_OQ);
    crossed = _mm512_mask_cmp_ps_mask(crossed, lo, exit, _CMP_LT_OQ);
    const __mmask16 rec = crossed & occupied;
    const std::size_t n = r.n;
#pragma GCC unroll 3
    for (int a = 0; a < 3; ++a) {  // entry_coordinate()
        const Axis& x = ax[a];
        const __m512 cell = _mm512_cvtepi32_ps(x.cell);
        const __m512 cell1 = _mm512_cvtepi32_ps(_mm512_add_epi32(x.cell, _mm512_set1_epi32(1)));
        const __m512 pos = _mm512_fmadd_ps(lo, x.gd, x.go);
        // std::clamp(p, c, c + 1) = std::min(std::max(p, c), c + 1)
        const __m512 clamped = _mm512_min_ps(cell1, _mm512_max_ps(cell, pos));
        const __mmask16 face = _mm512_mask_cmp_ps_mask(x.moves, x.enter, lo, _CMP_EQ_OQ);
        const __m512 plane = _mm512_mask_mov_ps(cell1, x.forward, cell);
        _mm512_storeu_ps(r.g[a] + n, _mm512_maskz_compress_ps(rec, _mm512_mask_mov_ps(clamped, face, plane)));
    }
    _mm512_storeu_ps(r.t + n, _mm512_maskz_compress_ps(rec, lo));
    _mm512_storeu_si512(r.voxel + n, _mm512_maskz_compress_epi32(rec, idx));
    _mm512_storeu_si512(r.ray + n, _mm512_maskz_compress_epi32(rec, ray));
    _mm512_storeu_si512(r.slot + n, _mm512_maskz_compress_epi32(rec, count));
    r.n = n + std::size_t(std::popcount(std::uint32_t(rec)));
    count = _mm512_mask_add_epi32(count, rec, count, _mm512_set1_epi32(1));
    return _mm512_mask_cmpeq_epi32_mask(rec, count, _mm512_set1_epi32(int(H)));
}

// Moves the lanes in `m` out of the aligned box of 2^shift voxels a side around their cell
// (shift per lane, 0 for the cell itself), at the first of its boundary planes reached, as
// the scalar walk does: its step out of a voxel is the box of one cell, its jump over an
// empty block the block. Skipping an empty aligned box keeps every occupied voxel's entry,
// as for the scalar walk's blocks. Returns the lanes whose walk is over (the box's exit
// lies beyond t_far, or they left the grid). Over 80 lines on purpose: the walk's inner
// step, one pass whose per-axis vectors stay in registers; splitting it would move that
// live vector state through calls or memory.
LSNIF_AVX512 inline __mmask16 leave_box(Axis (&ax)[3], __mmask16 m, __m512i shift, __m512 t_far, __m512i vV) {
    const __m512i vB = _mm512_sllv_epi32(_mm512_set1_epi32(1), shift);
    __m512 box_exit = _mm512_set1_ps(kInf);
    __m512i plane[3];
    __m512 plane_at_t[3];
#pragma GCC unroll 3
    for (int a = 0; a < 3; ++a) {
        const Axis& x = ax[a];
        const __m512i b0 = _mm512_sllv_epi32(_mm512_srlv_epi32(x.cell, shift), shift);
        plane[a] = _mm512_mask_min_epi32(b0, x.forward, _mm512_add_epi32(b0, vB), vV);
        plane_at_t[a] = plane_t(x, plane[a]);
        box_exit = _mm512_mask_min_ps(box_exit, x.moves, plane_at_t[a], box_exit);
    }
    __mmask16 over = _mm512_mask_cmp_ps_mask(m, box_exit, t_far, _CMP_GT_OQ);
    m &= ~over;
    // The scalar walk advances each axis one cell at a time while the cell's exit plane
    // comes at or before box_exit (for the box of one cell: the axes whose exit is the
    // cell's, edges and corners stepping together): it ends in the first cell (along the
    // step) whose exit is beyond box_exit, or leaves the grid. Exits grow monotonically
    // along the step (plane_t is monotonic in k), so that cell can be found directly: a
    // guess (the cell past the plane for an axis whose plane is the box's exit, else the
    // cell holding the position at box_exit), corrected by the same comparison until it
    // holds, then the cell's planes as stepping would have left them (enter = the previous
    // cell's exit plane). The axes do not depend on each other; a lane that leaves the grid
    // on one axis is over, whatever the other axes then did.
    const __m512i zero = _mm512_setzero_si512(), one = _mm512_set1_epi32(1), minus1 = _mm512_set1_epi32(-1);
#pragma GCC unroll 3
    for (int a = 0; a < 3; ++a) {
        Axis& x = ax[a];
        // No early exit for an axis no lane moves along: which axes move differs from step to
        // step, and the branch cost more than the masked work it saved.
        const __mmask16 moving = _mm512_mask_cmp_ps_mask(m & x.moves, x.exit, box_exit, _CMP_LE_OQ);
        // The guess, kept between the current cell and one cell past the grid.
        const __m512 pos = _mm512_fmadd_ps(box_exit, x.gd, x.go);
        __m512i c = _mm512_cvt_roundps_epi32(pos, _MM_FROUND_TO_NEG_INF | _MM_FROUND_NO_EXC);
        c = _mm512_mask_max_epi32(c, x.forward, c, x.cell);
        c = _mm512_mask_min_epi32(c, x.forward, c, vV);
        c = _mm512_mask_min_epi32(c, ~x.forward, c, x.cell);
        c = _mm512_mask_max_epi32(c, ~x.forward, c, minus1);
        // The position there lies on the plane itself and rounds to either side of it: a
        // correction loop taken at random, so the guess comes from the plane instead.
        const __mmask16 defining = _mm512_mask_cmp_ps_mask(moving, plane_at_t[a], box_exit, _CMP_EQ_OQ);
        c = _mm512_mask_mov_epi32(c, defining, _mm512_mask_sub_epi32(plane[a], ~x.forward, plane[a], one));
        const auto exit_of = [&](__m512i k) LSNIF_AVX512 { return plane_t(x, exit_plane(x, k)); };
        const auto inside = [&](__m512i k) LSNIF_AVX512 {
            return __mmask16(_mm512_cmpge_epi32_mask(k, zero) & _mm512_cmplt_epi32_mask(k, vV));
        };
        // Forward while the cell (inside the grid) exits at or before box_exit...
        __m512 exit_c = exit_of(c);
        for (__mmask16 adv = moving;
             (adv = _mm512_mask_cmp_ps_mask(adv & inside(c), exit_c, box_exit, _CMP_LE_OQ));) {
            c = _mm512_mask_add_epi32(c, adv, c, x.step);
            exit_c = _mm512_mask_mov_ps(exit_c, adv, exit_of(c));
        }
        // ...and back while the cell before it (not before the current one) exits beyond it.
        // The cell before's exit plane is the cell's entry plane.
        __m512 exit_prev = exit_of(_mm512_sub_epi32(c, x.step));
        for (__mmask16 back = moving;;) {
            back = _mm512_mask_cmpneq_epi32_mask(back, c, x.cell);
            back = _mm512_mask_cmp_ps_mask(back, exit_prev, box_exit, _CMP_GT_OQ);
            if (!back) break;
            c = _mm512_mask_sub_epi32(c, back, c, x.step);
            exit_c = _mm512_mask_mov_ps(exit_c, back, exit_prev);
            exit_prev = _mm512_mask_mov_ps(exit_prev, back, exit_of(_mm512_sub_epi32(c, x.step)));
        }
        const __mmask16 left = moving & ~inside(c);
        over |= left;
        const __mmask16 moved = moving & ~left;
        x.cell = _mm512_mask_mov_epi32(x.cell, moving, c);
        x.enter = _mm512_mask_mov_ps(x.enter, moved, exit_prev);
        x.exit = _mm512_mask_mov_ps(x.exit, moved, exit_c);
    }
    return over;
}

LSNIF_AVX512 inline void load_axes(const Lanes& L, Axis (&ax)[3]) {
#pragma GCC unroll 3
    for (int a = 0; a < 3; ++a) {
        Axis& x = ax[a];
        x.go = _mm512_load_ps(L.go[a]);
        x.gd = _mm512_load_ps(L.gd[a]);
        x.inv = _mm512_load_ps(L.inv[a]);
        x.enter = _mm512_load_ps(L.enter[a]);
        x.exit = _mm512_load_ps(L.exit[a]);
        x.cell = _mm512_load_si512(L.cell[a]);
        x.step = _mm512_load_si512(L.step[a]);
        x.moves = _mm512_test_epi32_mask(x.step, x.step);
        x.forward = _mm512_cmpgt_epi32_mask(x.step, _mm512_setzero_si512());
    }
}

// Writes back what the walk changes (the rays' constants never change).
LSNIF_AVX512 inline void store_axes(const Axis (&ax)[3], Lanes& L) {
#pragma GCC unroll 3
    for (int a = 0; a < 3; ++a) {
        _mm512_store_ps(L.enter[a], ax[a].enter);
        _mm512_store_ps(L.exit[a], ax[a].exit);
        _mm512_store_si512(L.cell[a], ax[a].cell);
    }
}

// The scalar walk for 16 rays at a time, each lane computing what walk() computes:
// std::max(a, b) is _mm512_max_ps(b, a) and std::min(a, b) is _mm512_min_ps(b, a) for
// every input, NaN included (MAXPS/MINPS return their second operand unless the first
// compares greater/less), and ordered comparisons are false on NaN as in C++. Each step
// records the occupied voxels' entries, then moves every lane out of a box: the cell in an
// occupied kSubBlock^3 block, else the largest empty block around it. The scalar walk's two
// branches (voxel, empty block) are one move here, so a step costs one pass whatever mix
// of the two its lanes need. With StopAtEnclosed, a lane whose cell is an enclosed voxel
// (OccupancyGrid::enclosed) stops as trace_points says; the cell of an empty box stands for
// the whole box, as in the scalar walk.
template <bool StopAtEnclosed>
LSNIF_AVX512 void trace_batch_avx512(const Geometry& geo, const OccupancyGrid& occ, std::span<const Ray> rays,
                                     RayPoints* out, TraceStatus* status) {
    static_assert(sizeof(TraceStatus) == sizeof(std::int32_t));
    Lanes L;
    std::size_t next = 0;
    StartQueue q;
    thread_local Recorded recorded;
    recorded.n = 0;
    std::uint32_t live = refill(geo, rays, next, out, status, q, L, 0);
    const __m512i vV = _mm512_set1_epi32(int(geo.V));
    const __m512i vS = _mm512_set1_epi32(int(occ.S));
    const auto log2_of = [](std::uint32_t n) { return std::has_single_bit(n) ? std::countr_zero(n) : -1; };
    const int log2V = log2_of(geo.V), log2S = log2_of(occ.S);
    while (live) {
        Axis ax[3];
        load_axes(L, ax);
        const __m512 t_near = _mm512_load_ps(L.t_near);
        const __m512 t_far = _mm512_load_ps(L.t_far);
        const __m512i ray = _mm512_load_si512(L.ray);
        __m512i count = _mm512_load_si512(L.count);
        __mmask16 unarmed =
            _mm512_test_epi32_mask(_mm512_load_si512(L.unarmed), _mm512_load_si512(L.unarmed));
        // Lanes whose walk is over leave `live`; the walks stay in registers until a quarter
        // of the lanes are free (or no rays are left to refill them with).
        const bool draining = next == rays.size() && !q.ready;
        do {
            if (recorded.n + kLanes > Recorded::kCapacity) flush(recorded, out);
            // One gather reads the voxel's kSubBlock^3 block entry (OccupancyGrid::blocks, in
            // the low 16 bits): its voxels, and whether its larger blocks are occupied.
            const __m512i idx = voxel_index(ax, vV, log2V);
            const __m512i one = _mm512_set1_epi32(1);
            const __m512i sub =
                linear_index(_mm512_srli_epi32(ax[0].cell, 1), _mm512_srli_epi32(ax[1].cell, 1),
                             _mm512_srli_epi32(ax[2].cell, 1), vS, log2S);
            const __m512i word =
                _mm512_mask_i32gather_epi32(_mm512_setzero_si512(), __mmask16(live), sub,
                                            reinterpret_cast<const int*>(occ.blocks.data()), 2);
            const __m512i in_sub =
                _mm512_add_epi32(_mm512_and_si512(ax[0].cell, one),
                                 _mm512_add_epi32(_mm512_slli_epi32(_mm512_and_si512(ax[1].cell, one), 1),
                                                  _mm512_slli_epi32(_mm512_and_si512(ax[2].cell, one), 2)));
            const __mmask16 voxel_occupied = _mm512_test_epi32_mask(_mm512_srlv_epi32(word, in_sub), one),
                            sub_occupied = _mm512_test_epi32_mask(word, _mm512_set1_epi32(0xFF)),
                            block_occupied = _mm512_test_epi32_mask(
                                word, _mm512_set1_epi32(1 << OccupancyGrid::kBlockBit)),
                            super_occupied = _mm512_test_epi32_mask(
                                word, _mm512_set1_epi32(1 << OccupancyGrid::kSuperBlockBit));
            const __mmask16 occupied = __mmask16(live) & voxel_occupied;
            __mmask16 crossed;
            __mmask16 over = record_entries(ax, __mmask16(live), occupied, idx, t_near, t_far, ray, count,
                                            geo.H, recorded, crossed);
            if constexpr (StopAtEnclosed) {
                const __mmask16 enclosed =
                    crossed & ~voxel_occupied &
                    _mm512_test_epi32_mask(word, _mm512_set1_epi32(1 << OccupancyGrid::kEnclosedBit));
                unarmed |= enclosed & ~_mm512_test_epi32_mask(count, count);
                const __mmask16 stop = enclosed & ~unarmed;
                if (stop) {
                    _mm512_mask_i32scatter_epi32(status, stop, ray,
                                                 _mm512_set1_epi32(int(TraceStatus::enclosed)), 4);
                    over |= stop;
                }
            }
            // The box to leave: the cell in an occupied 2^3 block, else the largest empty
            // block, 8^3 (shift 3), 4^3 (2) or 2^3 (1).
            const __m512i shift = _mm512_mask_mov_epi32(
                _mm512_mask_mov_epi32(
                    _mm512_mask_blend_epi32(super_occupied, _mm512_set1_epi32(3), _mm512_set1_epi32(2)),
                    block_occupied, _mm512_set1_epi32(1)),
                sub_occupied, _mm512_setzero_si512());
            over |= leave_box(ax, __mmask16(live) & ~over, shift, t_far, vV);
            live &= ~std::uint32_t(over);
        } while (live && (draining || std::popcount(live) > kLanes * 3 / 4));
        store_axes(ax, L);
        _mm512_store_si512(L.count, count);
        _mm512_store_si512(L.unarmed, _mm512_maskz_set1_epi32(unarmed, 1));
        live = refill(geo, rays, next, out, status, q, L, live);
    }
    flush(recorded, out);
    // A walk without a point is a miss; set once here rather than per finished lane inside
    // the loop, where a data-dependent branch per step cost more than this pass.
    for (std::size_t i = 0; i < rays.size(); ++i)
        if (status[i] == TraceStatus::ok && out[i].count == 0) status[i] = TraceStatus::miss;
}

#undef LSNIF_AVX512

#endif

}  // namespace

void trace_points_batch(const Geometry& geo, const OccupancyGrid& occ, std::span<const Ray> rays,
                        RayPoints* out, TraceStatus* status, bool stop_at_enclosed) {
#if LSNIF_HAVE_X86
    // A lone ray walks alone: the 16-lane step costs as much for one busy lane as for
    // sixteen, and is slower than the scalar step (a renderer's single-ray calls, the Embree
    // user geometry's 1-ray callbacks). From two rays on the lanes pay.
    if (cpu_features().avx512 && geo.V == occ.V && rays.size() >= 2)
        return stop_at_enclosed ? trace_batch_avx512<true>(geo, occ, rays, out, status)
                                : trace_batch_avx512<false>(geo, occ, rays, out, status);
#endif
    for (std::size_t i = 0; i < rays.size(); ++i)
        status[i] = trace_points(geo, occ, rays[i], out[i], stop_at_enclosed);
}

}  // namespace lsnif::format
