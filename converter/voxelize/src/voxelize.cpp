// Conservative triangle voxelizer (contract in <lsnif/voxelize/voxelize.hpp>).
//
// ---- Why rounding can only add voxels ---------------------------------------------------
//
// Notation: eps = 2^-53 (unit roundoff of IEEE double), V the resolution, "cell" the closed
// unit cube [x, x+1] × [y, y+1] × [z, z+1] in grid coordinates.
//
// 1. Grid coordinates. A vertex p maps to g = (p - box_min) * V / (box_max - box_min),
//    an exact affine map under which voxel (x, y, z) becomes the unit cell above. We compute
//    g' = fl(fl(p - min) * fl(V / fl(max - min))): four roundings, so
//    |g' - g| <= 4.01 eps |g| <= 5 eps S per coordinate, where S = max(V, M_T) + 1 and
//    M_T = max |g'| over the triangle's vertices (no underflow: p - min is a difference of
//    floats and the scale is >= 2^-130, so every nonzero product is a normal double).
//    If the true triangle T meets a cell C, the computed triangle T' meets C grown by
//    delta = 5 eps S: a point q = sum l_i g_i of T ∩ C has q' = sum l_i g'_i in T' with
//    |q' - q|_inf <= max_i |g'_i - g_i|_inf (barycentric weights sum to 1).
//
// 2. Slack. Each triangle is tested against cells of half-size h = 1/2 + tau, with
//    tau = 2^-40 S = 2^13 eps S, i.e. ~1600 times delta. The rest of tau absorbs the
//    rounding of the test itself, item 3.
//
// 3. The separating-axis test (Akenine-Möller 2001). For a direction a, triangle and cell
//    are disjoint if the projections a·g'_i all lie above a·c + h |a|_1 or all below
//    a·c - h |a|_1 (c = cell centre; h |a|_1 is the cell's projected radius). The SAT
//    is valid for ANY direction, so it does not matter that the axes we use (the normal
//    e0 × e1 and the nine e_j × unit_k, built from rounded edges e_j = fl(g'_{j+1} - g'_j))
//    are themselves rounded: only the evaluation of the projections must not err toward
//    "separated". With A = |a|_1 the computed projections and centre projection are off
//    by at most gamma_3 A S each (gamma_n = n eps / (1 - n eps), Higham, Accuracy and
//    Stability of Numerical Algorithms, §3.1), the computed radius by 4 eps h A and each
//    final comparison by a few eps A S more: in total well below (tau - delta) A. So
//    whenever the exact test says "not separated" for T' and the cell grown by delta, the
//    computed test says "not separated" too. Directions with A < 2^-900 are skipped
//    (never separate), so underflow (absolute error <= 2^-1074 per operation, vs. a slack
//    >= 2^-940) cannot break the bound. No overflow either: |g'| < 2^287 (float range over
//    the smallest float box extent, times V), so products stay below 2^900.
//
//    The three box axes are applied through the voxel range: voxel x is visited iff its
//    cell [x, x+1] meets [fl(lo - tau), fl(hi + tau)], lo/hi the triangle's extent.
//
// 4. Consequently no overlapping voxel is ever missed, and since the 13 axes decide
//    triangle-box overlap exactly (also for segments and points: the edge × axis
//    directions and the box axes cover them), a marked voxel is one whose cell, grown by
//    tau + O(eps S) < 2 tau, meets the true triangle.
//
// Nothing here may be built with value-changing floating-point optimizations.
#include <lsnif/voxelize/voxelize.hpp>

#include <algorithm>
#include <atomic>
#include <bit>
#include <cmath>
#include <cstring>
#include <limits>
#include <lsnif/base/parallel.hpp>
#include <new>
#include <optional>
#include <string>
#include <vector>

#if defined(__FAST_MATH__)
#error "the voxelizer's conservativeness proof needs IEEE double arithmetic: do not use -ffast-math"
#endif

namespace lsnif::voxelize {
namespace {

constexpr double kTinyAxis = 0x1p-900;        // |a|_1 below this: the axis is skipped
constexpr double kHintWiden = 0x1p-30;        // row-interval hint widening, relative to S
constexpr std::size_t kChunk = 8192;          // triangles per scheduling unit
constexpr std::size_t kFloatChunk = 1 << 16;  // positions per validation unit
constexpr unsigned kMaxThreads = 256;
constexpr std::size_t kPrefetch = 16;  // triangles ahead whose vertices are prefetched

// Object space -> grid coordinates (item 1 above).
struct GridMap {
    double origin[3];
    double scale[3];
    double vd;          // V as double
    double tau_inside;  // tau_T of any triangle inside the grid: 2^-40 (V + 1)
    std::uint32_t v;
};

inline void set_bit(std::uint64_t* words, std::size_t i) {
    words[i >> 6] |= std::uint64_t{1} << (i & 63);
}

inline std::size_t voxel_index(std::uint32_t v, int x, int y, int z) {
    return std::size_t(x) + std::size_t(v) * (std::size_t(y) + std::size_t(v) * std::size_t(z));
}

// One separating direction a, pre-evaluated for a triangle: the centre c of a cell passes
// (is not separated) iff lo <= a·c <= hi, where lo = min_i a·g_i - h|a|_1, hi = max + h|a|_1.
struct Axis {
    double a[3];
    double lo, hi;
};

// General path: the triangle spans several voxels along at least two axes. Visits the voxels
// of [f, l] (inclusive, clamped to the grid) and applies the normal and edge axes.
// `tau` and `s` as in the file comment.
//
// flat_axis = c >= 0 means the (grown) triangle lies within one voxel slab along axis c.
// Then it meets a cell of that slab iff its projection along c meets the cell's square, a
// 2D triangle-square problem whose separating axes are the square's (the voxel range) and
// the three edge normals, i.e. e_j × unit_c: those three axes suffice (fewer axes can only
// reject less, so the no-miss guarantee is untouched, and the 2D test is exact).
// Over 80 lines on purpose: the voxelizer's hot path; the per-cell loop reads the axes
// built above it (axes[], n) in the same frame, with no call or copy in between.
[[gnu::noinline]] void mark_by_sat(const double (&g)[3][3], double tau, double s, const int (&f)[3],
                                   const int (&l)[3], int flat_axis, std::uint32_t v, std::uint64_t* words) {
    const double h = 0.5 + tau;
    double e[3][3];
    for (int j = 0; j < 3; ++j)
        for (int k = 0; k < 3; ++k) e[j][k] = g[(j + 1) % 3][k] - g[j][k];

    Axis axes[10];
    int n = 0;
    auto add = [&](double ax, double ay, double az) {
        const double a1 = std::fabs(ax) + std::fabs(ay) + std::fabs(az);
        if (!(a1 >= kTinyAxis)) return false;  // zero (degenerate) or tiny: never separates
        const double p0 = ax * g[0][0] + ay * g[0][1] + az * g[0][2];
        const double p1 = ax * g[1][0] + ay * g[1][1] + az * g[1][2];
        const double p2 = ax * g[2][0] + ay * g[2][1] + az * g[2][2];
        const double r = h * a1;
        axes[n++] = Axis{{ax, ay, az}, std::min({p0, p1, p2}) - r, std::max({p0, p1, p2}) + r};
        return true;
    };
    // Triangle normal first: for large triangles it rejects the most cells.
    const double nx = e[0][1] * e[1][2] - e[0][2] * e[1][1];
    const double ny = e[0][2] * e[1][0] - e[0][0] * e[1][2];
    const double nz = e[0][0] * e[1][1] - e[0][1] * e[1][0];
    const bool have_normal = flat_axis < 0 && add(nx, ny, nz);
    for (int j = 0; j < 3; ++j) {
        if (flat_axis < 0 || flat_axis == 0) add(0.0, e[j][2], -e[j][1]);  // e_j × (1,0,0)
        if (flat_axis < 0 || flat_axis == 1) add(-e[j][2], 0.0, e[j][0]);  // e_j × (0,1,0)
        if (flat_axis < 0 || flat_axis == 2) add(e[j][1], -e[j][0], 0.0);  // e_j × (0,0,1)
    }

    // Inner loop along the normal's dominant axis w, so that the normal test can bound the
    // run of candidate cells in each row (a hint, widened far beyond its rounding error;
    // every visited cell still gets the full test).
    int w = 0;
    if (have_normal) {
        const double an[3] = {std::fabs(nx), std::fabs(ny), std::fabs(nz)};
        w = an[0] >= an[1] ? (an[0] >= an[2] ? 0 : 2) : (an[1] >= an[2] ? 1 : 2);
    }
    const int u = (w + 1) % 3, t = (w + 2) % 3;
    const double widen = 2.0 + kHintWiden * s;
    int c[3];
    for (c[t] = f[t]; c[t] <= l[t]; ++c[t]) {
        for (c[u] = f[u]; c[u] <= l[u]; ++c[u]) {
            const double cu = c[u] + 0.5, ct = c[t] + 0.5;
            double part[10];
            for (int m = 0; m < n; ++m) part[m] = axes[m].a[u] * cu + axes[m].a[t] * ct;
            double k0 = f[w], k1 = l[w];
            if (have_normal) {
                // |a_w| >= |a|_1 / 3 > 0, so the quotients are finite or +-inf, never NaN.
                const double aw = axes[0].a[w];
                double t0 = (axes[0].lo - part[0]) / aw, t1 = (axes[0].hi - part[0]) / aw;
                if (aw < 0) std::swap(t0, t1);
                k0 = std::max(k0, std::floor(t0 - 0.5 - widen));
                k1 = std::min(k1, std::ceil(t1 - 0.5 + widen));
            }
            if (!(k0 <= k1)) continue;
            for (c[w] = int(k0); c[w] <= int(k1); ++c[w]) {
                const double cw = c[w] + 0.5;
                bool separated = false;
                for (int m = 0; m < n; ++m) {
                    const double q = part[m] + axes[m].a[w] * cw;
                    if (q < axes[m].lo || q > axes[m].hi) {
                        separated = true;
                        break;
                    }
                }
                if (!separated) set_bit(words, voxel_index(v, c[0], c[1], c[2]));
            }
        }
    }
}

// Marks every voxel triangle g may overlap, given its extent [lo, hi] per axis (grid
// coordinates), S and tau (file comment).
[[gnu::noinline]] void mark_general(const double (&g)[3][3], const double (&lo)[3], const double (&hi)[3],
                                    double s, double tau, const GridMap& map, std::uint64_t* words) {
    // Non-finite coordinates only reach here from a mesh that voxelize() will reject; drop
    // the triangle before any float-to-int conversion could see them.
    double sum = 0.0;
    for (const auto& p : g) sum += p[0] + p[1] + p[2];  // |g| < 2^287: no overflow
    if (!std::isfinite(sum)) return;
    const double vd = map.vd;
    // Voxel x touches [lo - tau, hi + tau] iff ceil(lo - tau) - 1 <= x <= floor(hi + tau).
    double first[3], last[3];
    int multi = 0, flat_axis = -1;
    for (int a = 0; a < 3; ++a) {
        first[a] = std::ceil(lo[a] - tau) - 1.0;
        last[a] = std::floor(hi[a] + tau);
        if (last[a] < 0.0 || first[a] > vd - 1.0) return;  // wholly outside the grid
        if (first[a] != last[a])
            ++multi;
        else
            flat_axis = a;  // one voxel slab along a (unclamped, so the whole triangle)
    }
    int f[3], l[3];
    for (int a = 0; a < 3; ++a) {
        f[a] = int(std::max(first[a], 0.0));
        l[a] = int(std::min(last[a], vd - 1.0));
    }
    if (multi <= 1) {
        // The (grown) triangle lies inside one voxel slab along two axes; being connected,
        // its projection on the third axis covers [lo, hi], so it meets every voxel of the
        // range: no SAT needed.
        for (int z = f[2]; z <= l[2]; ++z)
            for (int y = f[1]; y <= l[1]; ++y)
                for (int x = f[0]; x <= l[0]; ++x) set_bit(words, voxel_index(map.v, x, y, z));
        return;
    }
    mark_by_sat(g, tau, s, f, l, multi == 2 ? flat_axis : -1, map.v, words);
}

// Marks every voxel triangle g (grid coordinates) may overlap; see the file comment.
inline void mark_triangle(const double (&g)[3][3], const GridMap& map, std::uint64_t* words) {
    const double vd = map.vd;
    double lo[3], hi[3];
    for (int a = 0; a < 3; ++a) {
        lo[a] = std::min(std::min(g[0][a], g[1][a]), g[2][a]);
        hi[a] = std::max(std::max(g[0][a], g[1][a]), g[2][a]);
    }
    // Fast path, the common case for triangles small against a voxel: on every axis the
    // range [lo - tau, hi + tau] lies inside the grid, its lower end is not an integer, and
    // it spans one voxel, or two along at most one axis. Then the touched voxels are k0 and
    // k1 (k = floor of the range ends), exactly what mark_general would mark, but without
    // floor/ceil and with a single, well-predicted branch. Inside the grid M_T <= V, so
    // tau = 2^-40 (V + 1) (map.tau_inside); the checks below establish that premise.
    const double tau = map.tau_inside;
    int k0[3], k1[3];
    bool simple = true;
    int spans = 0;
    for (int a = 0; a < 3; ++a) {
        const double a0 = lo[a] - tau, a1 = hi[a] + tau;
        // Clamped first (NaN -> 0: std::max returns its first argument when unordered), so
        // that the conversions are always defined.
        k0[a] = int(std::min(vd, std::max(0.0, a0)));
        k1[a] = int(std::min(vd, std::max(0.0, a1)));
        simple &= (double(k0[a]) < a0) & (a1 < vd);  // 0 < a0 (not an integer), a1 < V
        spans += k1[a] - k0[a];
    }
    if (simple & (spans <= 1)) {
        set_bit(words, voxel_index(map.v, k0[0], k0[1], k0[2]));
        set_bit(words, voxel_index(map.v, k1[0], k1[1], k1[2]));
        return;
    }
    double mag = vd;
    for (int a = 0; a < 3; ++a) mag = std::max(mag, std::max(-lo[a], hi[a]));
    const double s = mag + 1.0;
    mark_general(g, lo, hi, s, kSlackFactor * s, map, words);
}

// Marks the triangles [begin, end). Triangles with an index out of range are skipped and
// reported through the return value (false); the caller then discards the grid.
bool mark_range(const MeshView& mesh, const GridMap& map, std::size_t begin, std::size_t end,
                std::uint64_t* words) {
    const float* pos = mesh.positions.data();
    const std::uint32_t* idx = mesh.indices.data();
    const std::size_t nv = mesh.vertex_count();
    bool ok = true;
    for (std::size_t t = begin; t < end; ++t) {
        // The vertex fetches are the main memory cost on large meshes: request those of a
        // triangle kPrefetch ahead (indices are read sequentially and need no help).
        if (t + kPrefetch < end && nv != 0) {
            for (int i = 0; i < 3; ++i)
                __builtin_prefetch(pos + 3 * std::min<std::size_t>(idx[3 * (t + kPrefetch) + i], nv - 1));
        }
        const std::size_t i0 = idx[3 * t], i1 = idx[3 * t + 1], i2 = idx[3 * t + 2];
        if ((i0 >= nv) | (i1 >= nv) | (i2 >= nv)) {
            ok = false;
            continue;
        }
        const float* p[3] = {pos + 3 * i0, pos + 3 * i1, pos + 3 * i2};
        double g[3][3];
        for (int i = 0; i < 3; ++i)
            for (int a = 0; a < 3; ++a) g[i][a] = (double(p[i][a]) - map.origin[a]) * map.scale[a];
        mark_triangle(g, map, words);
    }
    return ok;
}

// The mesh rules of mesh::check (positions and indices; normals and materials are not read).
std::optional<Error> check_mesh(const MeshView& mesh) {
    if (std::string why = mesh::check({mesh.positions, mesh.indices}); !why.empty()) return Error{why};
    return std::nullopt;
}

float round_down(double d) {
    float f = float(d);
    if (double(f) > d) f = std::nextafter(f, -std::numeric_limits<float>::infinity());
    return f;
}

float round_up(double d) {
    float f = float(d);
    if (double(f) < d) f = std::nextafter(f, std::numeric_limits<float>::infinity());
    return f;
}

Result<Occupancy> voxelize_impl(const MeshView& mesh, const Box& box, std::uint32_t v,
                                const Options& options) {
    if (v < kMinResolution || v > kMaxResolution)
        return Error{"resolution " + std::to_string(v) + " is outside [" + std::to_string(kMinResolution) +
                     ", " + std::to_string(kMaxResolution) + "]"};
    for (int a = 0; a < 3; ++a) {
        const std::string axis(1, "xyz"[a]);
        if (!std::isfinite(box.min[a]) || !std::isfinite(box.max[a]))
            return Error{"box: " + axis + " bound is not finite"};
        if (!(box.min[a] < box.max[a]))
            return Error{"box: empty on axis " + axis + " (min " + std::to_string(box.min[a]) + " >= max " +
                         std::to_string(box.max[a]) + ")"};
    }
    if (mesh.positions.size() % 3 != 0 || mesh.indices.size() % 3 != 0) return *check_mesh(mesh);

    GridMap map{};
    map.v = v;
    map.vd = double(v);
    map.tau_inside = kSlackFactor * (map.vd + 1.0);
    for (int a = 0; a < 3; ++a) {
        map.origin[a] = box.min[a];
        map.scale[a] = map.vd / (double(box.max[a]) - double(box.min[a]));
    }

    const std::size_t voxels = std::size_t(v) * v * v;
    const std::size_t words = (voxels + 63) / 64;
    const std::size_t triangles = mesh.triangle_count();
    const std::size_t chunks = (triangles + kChunk - 1) / kChunk;
    unsigned threads = base::resolve_threads(options.threads);
    threads = unsigned(std::min<std::size_t>({threads, kMaxThreads, std::max<std::size_t>(chunks, 1)}));

    // One private grid per thread, OR-ed at the end: no shared writes, and the result is
    // independent of scheduling.
    std::vector<std::vector<std::uint64_t>> grids(threads, std::vector<std::uint64_t>(words, 0));
    // Validation is fused into the parallel passes (one read of the data, not two): the
    // workers scan every position for non-finite values, then mark the triangles, skipping
    // any with an index out of range. Marking tolerates non-finite coordinates (no
    // undefined behaviour; mark_general drops such triangles), and on any problem the grid
    // is discarded and check_mesh names the first offender, deterministically.
    std::atomic<std::size_t> next_float{0}, next_triangle{0};
    std::atomic<bool> invalid{false};
    const std::size_t floats = mesh.positions.size();
    auto work = [&](unsigned id) {
        std::uint64_t* out = grids[id].data();
        bool ok = true;
        for (;;) {
            const std::size_t begin = next_float.fetch_add(kFloatChunk, std::memory_order_relaxed);
            if (begin >= floats) break;
            const float* p = mesh.positions.data();
            ok &= mesh::all_finite({p + begin, p + std::min(begin + kFloatChunk, floats)});
        }
        for (;;) {
            const std::size_t begin = next_triangle.fetch_add(kChunk, std::memory_order_relaxed);
            if (begin >= triangles) break;
            ok &= mark_range(mesh, map, begin, std::min(begin + kChunk, triangles), out);
        }
        if (!ok) invalid.store(true, std::memory_order_relaxed);
    };
    base::run_on_threads(threads, [&](std::uint32_t id) { work(id); });
    if (invalid.load()) {
        if (auto err = check_mesh(mesh)) return *err;
        return Error{"invalid mesh"};  // unreachable: the workers check a subset of check_mesh
    }
    for (unsigned id = 1; id < threads; ++id)
        for (std::size_t i = 0; i < words; ++i) grids[0][i] |= grids[id][i];

    Occupancy occ;
    occ.resolution = v;
    occ.bits.resize(Occupancy::byte_count(v));
    // Bit i of the word array is bit i & 7 of byte i >> 3 (FORMAT.md §6.3), whatever the
    // host's endianness. Bits >= V^3 were never set, so the trailing bits are 0.
    const std::uint64_t* w = grids[0].data();
    for (std::size_t j = 0; j < occ.bits.size(); ++j) occ.bits[j] = std::uint8_t(w[j >> 3] >> (8 * (j & 7)));
    return occ;
}

Result<Box> padded_box_impl(const MeshView& mesh, const BoxOptions& options) {
    if (!(options.padding >= 0.0 && options.padding <= 1.0))
        return Error{"box options: padding " + std::to_string(options.padding) + " is outside [0, 1]"};
    if (!(options.min_thickness > 0.0 && options.min_thickness <= 1.0))
        return Error{"box options: min_thickness " + std::to_string(options.min_thickness) +
                     " is outside (0, 1]"};
    if (auto err = check_mesh(mesh)) return *err;
    if (mesh.triangle_count() == 0) return Error{"mesh has no triangles"};

    std::array<float, 3> lo, hi;
    lo.fill(std::numeric_limits<float>::infinity());
    hi.fill(-std::numeric_limits<float>::infinity());
    for (std::uint32_t i : mesh.indices) {
        const float* p = mesh.positions.data() + 3 * std::size_t(i);
        for (int a = 0; a < 3; ++a) {
            lo[a] = std::min(lo[a], p[a]);
            hi[a] = std::max(hi[a], p[a]);
        }
    }
    double extent = 0.0;
    for (int a = 0; a < 3; ++a) extent = std::max(extent, double(hi[a]) - double(lo[a]));
    if (extent == 0.0) {
        double m = 1.0;
        for (int a = 0; a < 3; ++a) m = std::max(m, std::fabs(double(lo[a])));
        extent = m * 0x1p-10;
    }
    Box box;
    for (int a = 0; a < 3; ++a) {
        const double pad = options.padding * extent;
        double b0 = double(lo[a]) - pad, b1 = double(hi[a]) + pad;
        const double thick = options.min_thickness * extent;
        if (b1 - b0 < thick) {
            const double mid = 0.5 * (double(lo[a]) + double(hi[a]));
            b0 = std::min(b0, mid - 0.5 * thick);
            b1 = std::max(b1, mid + 0.5 * thick);
        }
        float f0 = round_down(b0), f1 = round_up(b1);
        // Strict containment even where the padding is below float resolution.
        if (!(f0 < lo[a])) f0 = std::nextafter(lo[a], -std::numeric_limits<float>::infinity());
        if (!(f1 > hi[a])) f1 = std::nextafter(hi[a], std::numeric_limits<float>::infinity());
        if (!std::isfinite(f0) || !std::isfinite(f1))
            return Error{std::string("box: the padded extent of axis ") + "xyz"[a] + " overflows float"};
        box.min[a] = f0;
        box.max[a] = f1;
    }
    return box;
}

}  // namespace

std::size_t Occupancy::count() const {
    std::size_t n = 0;
    for (std::uint8_t b : bits) n += std::size_t(std::popcount(b));
    return n;
}

Result<Box> padded_box(const MeshView& mesh, const BoxOptions& options) {
    try {
        return padded_box_impl(mesh, options);
    } catch (const std::bad_alloc&) {
        return Error{"out of memory"};
    }
}

Result<Occupancy> voxelize(const MeshView& mesh, const Box& box, std::uint32_t resolution,
                           const Options& options) {
    try {
        return voxelize_impl(mesh, box, resolution, options);
    } catch (const std::bad_alloc&) {
        return Error{"out of memory"};
    }
}

}  // namespace lsnif::voxelize
