// Private to lsnif::sampling: what the library's source files share. The per-ray random
// streams, the double-precision vector helpers and direction samplers used both by the ray
// families and by the inside test, the per-thread float mode, the Embree ray records and
// geometry masks, the EmbreeSource::Impl state, and the construction stages that
// EmbreeSource::create() runs in order. Hot helpers are defined inline here so that every
// file that builds or traces rays can inline them; the rest of Impl is defined in the file
// of its job (inside.cpp, families.cpp, topology.cpp, ...). Every file of the library is
// compiled with -ffp-contract=off, so inlining never changes a rounding (see CMakeLists.txt).
#pragma once

#include <lsnif/base/parallel.hpp>
#include <lsnif/base/random.hpp>
#include <lsnif/base/triangle_hit.hpp>
#include <lsnif/base/vec3.hpp>
#include <lsnif/sampling/sampling.hpp>

#include <embree3/rtcore.h>

#if defined(__SSE__) || defined(__x86_64__)
#include <pmmintrin.h>
#include <xmmintrin.h>
#define LSNIF_SAMPLING_HAS_MXCSR 1
#endif

#include <algorithm>
#include <atomic>
#include <cmath>
#include <cstddef>
#include <cstdint>
#include <mutex>
#include <string>
#include <vector>

namespace lsnif::sampling {

// ---- random numbers ---------------------------------------------------------------------

using base::mix64;  // splitmix64's output function: seeds the per-ray streams
inline constexpr std::uint64_t kGolden = base::kGoldenGamma;

// A ray's draws: wyrand (Wang Yi 2019), a Weyl sequence whose state is folded by one
// 64 x 64 -> 128-bit multiply per draw, about half the instructions of a splitmix64
// draw (a ray takes 6-8 draws, and they were a visible share of its construction); the
// author reports it passing BigCrush and PractRand. Each stream is seeded by splitmix64
// of (seed, purpose, index) below, so neighbouring rays' streams are unrelated.
__extension__ typedef unsigned __int128 U128;
struct Rng {
    std::uint64_t s;
    std::uint64_t next() {
        s += 0xA0761D6478BD642Full;
        const U128 p = U128(s) * U128(s ^ 0xE7037ED1A0B428DBull);
        return std::uint64_t(p >> 64) ^ std::uint64_t(p);
    }
    // Uniform in the open interval (0, 1): 53 random bits, centred in their cell.
    double u01() { return (double(next() >> 11) + 0.5) * (1.0 / 9007199254740992.0); }
    // Two uniforms in (0, 1) from one draw, 32 bits each (resolution 2^-32, far below
    // the float precision of anything they place): halves the generator's share.
    void u01_pair(double& a, double& b) {
        const std::uint64_t x = next();
        a = (double(x >> 32) + 0.5) * (1.0 / 4294967296.0);
        b = (double(x & 0xFFFFFFFFull) + 0.5) * (1.0 / 4294967296.0);
    }
};

// Every ray owns streams that are functions of (seed, purpose, index) only, which is what
// makes generate() independent of the thread count and the work split. stream_base()
// depends on the seed alone and is computed once per generate() call.
inline constexpr std::uint64_t kMainSalt = 0x6C736E6966ull;  // the ray's construction draws
inline constexpr std::uint64_t kVoteSalt = 0x766F746573ull;  // family (c): inside-test vote directions
inline std::uint64_t stream_base(std::uint64_t seed, std::uint64_t salt) {
    return mix64(seed ^ salt);
}
inline Rng stream(std::uint64_t base, std::uint64_t index) {
    return Rng{mix64(base + index * kGolden)};
}
inline Rng ray_rng(std::uint64_t seed, std::uint64_t index) {
    return stream(stream_base(seed, kMainSalt), index);
}

// ---- small vector helpers (double precision for sample construction) ---------------------

using V3 = base::Vec3d;  // lsnif/base/vec3.hpp: +, -, scalar *, dot, cross, length

// Uniform point (x, y) of the open unit disk, q = x^2 + y^2, by rejection from the
// square (acceptance pi/4). Two candidates per round, the first one inside wins: the
// result is distributed exactly as with one candidate at a time, but the loop branch is
// taken in 5 % of the calls instead of 21 % (mispredictions were a visible share of the
// per-ray cost), and the selection compiles to blends.
inline void unit_disk(Rng& rng, double& x, double& y, double& q) {
    for (;;) {
        double x0, y0, x1, y1;
        rng.u01_pair(x0, y0);
        rng.u01_pair(x1, y1);
        x0 = 2.0 * x0 - 1.0, y0 = 2.0 * y0 - 1.0, x1 = 2.0 * x1 - 1.0, y1 = 2.0 * y1 - 1.0;
        const double q0 = x0 * x0 + y0 * y0, q1 = x1 * x1 + y1 * y1;
        const bool first = q0 < 1.0;
        x = first ? x0 : x1;
        y = first ? y0 : y1;
        q = first ? q0 : q1;
        if (q < 1.0) return;
    }
}

// Uniform direction on the unit sphere (Marsaglia 1972): a uniform point (x, y) of the
// unit disk, then (2x sqrt(1-q), 2y sqrt(1-q), 1-2q) with q = x^2 + y^2. No
// trigonometry: the sampler is on the per-ray critical path.
inline V3 uniform_sphere(Rng& rng) {
    double x, y, q;
    unit_disk(rng, x, y, q);
    const double f = 2.0 * std::sqrt(1.0 - q);
    return {x * f, y * f, 1.0 - 2.0 * q};
}

// ---- threads -----------------------------------------------------------------------------

// Embree recommends flush-to-zero / denormals-are-zero for traversal speed. Applied to
// every thread that generates or traces (the caller's mode is restored), so results do
// not depend on which thread ran a ray.
class FastFloatScope {
public:
    FastFloatScope() {
#ifdef LSNIF_SAMPLING_HAS_MXCSR
        saved_ = _mm_getcsr();
        _MM_SET_FLUSH_ZERO_MODE(_MM_FLUSH_ZERO_ON);
        _MM_SET_DENORMALS_ZERO_MODE(_MM_DENORMALS_ZERO_ON);
#endif
    }
    ~FastFloatScope() {
#ifdef LSNIF_SAMPLING_HAS_MXCSR
        _mm_setcsr(saved_);
#endif
    }
    FastFloatScope(const FastFloatScope&) = delete;
    FastFloatScope& operator=(const FastFloatScope&) = delete;

private:
    unsigned saved_ = 0;
};

// Runs body(begin, end) over [0, n) in chunks of 1024 handed out dynamically to `threads`
// threads of the shared pool. Results must not depend on the chunk-to-thread mapping.
// Flush-to-zero is set per chunk: the pool's threads outlive the call.
template <class Body>
void parallel_chunks(std::size_t n, std::uint32_t threads, Body&& body) {
    base::parallel_chunks(n, threads, 1024, [&](std::uint32_t, std::size_t b, std::size_t e) {
        FastFloatScope ffs;
        body(b, e);
    });
}

// Samples are generated, traced and decoded in batches of this many (generate_range(),
// trace_range()): large enough for the prefetches of one construction pass to overlap,
// small enough that a batch's samples, pending state and prefetched lines stay in L1/L2.
inline constexpr std::size_t kBatch = 256;

// ---- Embree rays -------------------------------------------------------------------------

// Geometry masks and IDs: ground-truth rays see the mesh; parity rays also see the caps
// over small holes, which exist only to make the surface watertight.
inline constexpr unsigned kMeshMask = 0x1u, kCapMask = 0x2u;
inline constexpr unsigned kMeshGeometry = 0, kCapGeometry = 1;

// One rtcIntersect1 record: the ray [tnear, tfar] seeing `mask`, the hit cleared as Embree
// requires before a query.
inline RTCRayHit make_ray_hit(const float org[3], const float dir[3], float tnear, float tfar,
                              unsigned mask) {
    RTCRayHit rh;
    rh.ray.org_x = org[0];
    rh.ray.org_y = org[1];
    rh.ray.org_z = org[2];
    rh.ray.tnear = tnear;
    rh.ray.dir_x = dir[0];
    rh.ray.dir_y = dir[1];
    rh.ray.dir_z = dir[2];
    rh.ray.time = 0;
    rh.ray.tfar = tfar;
    rh.ray.mask = mask;
    rh.ray.id = 0;
    rh.ray.flags = 0;
    rh.hit.geomID = RTC_INVALID_GEOMETRY_ID;
    rh.hit.primID = RTC_INVALID_GEOMETRY_ID;
    rh.hit.instID[0] = RTC_INVALID_GEOMETRY_ID;
    return rh;
}

// One crossing recorded by a parity vote (inside.cpp); callers own the buffer so that
// one allocation serves all votes of a thread.
struct ParityHit {
    float t;
    std::uint64_t prim;  // geomID << 32 | primID (mesh and hole caps)
};

// ---- implementation state ----------------------------------------------------------------

struct EmbreeSource::Impl {
    // Mesh, copied (the caller's spans need not outlive create()); construction only:
    // released at the end of create(), when the records below hold what is needed.
    std::vector<float> positions;
    std::vector<std::uint32_t> indices;
    std::vector<float> normals;       // per vertex, as given in MeshView::normals
    std::vector<float> face_normals;  // per triangle, unit geometric normal (zero if degenerate)
    std::vector<std::uint32_t> materials;
    std::size_t triangles = 0;

    double lo[3]{}, hi[3]{}, center[3]{}, diag = 0;
    SamplingConfig cfg;
    bool closed = false;        // edge-manifold as given
    bool parity_ready = false;  // family (c) is rejection sampled (closed, or capped)
    // Consistently oriented (with the caps): the inside vote is the facing of the first
    // hit; otherwise it is the parity of all crossings.
    bool oriented = false;
    double orientation = 1.0;         // +1 normals point out of the solid, -1 into it
    std::vector<std::uint32_t> caps;  // hole-cap triangles (3 vertex indices each)

    // Alias table over triangle areas (Vose 1991), construction precision.
    std::vector<double> alias_prob;
    std::vector<std::uint32_t> alias_index;

    // Hot per-triangle data in one cache line each (the construction arrays above are
    // released after create()): what a surface-leaving ray needs, and what a hit needs.
    // The alias entry of slot t lives in triangle t's surface record: when the slot keeps
    // its own triangle (most draws), the one line fetched for the entry is the record.
    struct alignas(64) SurfaceRecord {
        float v0[3], e1[3], e2[3];  // p = v0 + b1 e1 + b2 e2
        float ng[3];                // unit geometric normal
        float keep;                 // Vose's alias method: slot t keeps triangle t with
        std::uint32_t alias;        // probability `keep`, else it takes triangle `alias`
    };
    struct alignas(64) HitRecord {
        float n[3][3];  // vertex shading normals
        float ng[3];    // unit geometric normal (zero if degenerate)
        std::uint32_t material;
        std::uint32_t corner[3];  // vertex indices (tied_hit's neighbourhood)
    };
    std::vector<SurfaceRecord> surface;
    std::vector<HitRecord> hit_records;
    // tied_hit's neighbourhoods (the triangles around each vertex) and margin
    // (base::tie_margin of the box).
    base::VertexTriangles around;
    double tie_margin = 0;
    // The hole caps' triangles as the inside test's exact hits read them (one per cap
    // triangle, Embree's primID of geometry kCapGeometry): p = v0 + b1 e1 + b2 e2.
    struct CapRecord {
        float v0[3], e1[3], e2[3];
    };
    std::vector<CapRecord> cap_records;

    // Inside/outside classification grid (closed meshes): 0 = crossed by a triangle
    // (decide by votes), 1 = outside, 2 = inside. One byte per cell while building, then
    // packed to 2 bits (512 KiB at 128^3, 64 KiB at 64^3).
    std::uint32_t grid_res = 0;
    std::vector<std::uint8_t> grid, packed_grid;
    double inv_cell[3]{};

    RTCDevice device = nullptr;
    RTCScene scene = nullptr;
    std::atomic<std::int64_t> monitor_bytes{0};
    std::size_t bvh = 0, device_total = 0;
    mutable std::mutex error_mutex;
    std::string errors;

    GenerateCounters counters;

    ~Impl() {
        if (scene) rtcReleaseScene(scene);
        if (device) rtcReleaseDevice(device);
    }

    // Embree device callbacks (embree_scene.cpp); `user` is the Impl.
    static void on_error(void* user, RTCError code, const char* str);
    static bool on_memory(void* user, ssize_t bytes, bool post);
    std::string error_text() const {
        std::lock_guard lock(error_mutex);
        return errors;
    }

    // Construction only (positions are released at the end of create()).
    V3 vertex(std::uint32_t v) const {
        const float* p = &positions[3 * std::size_t(v)];
        return {p[0], p[1], p[2]};
    }

    // ---- tracing ground truth (families.cpp)

    // Embree's answer for one ray, before the hit is decoded.
    struct RawHit {
        float t, u, v;
        std::uint32_t prim;  // kNoPrimitive: miss (or invalid ray)
    };
    RawHit trace_raw(const format::Ray& r) const;
    RawHit exact_hit(const format::Ray& r, const RawHit& h) const;
    // exact_hit, with the triangle chosen the same way on every CPU where the ray meets
    // several at one point (an edge or a vertex they share).
    RawHit tied_hit(const format::Ray& r, const RawHit& h) const;
    RawHit exact_hit(const format::Ray& r, const RawHit& h, unsigned geometry) const;
    void prefetch_hit(std::uint32_t prim) const;
    void decode(const RawHit& h, samples::Sample& s, SampleExtras* x) const;
    void trace_range(samples::Sample* s, SampleExtras* x, std::size_t n) const;

    // ---- the inside test (inside.cpp)

    bool odd_crossings(const float o[3], V3 d, std::vector<ParityHit>& hits) const;
    bool first_hit_from_inside(const float o[3], V3 d, bool& clean, float tfar = INFINITY,
                               bool* missed = nullptr) const;
    bool vote(const float o[3], V3 d, std::vector<ParityHit>& hits, bool& clean) const;
    bool parity_inside(const float o[3], Rng& rng, std::vector<ParityHit>& hits,
                       std::uint64_t& queries) const;
    bool segment_vote(const float o[3], bool& clean, std::uint64_t& queries) const;
    bool inside(const float o[3], Rng& rng, std::vector<ParityHit>& hits, std::uint64_t& queries) const;
    void build_grid();
    void mark_touched_cells();
    void classify_untouched_cells();

    // Cell of point o, clamped into the grid (NaN coordinates go to cell 0 of the axis).
    // Clamping before truncating makes the truncation a floor. Requires grid_res > 0.
    std::size_t cell_of(const float o[3]) const {
        std::size_t c[3];
        for (int a = 0; a < 3; ++a) {
            const double g = (double(o[a]) - lo[a]) * inv_cell[a];
            c[a] = std::size_t(std::max(0.0, std::min(g, double(grid_res - 1))));
        }
        return c[0] + grid_res * (c[1] + grid_res * c[2]);
    }
    // The grid cell of a candidate as it will be stored (rounded to float).
    std::size_t cell_of(V3 o) const {
        const float of[3] = {float(o.x), float(o.y), float(o.z)};
        return cell_of(of);
    }
    // Grid state of cell c: 0 crossed by the surface (vote), 1 outside, 2 inside.
    // Requires a packed grid (packed_grid non-empty).
    unsigned cell_state(std::size_t c) const { return (packed_grid[c >> 2] >> (2 * (c & 3))) & 3u; }

    // Uniform point of the model box; three draws' worth of the stream (one pair, one single).
    V3 uniform_in_box(Rng& rng) const {
        double a, b;
        rng.u01_pair(a, b);
        const double cc = rng.u01();
        return V3{lo[0] + a * (hi[0] - lo[0]), lo[1] + b * (hi[1] - lo[1]), lo[2] + cc * (hi[2] - lo[2])};
    }

    // ---- staged construction of a batch of rays (families.cpp)
    //
    // A ray's first draws decide which random table entries its construction reads: the
    // alias slot and then the surface record of a family (b) ray, the grid cells of a
    // family (c) ray's first two candidates. Embree's traversals keep evicting these
    // tables (1.3 MB of surface records for 20 k triangles, a 64 KiB grid), so each
    // lookup is a cache miss unless prefetched at the right time. The batch is therefore
    // built in passes: draw() takes those first draws and prefetches the slots and grid
    // cells of the whole batch, resolve() turns slots into triangles (prefetching the
    // alias's record when the slot gives its triangle away), finish() builds the rays.
    // Between a prefetch and its use lie only the other rays' draws, no traversal, and
    // the misses of a batch overlap instead of stalling one after another. (Prefetching
    // a batch or two ahead of construction does not work: the traversals in between
    // evict the lines again before they are used.)
    //
    // Streams: construction draws come from the ray's main stream in a fixed order, so
    // draw() can look two family (c) candidates ahead; the inside test's vote directions
    // come from a separate per-ray stream (kVoteSalt), which is what lets the candidates
    // be drawn before it is known whether the first one needs votes.
    struct Streams {
        std::uint64_t main, votes;  // stream_base() of the seed for each purpose
    };
    struct Pending {
        Rng rng;                // the ray's main stream, after the draws taken so far
        std::uint32_t tri;      // family (b): alias slot, after resolve() the triangle
        double coin;            // family (b): the alias method's second draw
        V3 candidate;           // family (c): first candidate origin (rng is past it)
        std::uint32_t cell[2];  // family (c): grid cells of the first two candidates
    };
    void draw(const Streams& st, std::size_t index, Pending& p) const;
    void resolve(Pending& p) const;
    void finish(const Streams& st, std::size_t index, Pending& p, samples::Sample& s, SampleExtras* x,
                std::vector<ParityHit>& hits, GenerateCounters& c) const;
    V3 outside_ray(Rng& rng, float of[3]) const;
    V3 surface_ray(Pending& p, float of[3], SampleExtras* x) const;
    V3 interior_ray(const Streams& st, std::size_t index, Pending& p, float of[3],
                    std::vector<ParityHit>& hits, GenerateCounters& c) const;
    void move_to_nearest_box_face(float of[3]) const;

    static constexpr std::size_t kLanes = 16;
    void intersect16(const samples::Sample* s, std::size_t m, RawHit* raw) const;
    void intersect_packets(const samples::Sample* s, std::size_t n, RawHit* raw) const;
    void trace_generated(samples::Sample* s, SampleExtras* x, std::size_t n) const;
    void generate_range(std::uint64_t seed, std::size_t b, std::size_t e, samples::Sample* out,
                        SampleExtras* extras, std::vector<ParityHit>& hits, GenerateCounters& c) const;
};

// ---- construction stages -----------------------------------------------------------------
//
// EmbreeSource::create() runs these in the order listed, each once, on a fresh Impl; no
// other caller. Units are mesh units throughout. A stage that can fail returns the error
// message (without the "sampling: " prefix), "" on success; create() then discards the Impl.

// validate.cpp. Input: the caller's arguments, unchecked. Returns "" iff they meet the
// contracts of MeshView, Box and SamplingConfig in sampling.hpp: consistent sizes (normals
// one finite xyz per vertex, materials empty or one per triangle), finite coordinates
// inside the box, indices in range, fewer than 2^31 vertices and triangles, a positive
// finite total area, and config values in range. Every later stage relies on this.
std::string validate_input(const MeshView& mesh, const Box& box, const SamplingConfig& cfg);

// mesh_data.cpp. Input: validated arguments. Output: m.cfg, m.triangles, copies of the
// mesh arrays (positions, indices, normals, materials) and the box (lo, hi, center, diag).
void copy_input(EmbreeSource::Impl& m, const MeshView& mesh, const Box& box, const SamplingConfig& cfg);

// mesh_data.cpp. Triangle areas (mesh units^2, double) and their sum, in triangle order.
struct TriangleAreas {
    std::vector<double> area;
    double total = 0;
};
// Input: m.positions, m.indices. Output: m.face_normals (unit, zero when degenerate) and
// the areas, which build_alias_table() consumes.
TriangleAreas compute_face_geometry(EmbreeSource::Impl& m);

// mesh_data.cpp. Input: the areas (total > 0). Output: m.alias_prob, m.alias_index.
void build_alias_table(EmbreeSource::Impl& m, const TriangleAreas& areas);

// topology.cpp. Input: m.positions, m.indices, m.cfg.max_hole_size, m.diag, m.center.
// Output: m.closed, m.parity_ready, m.caps, m.oriented, m.orientation.
void analyze_topology(EmbreeSource::Impl& m);

// embree_scene.cpp. Input: m.positions, m.indices, m.caps, m.parity_ready, m.oriented.
// Output: m.device, m.scene (committed: mesh as geometry 0, caps as geometry 1), m.bvh,
// m.device_total, and the error callbacks installed. Returns an error message on failure.
std::string build_embree_scene(EmbreeSource::Impl& m);

// mesh_data.cpp. Input: m.positions, m.indices, m.normals, m.face_normals, m.materials, m.caps
// and the alias table. Output: m.surface and m.hit_records (one each per triangle),
// m.cap_records (one per cap triangle), m.around and m.tie_margin.
void build_triangle_records(EmbreeSource::Impl& m);

// inside.cpp. Only when m.parity_ready and m.cfg.classify_resolution > 0. Input: the
// committed scene, m.positions, m.indices, m.caps. Output: m.grid_res, m.inv_cell,
// m.packed_grid (m.grid is scratch).
void build_classification_grid(EmbreeSource::Impl& m);

// mesh_data.cpp. Frees the construction-only arrays (Embree holds its own geometry
// copies; the records hold the rest). After it, vertex() and build_grid() must not run.
void release_construction_data(EmbreeSource::Impl& m);

}  // namespace lsnif::sampling
