// Ground-truth ray generation with Embree 3 (see sampling.hpp for the contract).
#include <lsnif/base/clock.hpp>
#include <lsnif/base/parallel.hpp>
#include <lsnif/base/random.hpp>
#include <lsnif/sampling/sampling.hpp>

#include <embree3/rtcore.h>

#if defined(__SSE__) || defined(__x86_64__)
#include <pmmintrin.h>
#include <xmmintrin.h>
#define LSNIF_SAMPLING_HAS_MXCSR 1
#endif

#include <algorithm>
#include <atomic>
#include <bit>
#include <chrono>
#include <cmath>
#include <cstring>
#include <ctime>
#include <mutex>
#include <numbers>
#include <unordered_map>
#include <utility>

namespace lsnif::sampling {

using samples::Family;
using samples::Sample;

namespace {

// ---- random numbers ---------------------------------------------------------------------

using base::mix64;  // splitmix64's output function: seeds the per-ray streams
constexpr std::uint64_t kGolden = base::kGoldenGamma;

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
constexpr std::uint64_t kMainSalt = 0x6C736E6966ull;  // the ray's construction draws
constexpr std::uint64_t kVoteSalt = 0x766F746573ull;  // family (c): inside-test vote directions
std::uint64_t stream_base(std::uint64_t seed, std::uint64_t salt) {
    return mix64(seed ^ salt);
}
Rng stream(std::uint64_t base, std::uint64_t index) {
    return Rng{mix64(base + index * kGolden)};
}
Rng ray_rng(std::uint64_t seed, std::uint64_t index) {
    return stream(stream_base(seed, kMainSalt), index);
}

// ---- small vector helpers (double precision for sample construction) ---------------------

struct V3 {
    double x, y, z;
};
V3 operator+(V3 a, V3 b) {
    return {a.x + b.x, a.y + b.y, a.z + b.z};
}
V3 operator-(V3 a, V3 b) {
    return {a.x - b.x, a.y - b.y, a.z - b.z};
}
V3 operator*(double s, V3 a) {
    return {s * a.x, s * a.y, s * a.z};
}
double dot(V3 a, V3 b) {
    return a.x * b.x + a.y * b.y + a.z * b.z;
}
V3 cross(V3 a, V3 b) {
    return {a.y * b.z - a.z * b.y, a.z * b.x - a.x * b.z, a.x * b.y - a.y * b.x};
}
double length(V3 a) {
    return std::sqrt(dot(a, a));
}

// Uniform point (x, y) of the open unit disk, q = x^2 + y^2, by rejection from the
// square (acceptance pi/4). Two candidates per round, the first one inside wins: the
// result is distributed exactly as with one candidate at a time, but the loop branch is
// taken in 5 % of the calls instead of 21 % (mispredictions were a visible share of the
// per-ray cost), and the selection compiles to blends.
void unit_disk(Rng& rng, double& x, double& y, double& q) {
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
V3 uniform_sphere(Rng& rng) {
    double x, y, q;
    unit_disk(rng, x, y, q);
    const double f = 2.0 * std::sqrt(1.0 - q);
    return {x * f, y * f, 1.0 - 2.0 * q};
}

// Orthonormal frame around unit n (Duff et al. 2017, "Building an orthonormal basis,
// revisited"); returns x*t + y*b + z*n.
V3 from_frame(V3 n, double x, double y, double z) {
    const double sign = std::copysign(1.0, n.z);
    const double a = -1.0 / (sign + n.z), b = n.x * n.y * a;
    const V3 t{1.0 + sign * n.x * n.x * a, sign * b, -sign * n.x};
    const V3 bt{b, sign + n.y * n.y * a, -n.y};
    return x * t + y * bt + z * n;
}

// Direction over the hemisphere around unit n, cosine-weighted (`cosine`) or uniform,
// from one uniform disk point (x, y), q = x^2 + y^2, lifted in n's frame:
//   cosine-weighted  (x, y, sqrt(1-q))              (Malley's method, PBRT 3rd ed. §13.6.3)
//   uniform          (2x sqrt(1-q), 2y sqrt(1-q), |1-2q|)
// The second is Marsaglia's sphere point with its height folded onto n's side: 1-2q is
// uniform in (-1, 1), so |1-2q| is uniform in [0, 1), which is the uniform hemisphere.
// Both laws share the disk point and the frame, and the law is chosen by selects, not
// branches (the law is a coin flip, which no branch predictor learns).
V3 hemisphere(Rng& rng, V3 n, bool cosine) {
    double x, y, q;
    unit_disk(rng, x, y, q);
    const double r = std::sqrt(1.0 - q), f = cosine ? 1.0 : 2.0 * r;
    return from_frame(n, f * x, f * y, cosine ? r : std::abs(1.0 - 2.0 * q));
}

// Triangle / axis-aligned box overlap by the separating axis theorem (Akenine-Möller
// 2001, "Fast 3D triangle-box overlap testing"): the box is centred at the origin with
// half extents h, the triangle given relative to that centre. Candidate axes: the box
// normals, the triangle normal and the 9 cross products of edges and box axes. Double
// precision; callers grow h slightly to make it conservative.
bool triangle_box_overlap(const V3 v[3], const double h[3]) {
    const double c[3][3] = {{v[0].x, v[0].y, v[0].z}, {v[1].x, v[1].y, v[1].z}, {v[2].x, v[2].y, v[2].z}};
    for (int a = 0; a < 3; ++a) {
        const double mn = std::min({c[0][a], c[1][a], c[2][a]}), mx = std::max({c[0][a], c[1][a], c[2][a]});
        if (mn > h[a] || mx < -h[a]) return false;
    }
    const V3 e[3] = {v[1] - v[0], v[2] - v[1], v[0] - v[2]};
    auto separated = [&](V3 axis) {
        const double p0 = dot(axis, v[0]), p1 = dot(axis, v[1]), p2 = dot(axis, v[2]);
        const double r = h[0] * std::abs(axis.x) + h[1] * std::abs(axis.y) + h[2] * std::abs(axis.z);
        return std::min({p0, p1, p2}) > r || std::max({p0, p1, p2}) < -r;
    };
    if (separated(cross(e[0], e[1]))) return false;
    for (const V3& ed : e)
        for (const V3& u : {V3{1, 0, 0}, V3{0, 1, 0}, V3{0, 0, 1}})
            if (separated(cross(ed, u))) return false;
    return true;
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

using base::seconds_since;

// CPU time of the whole process (every thread), in seconds.
double process_cpu_seconds() {
    timespec ts{};
    clock_gettime(CLOCK_PROCESS_CPUTIME_ID, &ts);
    return double(ts.tv_sec) + 1e-9 * double(ts.tv_nsec);
}

// Samples are generated, traced and decoded in batches of this many (generate_range(),
// trace_range()): large enough for the prefetches of one construction pass to overlap,
// small enough that a batch's samples, pending state and prefetched lines stay in L1/L2.
constexpr std::size_t kBatch = 256;

// Geometry masks: ground-truth rays see the mesh (geomID 0); parity rays also see the
// caps over small holes (geomID 1), which exist only to make the surface watertight.
constexpr unsigned kMeshMask = 0x1u, kCapMask = 0x2u;

// One rtcIntersect1 record: the ray [tnear, tfar] seeing `mask`, the hit cleared as Embree
// requires before a query.
RTCRayHit make_ray_hit(const float org[3], const float dir[3], float tnear, float tfar, unsigned mask) {
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

// ---- parity counting through an Embree context filter ------------------------------------

struct ParityHit {
    float t;
    std::uint64_t prim;  // geomID << 32 | primID (mesh and hole caps)
};

// RTCIntersectContext must be the first member: the filter receives a pointer to it.
struct ParityContext {
    RTCIntersectContext ctx;
    std::vector<ParityHit>* hits;
};

// Records every candidate hit and rejects it, so one traversal enumerates all crossings
// of the ray. Embree may report a triangle more than once (spatial-split references),
// which odd_crossings() removes.
void parity_filter(const RTCFilterFunctionNArguments* args) {
    auto* pc = reinterpret_cast<ParityContext*>(args->context);
    for (unsigned i = 0; i < args->N; ++i) {
        if (args->valid[i] == 0) continue;
        pc->hits->push_back(
            {RTCRayN_tfar(args->ray, args->N, i), std::uint64_t(RTCHitN_geomID(args->hit, args->N, i)) << 32 |
                                                      RTCHitN_primID(args->hit, args->N, i)});
        args->valid[i] = 0;
    }
}

}  // namespace

// ---- implementation state ----------------------------------------------------------------

struct EmbreeSource::Impl {
    // Mesh, copied (the caller's spans need not outlive create()); construction only:
    // released at the end of create(), when the records below hold what is needed.
    std::vector<float> positions;
    std::vector<std::uint32_t> indices;
    std::vector<float> normals;       // per vertex, unit (or zero for isolated vertices)
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
    };
    std::vector<SurfaceRecord> surface;
    std::vector<HitRecord> hit_records;

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

    static void on_error(void* user, RTCError code, const char* str) {
        auto* self = static_cast<Impl*>(user);
        std::lock_guard lock(self->error_mutex);
        if (!self->errors.empty()) self->errors += "; ";
        self->errors += "embree error " + std::to_string(int(code)) + ": " + (str ? str : "(no message)");
    }
    // Called before every allocation (bytes > 0, post = false) and after every release
    // (bytes < 0, post = true); a refused or failed allocation is undone the same way.
    static bool on_memory(void* user, ssize_t bytes, bool /*post*/) {
        static_cast<Impl*>(user)->monitor_bytes.fetch_add(std::int64_t(bytes), std::memory_order_relaxed);
        return true;
    }
    std::string error_text() const {
        std::lock_guard lock(error_mutex);
        return errors;
    }

    V3 vertex(std::uint32_t v) const {
        const float* p = &positions[3 * std::size_t(v)];
        return {p[0], p[1], p[2]};
    }

    // Embree's answer for one ray, before the hit is decoded.
    struct RawHit {
        float t, u, v;
        std::uint32_t prim;  // kNoPrimitive: miss (or invalid ray)
    };

    // Traces s.ray against the mesh (not the hole caps). Invalid rays (non-finite, zero
    // direction, tmin < 0 or > tmax) report a miss without calling Embree.
    RawHit trace_raw(const format::Ray& r) const {
        RawHit out{0, 0, 0, kNoPrimitive};
        bool valid = std::isfinite(r.tmin) && r.tmin >= 0 && !(r.tmax < r.tmin) && !std::isnan(r.tmax);
        for (int i = 0; i < 3; ++i) valid = valid && std::isfinite(r.org[i]) && std::isfinite(r.dir[i]);
        valid = valid && (r.dir[0] != 0 || r.dir[1] != 0 || r.dir[2] != 0);
        if (!valid) return out;
        RTCIntersectContext ctx;
        rtcInitIntersectContext(&ctx);
        RTCRayHit rh =
            make_ray_hit(r.org, r.dir, r.tmin, r.tmax, kMeshMask);  // the mesh only, never the hole caps
        rtcIntersect1(scene, &ctx, &rh);
        if (rh.hit.geomID == RTC_INVALID_GEOMETRY_ID) return out;
        return {rh.ray.tfar, rh.hit.u, rh.hit.v, rh.hit.primID};
    }

    // Writes the ground-truth fields of s (and x) from Embree's answer.
    void decode(const RawHit& h, Sample& s, SampleExtras* x) const {
        // Hits and misses take the same path (a miss reads record 0 and its results are
        // replaced by zeros): whether a ray hits is a coin flip to the branch predictor.
        const bool hit = h.prim != kNoPrimitive;
        const HitRecord& rec = hit_records[hit ? h.prim : 0];
        // Embree's (u, v) are the barycentrics of v1 and v2: P = (1-u-v) v0 + u v1 + v v2.
        const float u = hit ? h.u : 0.0f, v = hit ? h.v : 0.0f, w = 1.0f - u - v;
        float n[3], len2 = 0;
        for (int i = 0; i < 3; ++i) {
            n[i] = w * rec.n[0][i] + u * rec.n[1][i] + v * rec.n[2][i];
            len2 += n[i] * n[i];
        }
        if (len2 > 1e-20f && std::isfinite(len2)) {
            const float inv = 1.0f / std::sqrt(len2);
            for (int i = 0; i < 3; ++i) n[i] *= inv;
        } else {  // opposite vertex normals cancel: fall back to the faceted normal
            for (int i = 0; i < 3; ++i) n[i] = rec.ng[i];
        }
        for (int i = 0; i < 3; ++i) s.normal[i] = hit ? n[i] : 0.0f;
        s.t = hit ? h.t : 0.0f;
        s.material = hit ? rec.material : 0;
        s.hit = hit ? 1 : 0;
        if (x) {
            for (int i = 0; i < 3; ++i) x->geometric_normal[std::size_t(i)] = hit ? rec.ng[i] : 0.0f;
            x->primitive = h.prim;
        }
    }

    // Ground truth for samples [b, e) whose rays are set: all traces first (each issuing a
    // prefetch of the hit triangle's record), then all decodes, so the record loads
    // overlap the following traversals instead of stalling after each one.
    void trace_range(Sample* s, SampleExtras* x, std::size_t n) const {
        RawHit raw[kBatch];
        for (std::size_t b = 0; b < n; b += kBatch) {
            const std::size_t m = std::min(kBatch, n - b);
            for (std::size_t i = 0; i < m; ++i) {
                raw[i] = trace_raw(s[b + i].ray);
                if (raw[i].prim != kNoPrimitive) __builtin_prefetch(&hit_records[raw[i].prim]);
            }
            for (std::size_t i = 0; i < m; ++i) decode(raw[i], s[b + i], x ? &x[b + i] : nullptr);
        }
    }

    // Parity of the number of surface crossings of the ray o + t d, t >= 0.
    bool odd_crossings(const float o[3], V3 d, std::vector<ParityHit>& hits) const {
        hits.clear();
        ParityContext pc;
        rtcInitIntersectContext(&pc.ctx);
        pc.ctx.filter = parity_filter;
        pc.hits = &hits;
        const float dir[3] = {float(d.x), float(d.y), float(d.z)};
        RTCRayHit rh =
            make_ray_hit(o, dir, 0.0f, INFINITY, kMeshMask | kCapMask);  // caps close the surface for parity
        rtcIntersect1(scene, &pc.ctx, &rh);
        // A triangle is crossed at most once: drop repeated references first.
        std::sort(hits.begin(), hits.end(),
                  [](const ParityHit& a, const ParityHit& b) { return a.prim < b.prim; });
        hits.erase(std::unique(hits.begin(), hits.end(),
                               [](const ParityHit& a, const ParityHit& b) { return a.prim == b.prim; }),
                   hits.end());
        // A ray through a shared edge or vertex is reported by every triangle there:
        // crossings closer than 1e-6 x diagonal count once.
        std::sort(hits.begin(), hits.end(), [](const ParityHit& a, const ParityHit& b) { return a.t < b.t; });
        const double tol = 1e-6 * diag;
        std::size_t crossings = 0;
        double last = -INFINITY;
        for (const ParityHit& h : hits) {
            if (double(h.t) - last > tol) ++crossings;
            last = h.t;
        }
        return (crossings & 1) != 0;
    }

    // For a closed, consistently oriented surface: o is inside iff the first surface the
    // ray o + t d meets faces away from it (the ray leaves the solid there). One
    // closest-hit query, which stops at that first hit; origins that need a vote lie in
    // grid cells the surface crosses, so the hit is usually close. `clean` is false when
    // the answer could be an artefact of float precision: the hit is within 1e-6 of a
    // triangle edge (barycentrics), grazing (|cos| < 1e-3) or at the origin.
    // With a finite `tfar`, `missed` reports that nothing was hit before it (then the
    // result is false and clean).
    bool first_hit_from_inside(const float o[3], V3 d, bool& clean, float tfar = INFINITY,
                               bool* missed = nullptr) const {
        RTCIntersectContext ctx;
        rtcInitIntersectContext(&ctx);
        const float dir[3] = {float(d.x), float(d.y), float(d.z)};
        RTCRayHit rh = make_ray_hit(o, dir, 0.0f, tfar, kMeshMask | kCapMask);
        rtcIntersect1(scene, &ctx, &rh);
        clean = true;
        if (missed) *missed = rh.hit.geomID == RTC_INVALID_GEOMETRY_ID;
        if (rh.hit.geomID == RTC_INVALID_GEOMETRY_ID) return false;
        // Embree's unnormalized geometric normal follows the same right-hand rule on
        // (v0, v1, v2) as the records (mesh and caps alike), and reading it avoids a
        // cache miss on a per-triangle record. Zero (degenerate): cosine 0, not clean.
        const V3 ng{rh.hit.Ng_x, rh.hit.Ng_y, rh.hit.Ng_z};
        const double len = length(ng);
        const double cosine = len > 0 ? orientation * dot(d, ng) / len : 0.0;
        const double u = rh.hit.u, v = rh.hit.v;
        clean =
            std::abs(cosine) >= 1e-3 && std::min({u, v, 1.0 - u - v}) >= 1e-6 && rh.ray.tfar > 1e-7 * diag;
        return cosine > 0;
    }

    bool vote(const float o[3], V3 d, std::vector<ParityHit>& hits, bool& clean) const {
        if (oriented) return first_hit_from_inside(o, d, clean);
        clean = false;
        return odd_crossings(o, d, hits);
    }

    // First-hit votes: one clean vote decides. Otherwise (parity votes, or an unclean
    // first-hit vote) the majority of three votes along random directions, the third only
    // when the first two disagree. A vote goes wrong only when its ray grazes an edge or
    // vertex within float precision; two independent directions doing so is negligible.
    bool parity_inside(const float o[3], Rng& rng, std::vector<ParityHit>& hits,
                       std::uint64_t& queries) const {
        bool clean = false;
        if (oriented && !packed_grid.empty()) {
            const bool a = segment_vote(o, clean, queries);
            if (clean) return a;
        }
        const bool a = vote(o, uniform_sphere(rng), hits, clean);
        ++queries;
        if (clean) return a;
        const bool b = vote(o, uniform_sphere(rng), hits, clean);
        ++queries;
        if (a == b) return a;
        ++queries;
        return vote(o, uniform_sphere(rng), hits, clean);
    }

    // First-hit vote along the segment from o to the centre of a classified cell next to
    // o's cell (closed, consistently oriented surfaces with a classification grid).
    // Untouched cells lie wholly on one side of the surface (build_grid()), so if the
    // segment meets no surface, o has that cell's state; otherwise the facing of the first
    // hit decides, as in any first-hit vote. A segment of at most 1.5 cells is a much
    // cheaper traversal than a ray in a random direction, which from a point next to the
    // surface often runs across the whole model; votes were ~5 % of generation time.
    // `clean` false: no classified face neighbour, or the hit is not clean (the caller
    // falls back to random directions).
    bool segment_vote(const float o[3], bool& clean, std::uint64_t& queries) const {
        clean = false;
        std::size_t g[3];
        for (int a = 0; a < 3; ++a) {
            const double t = (double(o[a]) - lo[a]) * inv_cell[a];
            g[a] = std::size_t(std::max(0.0, std::min(t, double(grid_res - 1))));
        }
        // The classified face neighbour whose centre is nearest to o.
        double best = INFINITY;
        V3 target{};
        unsigned target_state = 0;
        for (int a = 0; a < 3; ++a)
            for (int step : {-1, 1}) {
                if ((step < 0 && g[a] == 0) || (step > 0 && g[a] + 1 >= grid_res)) continue;
                std::size_t q[3] = {g[0], g[1], g[2]};
                q[a] = step < 0 ? q[a] - 1 : q[a] + 1;
                const unsigned state = cell_state(q[0] + grid_res * (q[1] + grid_res * q[2]));
                if (!state) continue;
                const V3 ctr{lo[0] + (double(q[0]) + 0.5) / inv_cell[0],
                             lo[1] + (double(q[1]) + 0.5) / inv_cell[1],
                             lo[2] + (double(q[2]) + 0.5) / inv_cell[2]};
                const V3 d = ctr - V3{o[0], o[1], o[2]};
                const double d2 = dot(d, d);
                if (d2 < best) best = d2, target = ctr, target_state = state;
            }
        if (!target_state || !(best > 0)) return false;
        const V3 d = target - V3{o[0], o[1], o[2]};
        const double len = std::sqrt(best);
        bool missed = false;
        ++queries;
        const bool in = first_hit_from_inside(o, (1.0 / len) * d, clean, float(len), &missed);
        return missed ? target_state == 2 : in;
    }

    // Cell of point o, clamped into the grid (NaN coordinates go to cell 0 of the axis).
    // Clamping before truncating makes the truncation a floor.
    std::size_t cell_of(const float o[3]) const {
        std::size_t c[3];
        for (int a = 0; a < 3; ++a) {
            const double g = (double(o[a]) - lo[a]) * inv_cell[a];
            c[a] = std::size_t(std::max(0.0, std::min(g, double(grid_res - 1))));
        }
        return c[0] + grid_res * (c[1] + grid_res * c[2]);
    }

    // Grid state of cell c: 0 crossed by the surface (vote), 1 outside, 2 inside.
    unsigned cell_state(std::size_t c) const { return (packed_grid[c >> 2] >> (2 * (c & 3))) & 3u; }

    bool inside(const float o[3], Rng& rng, std::vector<ParityHit>& hits, std::uint64_t& queries) const {
        if (!packed_grid.empty()) {
            const unsigned state = cell_state(cell_of(o));
            if (state) return state == 2;
        }
        return parity_inside(o, rng, hits, queries);
    }

    void build_grid();

    // ---- staged construction of a batch of rays
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

    void draw(const Streams& st, std::size_t index, Pending& p) const {
        p.rng = stream(st.main, index);
        switch (index % 3) {
            case 1: {  // family (b): the alias slot and its coin
                double ut;
                p.rng.u01_pair(ut, p.coin);
                p.tri = std::uint32_t(std::min(triangles - 1, std::size_t(ut * double(triangles))));
                __builtin_prefetch(&surface[p.tri]);
                break;
            }
            case 2: {  // family (c): the first candidate; the cells of the first two
                p.candidate = uniform_in_box(p.rng);
                if (parity_ready && !packed_grid.empty()) {
                    Rng ahead = p.rng;  // finish() draws the second candidate again
                    const V3 second = uniform_in_box(ahead);
                    p.cell[0] = std::uint32_t(cell_of(p.candidate));
                    p.cell[1] = std::uint32_t(cell_of(second));
                    __builtin_prefetch(&packed_grid[p.cell[0] >> 2]);
                    __builtin_prefetch(&packed_grid[p.cell[1] >> 2]);
                }
                break;
            }
            default: break;
        }
    }
    void resolve(Pending& p) const {
        const SurfaceRecord& slot = surface[p.tri];
        if (!(p.coin < double(slot.keep))) {
            p.tri = slot.alias;
            __builtin_prefetch(&surface[p.tri]);
        }
    }

    V3 uniform_in_box(Rng& rng) const {
        double a, b;
        rng.u01_pair(a, b);
        const double cc = rng.u01();
        return V3{lo[0] + a * (hi[0] - lo[0]), lo[1] + b * (hi[1] - lo[1]), lo[2] + cc * (hi[2] - lo[2])};
    }
    // The grid cell of a candidate as it will be stored (rounded to float).
    std::size_t cell_of(V3 o) const {
        const float of[3] = {float(o.x), float(o.y), float(o.z)};
        return cell_of(of);
    }

    void finish(const Streams& st, std::size_t index, Pending& p, Sample& s, SampleExtras* x,
                std::vector<ParityHit>& hits, GenerateCounters& c) const;

    // Closest hits of m <= 16 rays with valid fields (rays made by finish()) through
    // Embree's 16-wide packet interface; unused lanes are masked off. Embree's hybrid
    // packet traversal gives the same hits as rtcIntersect1 for these incoherent rays
    // (checked bit for bit in the tests) at a lower cost per ray.
    static constexpr std::size_t kLanes = 16;
    void intersect16(const Sample* s, std::size_t m, RawHit* raw) const {
        RTCIntersectContext ctx;
        rtcInitIntersectContext(&ctx);
        alignas(64) RTCRayHit16 pk;
        alignas(64) int valid[kLanes];
        for (std::size_t k = 0; k < kLanes; ++k) {
            valid[k] = k < m ? -1 : 0;
            pk.ray.time[k] = 0;
            pk.ray.mask[k] = kMeshMask;
            pk.ray.id[k] = 0;
            pk.ray.flags[k] = 0;
            pk.hit.geomID[k] = RTC_INVALID_GEOMETRY_ID;
            pk.hit.primID[k] = RTC_INVALID_GEOMETRY_ID;
            pk.hit.instID[0][k] = RTC_INVALID_GEOMETRY_ID;
        }
        for (std::size_t k = 0; k < kLanes; ++k) {
            const format::Ray& r = s[std::min(k, m - 1)].ray;  // masked lanes repeat a valid ray
            pk.ray.org_x[k] = r.org[0];
            pk.ray.org_y[k] = r.org[1];
            pk.ray.org_z[k] = r.org[2];
            pk.ray.tnear[k] = r.tmin;
            pk.ray.dir_x[k] = r.dir[0];
            pk.ray.dir_y[k] = r.dir[1];
            pk.ray.dir_z[k] = r.dir[2];
            pk.ray.tfar[k] = r.tmax;
        }
        rtcIntersect16(valid, scene, &ctx, &pk);
        // The mask makes geomID 0 (hit) or RTC_INVALID_GEOMETRY_ID (all ones, miss), so
        // or-ing it in gives kNoPrimitive for misses and masking with its complement
        // zeroes their (u, v): no branch on a coin flip per lane.
        static_assert(RTC_INVALID_GEOMETRY_ID == kNoPrimitive);
        for (std::size_t k = 0; k < m; ++k) {
            const std::uint32_t miss = pk.hit.geomID[k];
            raw[k] = {pk.ray.tfar[k], std::bit_cast<float>(std::bit_cast<std::uint32_t>(pk.hit.u[k]) & ~miss),
                      std::bit_cast<float>(std::bit_cast<std::uint32_t>(pk.hit.v[k]) & ~miss),
                      pk.hit.primID[k] | miss};
        }
    }
    // intersect16() over n rays (the packet baseline of measure_throughput()).
    void intersect_packets(const Sample* s, std::size_t n, RawHit* raw) const {
        for (std::size_t b = 0; b < n; b += kLanes) intersect16(s + b, std::min(kLanes, n - b), raw + b);
    }

    // Ground truth for n <= kBatch rays made by finish() (valid by construction: no
    // checks): all packets first, each hit's record prefetched as soon as its packet
    // returns, then all decodes, so the record loads overlap the following traversals.
    void trace_generated(Sample* s, SampleExtras* x, std::size_t n) const {
        RawHit raw[kBatch];
        for (std::size_t b = 0; b < n; b += kLanes) {
            const std::size_t m = std::min(kLanes, n - b);
            intersect16(s + b, m, raw + b);
            for (std::size_t i = b; i < b + m; ++i)  // a miss prefetches record 0 (no branch)
                __builtin_prefetch(&hit_records[raw[i].prim != kNoPrimitive ? raw[i].prim : 0]);
        }
        for (std::size_t i = 0; i < n; ++i) decode(raw[i], s[i], x ? &x[i] : nullptr);
    }

    void generate_range(std::uint64_t seed, std::size_t b, std::size_t e, Sample* out, SampleExtras* extras,
                        std::vector<ParityHit>& hits, GenerateCounters& c) const {
        const Streams st{stream_base(seed, kMainSalt), stream_base(seed, kVoteSalt)};
        Pending pending[kBatch];
        for (std::size_t i = b; i < e; i += kBatch) {
            const std::size_t m = std::min(e, i + kBatch) - i;
            for (std::size_t k = 0; k < m; ++k) draw(st, i + k, pending[k]);
            for (std::size_t k = (4 - i % 3) % 3; k < m; k += 3) resolve(pending[k]);  // (i + k) % 3 == 1
            for (std::size_t k = 0; k < m; ++k)
                finish(st, i + k, pending[k], out[i + k], extras ? &extras[i + k] : nullptr, hits, c);
            trace_generated(out + i, extras ? extras + i : nullptr, m);
        }
    }
};

// Marks every cell a triangle (mesh or hole cap) overlaps (separating-axis test on the
// cell grown by 1e-3 of its size: conservative against rounding), then flood-fills the
// untouched cells 6-connected to the box faces as outside. No surface passes through an untouched cell, so a
// connected set of them is wholly inside or wholly outside; a set touching the box face is outside (the box
// contains the mesh). Each remaining set is classified by parity votes at up to three of
// its cell centres.
void EmbreeSource::Impl::build_grid() {
    const std::uint32_t R = cfg.classify_resolution;
    grid_res = R;
    for (int a = 0; a < 3; ++a) inv_cell[a] = double(R) / (hi[a] - lo[a]);
    const std::size_t cells = std::size_t(R) * R * R;
    constexpr std::uint8_t kTouched = 0, kUnknown = 3;
    grid.assign(cells, kUnknown);
    // Cells grown by 1e-3 of their size on every side: conservative against rounding in
    // the overlap test and in cell_of().
    double size[3], half[3];
    for (int a = 0; a < 3; ++a) {
        size[a] = (hi[a] - lo[a]) / double(R);
        half[a] = 0.5 * size[a] * (1.0 + 2e-3);
    }
    const std::size_t all = triangles + caps.size() / 3;
    for (std::size_t t = 0; t < all; ++t) {
        const std::uint32_t* tri = t < triangles ? &indices[3 * t] : &caps[3 * (t - triangles)];
        std::size_t k0[3], k1[3];
        for (int a = 0; a < 3; ++a) {
            double mn = INFINITY, mx = -INFINITY;
            for (int j = 0; j < 3; ++j) {
                const double p = positions[3 * std::size_t(tri[j]) + std::size_t(a)];
                mn = std::min(mn, p);
                mx = std::max(mx, p);
            }
            const double g0 = std::floor((mn - lo[a]) * inv_cell[a] - 1e-3);
            const double g1 = std::floor((mx - lo[a]) * inv_cell[a] + 1e-3);
            k0[a] = std::size_t(std::clamp(g0, 0.0, double(R - 1)));
            k1[a] = std::size_t(std::clamp(g1, 0.0, double(R - 1)));
        }
        const V3 p[3] = {vertex(tri[0]), vertex(tri[1]), vertex(tri[2])};
        for (std::size_t z = k0[2]; z <= k1[2]; ++z)
            for (std::size_t y = k0[1]; y <= k1[1]; ++y)
                for (std::size_t x = k0[0]; x <= k1[0]; ++x) {
                    const std::size_t cell = x + R * (y + R * z);
                    if (grid[cell] == kTouched) continue;
                    const V3 ctr{lo[0] + (double(x) + 0.5) * size[0], lo[1] + (double(y) + 0.5) * size[1],
                                 lo[2] + (double(z) + 0.5) * size[2]};
                    const V3 rel[3] = {p[0] - ctr, p[1] - ctr, p[2] - ctr};
                    if (triangle_box_overlap(rel, half)) grid[cell] = kTouched;
                }
    }
    // Label the untouched components (BFS, 6-connectivity).
    std::vector<std::size_t> stack, members;
    Rng rng{mix64(0x636C6173736966ull)};
    std::vector<ParityHit> hits;
    std::uint64_t queries = 0;
    auto flood = [&](std::size_t start, std::vector<std::size_t>& out) {
        out.clear();
        stack.assign(1, start);
        grid[start] = 0xFF;  // visiting
        while (!stack.empty()) {
            const std::size_t c = stack.back();
            stack.pop_back();
            out.push_back(c);
            const std::size_t x = c % R, y = (c / R) % R, z = c / (std::size_t(R) * R);
            const std::size_t nb[6][3] = {{x - 1, y, z}, {x + 1, y, z}, {x, y - 1, z},
                                          {x, y + 1, z}, {x, y, z - 1}, {x, y, z + 1}};
            for (const auto& q : nb) {
                if (q[0] >= R || q[1] >= R || q[2] >= R) continue;  // wraps below 0 too
                const std::size_t n = q[0] + R * (q[1] + R * q[2]);
                if (grid[n] == kUnknown) {
                    grid[n] = 0xFF;
                    stack.push_back(n);
                }
            }
        }
    };
    for (std::size_t c = 0; c < cells; ++c) {
        if (grid[c] != kUnknown) continue;
        flood(c, members);
        bool border = false;
        for (std::size_t m : members) {
            const std::size_t x = m % R, y = (m / R) % R, z = m / (std::size_t(R) * R);
            if (x == 0 || y == 0 || z == 0 || x == R - 1 || y == R - 1 || z == R - 1) {
                border = true;
                break;
            }
        }
        std::uint8_t state = 1;
        if (!border) {
            int inside_votes = 0, votes = 0;
            for (std::size_t k = 0; k < std::min<std::size_t>(3, members.size()); ++k) {
                const std::size_t m = members[k * members.size() / 3];
                const std::size_t idx[3] = {m % R, (m / R) % R, m / (std::size_t(R) * R)};
                float o[3];
                for (int a = 0; a < 3; ++a) o[a] = float(lo[a] + (double(idx[a]) + 0.5) / inv_cell[a]);
                inside_votes += parity_inside(o, rng, hits, queries) ? 1 : 0;
                ++votes;
            }
            state = 2 * inside_votes > votes ? 2 : 1;
        }
        for (std::size_t m : members) grid[m] = state;
    }
}

void EmbreeSource::Impl::finish(const Streams& st, std::size_t index, Pending& p, Sample& s, SampleExtras* x,
                                std::vector<ParityHit>& hits, GenerateCounters& c) const {
    Rng& rng = p.rng;
    s = Sample{};
    s.family = Family(index % 3);
    if (x) *x = SampleExtras{};
    V3 o{}, d{};
    float of[3];
    bool origin_set = false;
    switch (s.family) {
        case Family::outside: {  // (a)
            const V3 ctr{center[0], center[1], center[2]};
            o = ctr + (0.75 * diag) * uniform_sphere(rng);
            d = uniform_in_box(rng) - o;
            d = (1.0 / length(d)) * d;
            break;
        }
        case Family::surface: {             // (b)
            const std::size_t tri = p.tri;  // drawn by draw(), resolved by resolve()
            const SurfaceRecord& rec = surface[tri];
            // Uniform point: b0 = 1 - sqrt(u1), b1 = u2 sqrt(u1) (Shirley 1990; PBRT §13.6.5).
            double u1, u2;
            rng.u01_pair(u1, u2);
            const double su = std::sqrt(u1);
            // With b0 = 1 - su: b2 = 1 - b0 - b1 = su - b1, and p = v0 + b1 e1 + b2 e2.
            const double b1 = u2 * su, b2 = su - b1;
            const V3 pt{rec.v0[0] + b1 * rec.e1[0] + b2 * rec.e2[0],
                        rec.v0[1] + b1 * rec.e1[1] + b2 * rec.e2[1],
                        rec.v0[2] + b1 * rec.e1[2] + b2 * rec.e2[2]};
            const float* fn = rec.ng;
            const std::uint64_t coins = rng.next();  // bit 63: side, bit 62: direction law
            const double side = (coins >> 63) ? 1.0 : -1.0;
            const V3 n = side * V3{fn[0], fn[1], fn[2]};
            const double eps =
                double(cfg.offset_diagonal) * diag +
                double(cfg.offset_relative) * std::max({std::abs(pt.x), std::abs(pt.y), std::abs(pt.z)});
            o = pt + eps * n;
            // Unit up to rounding (n is a unit normal stored in float): no renormalization.
            d = hemisphere(rng, n, (coins >> 62) & 1);
            if (x) {
                x->source_primitive = std::uint32_t(tri);
                x->side = std::int8_t(side);
            }
            break;
        }
        case Family::interior: {  // (c)
            Rng votes{0};         // the vote stream, set up by the first vote
            bool votes_ready = false;
            auto vote_rng = [&]() -> Rng& {
                if (!votes_ready) votes = stream(st.votes, index), votes_ready = true;
                return votes;
            };
            for (std::uint32_t attempt = 0;;) {
                o = attempt == 0 ? p.candidate : uniform_in_box(rng);  // the first one drawn by draw()
                // Classify the origin exactly as it will be stored (float).
                of[0] = float(o.x), of[1] = float(o.y), of[2] = float(o.z);
                ++c.interior_candidates;
                if (!parity_ready) break;
                bool in;
                if (!packed_grid.empty()) {
                    const unsigned state = cell_state(attempt < 2 ? p.cell[attempt] : cell_of(of));
                    in = state ? state == 2 : parity_inside(of, vote_rng(), hits, c.parity_queries);
                } else {
                    in = parity_inside(of, vote_rng(), hits, c.parity_queries);
                }
                if (!in) break;
                if (++attempt >= std::max<std::uint32_t>(1, cfg.max_interior_attempts)) {
                    // Give up: move to the nearest box face (outside the solid).
                    int best_axis = 0;
                    bool best_hi = false;
                    double best = INFINITY;
                    for (int a = 0; a < 3; ++a) {
                        const double dl = double(of[a]) - lo[a], dh = hi[a] - double(of[a]);
                        if (dl < best) best = dl, best_axis = a, best_hi = false;
                        if (dh < best) best = dh, best_axis = a, best_hi = true;
                    }
                    of[best_axis] = float(best_hi ? hi[best_axis] : lo[best_axis]);
                    ++c.interior_fallbacks;
                    break;
                }
            }
            origin_set = true;
            d = uniform_sphere(rng);  // unit up to rounding
            break;
        }
    }
    if (!origin_set) of[0] = float(o.x), of[1] = float(o.y), of[2] = float(o.z);
    const double dd[3] = {d.x, d.y, d.z};
    for (int i = 0; i < 3; ++i) {
        s.ray.org[i] = of[i];
        s.ray.dir[i] = float(dd[i]);
    }
    s.ray.tmin = 0.0f;
    double u_shadow, u_tmax;
    rng.u01_pair(u_shadow, u_tmax);
    s.ray.tmax = u_shadow < double(cfg.shadow_fraction) ? float(u_tmax * diag) : INFINITY;
}

// Splits the odd edges into simple cycles (walk until a vertex repeats, emit the repeated
// part) and fans each one into m.caps. With `directed`, edges are only walked from first
// to second (the caps then continue the mesh's orientation); every vertex has as many
// outgoing as incoming odd edges, so the walks close. Returns false (and leaves no caps)
// when a loop's bounding-box diagonal exceeds `max_extent`: that mesh is genuinely open.
static bool cap_holes(EmbreeSource::Impl& m, const std::vector<std::pair<std::uint32_t, std::uint32_t>>& odd,
                      bool directed, double max_extent) {
    std::unordered_map<std::uint32_t, std::vector<std::size_t>> at;  // vertex -> walkable edges
    for (std::size_t e = 0; e < odd.size(); ++e) {
        at[odd[e].first].push_back(e);
        if (!directed) at[odd[e].second].push_back(e);
    }
    std::vector<char> used(odd.size(), 0);
    std::vector<std::uint32_t> caps, path;
    std::unordered_map<std::uint32_t, std::size_t> on_path;
    bool small = true;
    auto emit = [&](std::size_t from) {  // path[from..] is a simple cycle
        double lo3[3] = {INFINITY, INFINITY, INFINITY}, hi3[3] = {-INFINITY, -INFINITY, -INFINITY};
        for (std::size_t k = from; k < path.size(); ++k)
            for (int a = 0; a < 3; ++a) {
                lo3[a] = std::min(lo3[a], double(m.positions[3 * std::size_t(path[k]) + std::size_t(a)]));
                hi3[a] = std::max(hi3[a], double(m.positions[3 * std::size_t(path[k]) + std::size_t(a)]));
            }
        const double ext = length({hi3[0] - lo3[0], hi3[1] - lo3[1], hi3[2] - lo3[2]});
        if (!(ext <= max_extent)) small = false;
        for (std::size_t k = from + 1; k + 1 < path.size(); ++k)
            caps.insert(caps.end(), {path[from], path[k], path[k + 1]});
    };
    for (std::size_t start = 0; start < odd.size() && small; ++start) {
        if (used[start]) continue;
        path.assign(1, odd[start].first);
        on_path.clear();
        on_path[path[0]] = 0;
        std::uint32_t cur = path[0];
        for (;;) {
            std::size_t next = odd.size();
            for (std::size_t e : at[cur])
                if (!used[e]) {
                    next = e;
                    break;
                }
            if (next == odd.size()) break;  // only back at the walk's start (balanced degrees)
            used[next] = 1;
            cur = odd[next].first == cur ? odd[next].second : odd[next].first;
            if (auto it = on_path.find(cur); it != on_path.end()) {
                const std::size_t j = it->second;
                emit(j);
                for (std::size_t k = j + 1; k < path.size(); ++k) on_path.erase(path[k]);
                path.resize(j + 1);
            } else {
                on_path[cur] = path.size();
                path.push_back(cur);
            }
        }
    }
    if (!small) return false;
    m.caps = std::move(caps);
    return true;
}

// ---- EmbreeSource -------------------------------------------------------------------------

EmbreeSource::EmbreeSource(std::unique_ptr<Impl> impl) : impl_(std::move(impl)) {}
EmbreeSource::~EmbreeSource() = default;

std::unique_ptr<EmbreeSource> EmbreeSource::create(const MeshView& mesh, const Box& box,
                                                   const SamplingConfig& cfg, std::string& error) {
    error.clear();
    auto fail = [&](std::string msg) {
        error = "sampling: " + std::move(msg);
        return std::unique_ptr<EmbreeSource>();
    };
    // ---- validation
    if (mesh.positions.empty() || mesh.indices.empty())
        return fail("empty mesh (no vertices or no triangles)");
    if (mesh.positions.size() % 3) return fail("positions size is not a multiple of 3");
    if (mesh.indices.size() % 3) return fail("indices size is not a multiple of 3");
    const std::size_t nv = mesh.positions.size() / 3, nt = mesh.indices.size() / 3;
    if (nv >= 0x80000000u || nt >= 0x80000000u) return fail("mesh too large (2^31 vertices or triangles)");
    if (!mesh.normals.empty() && mesh.normals.size() != mesh.positions.size())
        return fail("normals must be empty or one xyz per vertex");
    if (!mesh.materials.empty() && mesh.materials.size() != nt)
        return fail("materials must be empty or one per triangle");
    if (!(cfg.shadow_fraction >= 0.0f && cfg.shadow_fraction <= 1.0f))
        return fail("shadow_fraction outside [0, 1]");
    if (!(cfg.offset_diagonal >= 0.0f) || !(cfg.offset_relative >= 0.0f) ||
        !std::isfinite(cfg.offset_diagonal) || !std::isfinite(cfg.offset_relative))
        return fail("offsets must be finite and >= 0");
    if (cfg.classify_resolution > 1024) return fail("classify_resolution above 1024");
    if (!(cfg.max_hole_size >= 0.0f) || !std::isfinite(cfg.max_hole_size))
        return fail("max_hole_size must be finite and >= 0");
    for (int a = 0; a < 3; ++a) {
        if (!std::isfinite(box.min[std::size_t(a)]) || !std::isfinite(box.max[std::size_t(a)]))
            return fail("box is not finite");
        if (!(box.min[std::size_t(a)] < box.max[std::size_t(a)]))
            return fail("box min must be below max on every axis");
    }
    for (std::size_t i = 0; i < mesh.positions.size(); ++i) {
        const float p = mesh.positions[i];
        if (!std::isfinite(p))
            return fail("vertex " + std::to_string(i / 3) + " has a non-finite coordinate");
        if (p < box.min[i % 3] || p > box.max[i % 3])
            return fail("vertex " + std::to_string(i / 3) + " lies outside the box");
    }
    for (std::size_t i = 0; i < mesh.normals.size(); ++i)
        if (!std::isfinite(mesh.normals[i]))
            return fail("normal " + std::to_string(i / 3) + " is not finite");
    for (std::size_t i = 0; i < mesh.indices.size(); ++i)
        if (mesh.indices[i] >= nv)
            return fail("triangle " + std::to_string(i / 3) + " has an index out of range");

    auto impl = std::make_unique<Impl>();
    Impl& m = *impl;
    m.cfg = cfg;
    m.positions.assign(mesh.positions.begin(), mesh.positions.end());
    m.indices.assign(mesh.indices.begin(), mesh.indices.end());
    m.materials.assign(mesh.materials.begin(), mesh.materials.end());
    m.triangles = nt;
    double d2 = 0;
    for (int a = 0; a < 3; ++a) {
        m.lo[a] = box.min[std::size_t(a)];
        m.hi[a] = box.max[std::size_t(a)];
        m.center[a] = 0.5 * (m.lo[a] + m.hi[a]);
        d2 += (m.hi[a] - m.lo[a]) * (m.hi[a] - m.lo[a]);
    }
    m.diag = std::sqrt(d2);

    // ---- geometric normals, areas, vertex normals
    m.face_normals.assign(3 * nt, 0.0f);
    std::vector<double> area(nt);
    std::vector<double> vn(3 * nv, 0.0);
    double total_area = 0;
    for (std::size_t t = 0; t < nt; ++t) {
        const std::uint32_t* v = &m.indices[3 * t];
        const V3 c = cross(m.vertex(v[1]) - m.vertex(v[0]), m.vertex(v[2]) - m.vertex(v[0]));
        const double len = length(c);
        area[t] = 0.5 * len;
        total_area += area[t];
        if (len > 0) {
            m.face_normals[3 * t] = float(c.x / len);
            m.face_normals[3 * t + 1] = float(c.y / len);
            m.face_normals[3 * t + 2] = float(c.z / len);
        }
        for (int j = 0; j < 3; ++j) {  // |c| = 2 x area: area-weighted accumulation
            vn[3 * std::size_t(v[j])] += c.x;
            vn[3 * std::size_t(v[j]) + 1] += c.y;
            vn[3 * std::size_t(v[j]) + 2] += c.z;
        }
    }
    if (!(total_area > 0) || !std::isfinite(total_area)) return fail("mesh has zero total area");
    if (!mesh.normals.empty()) {
        m.normals.assign(mesh.normals.begin(), mesh.normals.end());
    } else {
        m.normals.assign(3 * nv, 0.0f);
        for (std::size_t i = 0; i < nv; ++i) {
            const double len = length({vn[3 * i], vn[3 * i + 1], vn[3 * i + 2]});
            if (len > 0)
                for (int a = 0; a < 3; ++a)
                    m.normals[3 * i + std::size_t(a)] = float(vn[3 * i + std::size_t(a)] / len);
        }
    }

    // ---- alias table over areas (Vose 1991)
    m.alias_prob.assign(nt, 1.0);
    m.alias_index.resize(nt);
    {
        std::vector<double> scaled(nt);
        std::vector<std::uint32_t> small, large;
        for (std::size_t t = 0; t < nt; ++t) {
            m.alias_index[t] = std::uint32_t(t);
            scaled[t] = area[t] * double(nt) / total_area;
            (scaled[t] < 1.0 ? small : large).push_back(std::uint32_t(t));
        }
        while (!small.empty() && !large.empty()) {
            const std::uint32_t l = small.back(), g = large.back();
            small.pop_back();
            m.alias_prob[l] = scaled[l];
            m.alias_index[l] = g;
            scaled[g] = (scaled[g] + scaled[l]) - 1.0;
            if (scaled[g] < 1.0) {
                large.pop_back();
                small.push_back(g);
            }
        }
        // Leftovers (rounding) keep probability 1 and alias themselves; a zero-area
        // leftover would be chosen, so give it away to the largest triangle instead.
        const std::uint32_t biggest =
            std::uint32_t(std::max_element(area.begin(), area.end()) - area.begin());
        for (std::uint32_t l : small)
            if (area[l] == 0) {
                m.alias_prob[l] = 0.0;
                m.alias_index[l] = biggest;
            }
    }

    // ---- closedness: edge manifoldness after welding bit-identical positions
    {
        std::unordered_map<std::uint64_t, std::vector<std::uint32_t>> buckets;  // hash -> canonical ids
        std::vector<std::uint32_t> canon(nv);
        auto bits = [](float f) {
            f += 0.0f;  // -0 -> +0
            std::uint32_t b;
            std::memcpy(&b, &f, 4);
            return b;
        };
        buckets.reserve(nv);
        for (std::size_t i = 0; i < nv; ++i) {
            const std::uint32_t bx = bits(m.positions[3 * i]), by = bits(m.positions[3 * i + 1]),
                                bz = bits(m.positions[3 * i + 2]);
            const std::uint64_t h = mix64((std::uint64_t(bx) << 32 | by) ^ mix64(bz));
            auto& list = buckets[h];
            std::uint32_t id = std::uint32_t(i);
            for (std::uint32_t j : list)
                if (bits(m.positions[3 * std::size_t(j)]) == bx &&
                    bits(m.positions[3 * std::size_t(j) + 1]) == by &&
                    bits(m.positions[3 * std::size_t(j) + 2]) == bz) {
                    id = j;
                    break;
                }
            if (id == i) list.push_back(id);
            canon[i] = id;
        }
        // Half-edges a -> b as (undirected key, direction bit), grouped per edge.
        std::vector<std::uint64_t> edges;  // key << 1 | (a > b)
        edges.reserve(3 * nt);
        for (std::size_t t = 0; t < nt; ++t) {
            const std::uint32_t a = canon[m.indices[3 * t]], b = canon[m.indices[3 * t + 1]],
                                c = canon[m.indices[3 * t + 2]];
            if (a == b || b == c || c == a) continue;  // degenerate: no edges of its own
            for (auto [p, q] : {std::pair{a, b}, std::pair{b, c}, std::pair{c, a}})
                edges.push_back((std::uint64_t(std::min(p, q)) << 32 | std::max(p, q)) << 1 |
                                (p > q ? 1u : 0u));
        }
        std::sort(edges.begin(), edges.end());
        bool closed = !edges.empty(), oriented = !edges.empty();
        // Edges used an odd number of times, as directed edges for the caps: the reverse
        // of the single half-edge when the surface is oriented.
        std::vector<std::pair<std::uint32_t, std::uint32_t>> odd;
        for (std::size_t i = 0; i < edges.size();) {
            std::size_t j = i, forward = 0;
            while (j < edges.size() && (edges[j] >> 1) == (edges[i] >> 1)) forward += !(edges[j++] & 1);
            const std::size_t n = j - i;
            const std::uint32_t lo_v = std::uint32_t(edges[i] >> 33), hi_v = std::uint32_t(edges[i] >> 1);
            closed = closed && n == 2;
            oriented = oriented && ((n == 2 && forward == 1) || n == 1);
            if (n & 1) odd.push_back(forward ? std::pair{hi_v, lo_v} : std::pair{lo_v, hi_v});
            i = j;
        }
        m.closed = closed;
        // Parity is well defined iff every edge is used an even number of times (the
        // surface is a mod-2 cycle). Otherwise the odd edges form closed loops (every
        // vertex has even degree among them); when every loop is small, a fan over it
        // closes the surface for the inside test (Embree geometry 1, invisible to
        // ground-truth rays through the ray mask). Loops of an oriented surface are walked
        // against its boundary half-edges, so the caps continue the orientation.
        if (odd.empty()) {
            m.parity_ready = !edges.empty();
        } else if (cfg.max_hole_size > 0) {
            m.parity_ready = cap_holes(m, odd, oriented, double(cfg.max_hole_size) * m.diag);
        }
        if (m.parity_ready && oriented) {
            // Signed volume (about the box centre, divergence theorem) says whether the
            // consistent orientation points out of or into the solid.
            const V3 ctr{m.center[0], m.center[1], m.center[2]};
            double volume = 0;
            auto add = [&](const std::uint32_t* v) {
                volume += dot(m.vertex(v[0]) - ctr, cross(m.vertex(v[1]) - ctr, m.vertex(v[2]) - ctr));
            };
            for (std::size_t t = 0; t < nt; ++t) add(&m.indices[3 * t]);
            for (std::size_t t = 0; t < m.caps.size(); t += 3) add(&m.caps[t]);
            m.oriented = volume != 0 && std::isfinite(volume);
            m.orientation = volume < 0 ? -1.0 : 1.0;
        }
    }

    // ---- Embree device and scene
    m.device = rtcNewDevice(nullptr);
    if (!m.device)
        return fail("rtcNewDevice failed (embree error " + std::to_string(int(rtcGetDeviceError(nullptr))) +
                    ")");
    rtcSetDeviceErrorFunction(m.device, &Impl::on_error, &m);
    rtcSetDeviceMemoryMonitorFunction(m.device, &Impl::on_memory, &m);
    m.scene = rtcNewScene(m.device);
    if (!m.scene) return fail("rtcNewScene failed: " + m.error_text());
    // Context filters (parity votes) only where parity votes happen: the flag makes every
    // traversal check for one.
    const bool parity_votes = m.parity_ready && !m.oriented;
    rtcSetSceneFlags(m.scene, RTCSceneFlags(RTC_SCENE_FLAG_ROBUST |
                                            (parity_votes ? RTC_SCENE_FLAG_CONTEXT_FILTER_FUNCTION : 0)));
    rtcSetSceneBuildQuality(m.scene, RTC_BUILD_QUALITY_HIGH);
    RTCGeometry geom = rtcNewGeometry(m.device, RTC_GEOMETRY_TYPE_TRIANGLE);
    if (!geom) return fail("rtcNewGeometry failed: " + m.error_text());
    rtcSetGeometryBuildQuality(geom, RTC_BUILD_QUALITY_HIGH);
    // Embree-owned copies (rtcSetNewGeometryBuffer pads them for its vector loads).
    auto* vb = static_cast<float*>(
        rtcSetNewGeometryBuffer(geom, RTC_BUFFER_TYPE_VERTEX, 0, RTC_FORMAT_FLOAT3, 3 * sizeof(float), nv));
    auto* ib = static_cast<std::uint32_t*>(rtcSetNewGeometryBuffer(
        geom, RTC_BUFFER_TYPE_INDEX, 0, RTC_FORMAT_UINT3, 3 * sizeof(std::uint32_t), nt));
    if (!vb || !ib) {
        rtcReleaseGeometry(geom);
        return fail("embree buffer allocation failed: " + m.error_text());
    }
    std::memcpy(vb, m.positions.data(), m.positions.size() * sizeof(float));
    std::memcpy(ib, m.indices.data(), m.indices.size() * sizeof(std::uint32_t));
    rtcSetGeometryMask(geom, kMeshMask);
    rtcCommitGeometry(geom);
    rtcAttachGeometryByID(m.scene, geom, 0);
    rtcReleaseGeometry(geom);
    if (!m.caps.empty()) {  // geometry 1: hole caps, for parity rays only
        RTCGeometry cg = rtcNewGeometry(m.device, RTC_GEOMETRY_TYPE_TRIANGLE);
        if (!cg) return fail("rtcNewGeometry failed: " + m.error_text());
        rtcSetGeometryBuildQuality(cg, RTC_BUILD_QUALITY_HIGH);
        // Only the loop vertices, bit-identical to the mesh's (watertight shared edges).
        std::unordered_map<std::uint32_t, std::uint32_t> local;
        std::vector<std::uint32_t> cap_index(m.caps.size());
        std::vector<float> cap_pos;
        for (std::size_t k = 0; k < m.caps.size(); ++k) {
            auto [it, fresh] = local.try_emplace(m.caps[k], std::uint32_t(local.size()));
            if (fresh)
                for (int a = 0; a < 3; ++a)
                    cap_pos.push_back(m.positions[3 * std::size_t(m.caps[k]) + std::size_t(a)]);
            cap_index[k] = it->second;
        }
        auto* cvb = static_cast<float*>(rtcSetNewGeometryBuffer(
            cg, RTC_BUFFER_TYPE_VERTEX, 0, RTC_FORMAT_FLOAT3, 3 * sizeof(float), cap_pos.size() / 3));
        auto* cib = static_cast<std::uint32_t*>(rtcSetNewGeometryBuffer(
            cg, RTC_BUFFER_TYPE_INDEX, 0, RTC_FORMAT_UINT3, 3 * sizeof(std::uint32_t), m.caps.size() / 3));
        if (!cvb || !cib) {
            rtcReleaseGeometry(cg);
            return fail("embree buffer allocation failed: " + m.error_text());
        }
        std::memcpy(cvb, cap_pos.data(), cap_pos.size() * sizeof(float));
        std::memcpy(cib, cap_index.data(), cap_index.size() * sizeof(std::uint32_t));
        rtcSetGeometryMask(cg, kCapMask);
        rtcCommitGeometry(cg);
        rtcAttachGeometryByID(m.scene, cg, 1);
        rtcReleaseGeometry(cg);
    }
    const std::int64_t before = m.monitor_bytes.load();
    rtcCommitScene(m.scene);
    const std::int64_t after = m.monitor_bytes.load();
    if (rtcGetDeviceError(m.device) != RTC_ERROR_NONE || !m.error_text().empty())
        return fail("embree scene build failed: " + m.error_text());
    m.bvh = std::size_t(std::max<std::int64_t>(0, after - before));
    m.device_total = std::size_t(std::max<std::int64_t>(0, after));

    // ---- hot per-triangle records
    m.surface.resize(nt);
    m.hit_records.resize(nt);
    for (std::size_t t = 0; t < nt; ++t) {
        const std::uint32_t* v = &m.indices[3 * t];
        Impl::SurfaceRecord& sr = m.surface[t];
        Impl::HitRecord& hr = m.hit_records[t];
        const V3 p0 = m.vertex(v[0]), e1 = m.vertex(v[1]) - p0, e2 = m.vertex(v[2]) - p0;
        const double ev[2][3] = {{e1.x, e1.y, e1.z}, {e2.x, e2.y, e2.z}};
        for (int a = 0; a < 3; ++a) {
            sr.v0[a] = m.positions[3 * std::size_t(v[0]) + std::size_t(a)];
            sr.e1[a] = float(ev[0][a]);
            sr.e2[a] = float(ev[1][a]);
            sr.ng[a] = hr.ng[a] = m.face_normals[3 * t + std::size_t(a)];
            for (int j = 0; j < 3; ++j) hr.n[j][a] = m.normals[3 * std::size_t(v[j]) + std::size_t(a)];
        }
        sr.keep = float(m.alias_prob[t]);
        sr.alias = m.alias_index[t];
        hr.material = m.materials.empty() ? 0 : m.materials[t];
    }

    if (m.parity_ready && cfg.classify_resolution > 0) {
        FastFloatScope ffs;
        m.build_grid();
        m.packed_grid.assign((m.grid.size() + 3) / 4, 0);
        for (std::size_t c = 0; c < m.grid.size(); ++c)
            m.packed_grid[c >> 2] = std::uint8_t(m.packed_grid[c >> 2] | (m.grid[c] & 3u) << (2 * (c & 3)));
    }
    // Construction-only arrays (Embree holds its own copies of the geometry).
    for (auto* v : {&m.positions, &m.normals, &m.face_normals}) std::vector<float>().swap(*v);
    for (auto* v : {&m.indices, &m.materials, &m.alias_index}) std::vector<std::uint32_t>().swap(*v);
    std::vector<double>().swap(m.alias_prob);
    std::vector<std::uint8_t>().swap(m.grid);
    return std::unique_ptr<EmbreeSource>(new EmbreeSource(std::move(impl)));
}

void EmbreeSource::generate(std::uint64_t seed, std::size_t count, std::vector<Sample>& out) {
    generate(seed, count, out, nullptr);
}

void EmbreeSource::generate(std::uint64_t seed, std::size_t count, std::vector<Sample>& out,
                            std::vector<SampleExtras>* extras) {
    out.resize(count);
    if (extras) extras->resize(count);
    const Impl& m = *impl_;
    std::atomic<std::uint64_t> candidates{0}, queries{0}, fallbacks{0};
    parallel_chunks(count, base::resolve_threads(m.cfg.threads), [&](std::size_t b, std::size_t e) {
        std::vector<ParityHit> hits;
        GenerateCounters c;
        m.generate_range(seed, b, e, out.data(), extras ? extras->data() : nullptr, hits, c);
        candidates += c.interior_candidates;
        queries += c.parity_queries;
        fallbacks += c.interior_fallbacks;
    });
    impl_->counters = {candidates.load(), queries.load(), fallbacks.load()};
}

void EmbreeSource::trace(std::span<Sample> samples, std::span<SampleExtras> extras) const {
    const Impl& m = *impl_;
    const bool with_extras = extras.size() >= samples.size();
    parallel_chunks(samples.size(), base::resolve_threads(m.cfg.threads), [&](std::size_t b, std::size_t e) {
        m.trace_range(samples.data() + b, with_extras ? extras.data() + b : nullptr, e - b);
    });
}

bool EmbreeSource::inside_solid(const std::array<float, 3>& p, std::uint64_t seed) const {
    Rng rng = ray_rng(seed, 0xFFFFFFFFFFFFFFFFull);
    std::vector<ParityHit> hits;
    std::uint64_t queries = 0;
    FastFloatScope ffs;
    return impl_->inside(p.data(), rng, hits, queries);
}

bool EmbreeSource::is_closed() const {
    return impl_->closed;
}
bool EmbreeSource::rejects_interior() const {
    return impl_->parity_ready;
}
InsideTest EmbreeSource::inside_test() const {
    return !impl_->parity_ready ? InsideTest::none
           : impl_->oriented    ? InsideTest::first_hit_facing
                                : InsideTest::parity;
}
std::size_t EmbreeSource::cap_triangle_count() const {
    return impl_->caps.size() / 3;
}
std::size_t EmbreeSource::bvh_bytes() const {
    return impl_->bvh;
}
std::size_t EmbreeSource::device_bytes() const {
    return impl_->device_total;
}
std::size_t EmbreeSource::triangle_count() const {
    return impl_->triangles;
}
float EmbreeSource::diagonal() const {
    return float(impl_->diag);
}
void EmbreeSource::set_threads(std::uint32_t threads) {
    impl_->cfg.threads = threads;
}
std::uint32_t EmbreeSource::threads() const {
    return base::resolve_threads(impl_->cfg.threads);
}
const GenerateCounters& EmbreeSource::counters() const {
    return impl_->counters;
}
std::string EmbreeSource::last_error() const {
    return impl_->error_text();
}

std::vector<std::array<float, 3>> geometric_normals(std::span<const SampleExtras> extras) {
    std::vector<std::array<float, 3>> out(extras.size());
    for (std::size_t i = 0; i < extras.size(); ++i) out[i] = extras[i].geometric_normal;
    return out;
}

// ---- throughput --------------------------------------------------------------------------

GenerationStats measure_throughput(EmbreeSource& src, std::uint64_t seed, std::size_t count,
                                   std::uint32_t repeats) {
    GenerationStats st;
    st.rays = count;
    st.threads = src.threads();
    if (count == 0) return st;
    repeats = std::max<std::uint32_t>(1, repeats);
    const EmbreeSource::Impl& m = *src.impl_;
    std::vector<Sample> samples;
    struct PlainHit {
        float t, u, v;
        std::uint32_t prim;
    };
    std::vector<PlainHit> plain(count);
    std::vector<EmbreeSource::Impl::RawHit> packet(count);
    double best_gen = INFINITY, best_plain = INFINITY, best_gen_cpu = INFINITY, best_plain_cpu = INFINITY;
    double best_packet = INFINITY, best_packet_cpu = INFINITY;
    for (std::uint32_t r = 0; r < repeats; ++r) {
        auto t0 = std::chrono::steady_clock::now();
        double c0 = process_cpu_seconds();
        src.generate(seed, count, samples, nullptr);
        best_gen = std::min(best_gen, seconds_since(t0));
        best_gen_cpu = std::min(best_gen_cpu, process_cpu_seconds() - c0);

        // The baseline: the same rays, one rtcIntersect1 each, same threads and chunks.
        t0 = std::chrono::steady_clock::now();
        c0 = process_cpu_seconds();
        parallel_chunks(count, st.threads, [&](std::size_t b, std::size_t e) {
            RTCIntersectContext ctx;
            rtcInitIntersectContext(&ctx);
            for (std::size_t i = b; i < e; ++i) {
                const format::Ray& ray = samples[i].ray;
                RTCRayHit rh = make_ray_hit(ray.org, ray.dir, ray.tmin, ray.tmax, kMeshMask);
                rtcIntersect1(m.scene, &ctx, &rh);
                plain[i] = {rh.ray.tfar, rh.hit.u, rh.hit.v,
                            rh.hit.geomID == RTC_INVALID_GEOMETRY_ID ? kNoPrimitive : rh.hit.primID};
            }
        });
        best_plain = std::min(best_plain, seconds_since(t0));
        best_plain_cpu = std::min(best_plain_cpu, process_cpu_seconds() - c0);

        // For comparison only: the same rays through Embree's 16-wide packet interface.
        t0 = std::chrono::steady_clock::now();
        c0 = process_cpu_seconds();
        parallel_chunks(count, st.threads, [&](std::size_t b, std::size_t e) {
            m.intersect_packets(samples.data() + b, e - b, packet.data() + b);
        });
        best_packet = std::min(best_packet, seconds_since(t0));
        best_packet_cpu = std::min(best_packet_cpu, process_cpu_seconds() - c0);
    }
    st.seconds = best_gen;
    st.rays_per_second = double(count) / best_gen;
    st.plain_seconds = best_plain;
    st.plain_rtcintersect_rays_per_second = double(count) / best_plain;
    st.ratio = st.rays_per_second / st.plain_rtcintersect_rays_per_second;
    st.cpu_seconds = best_gen_cpu;
    st.plain_cpu_seconds = best_plain_cpu;
    st.cpu_ratio = best_gen_cpu > 0 ? best_plain_cpu / best_gen_cpu : 0;
    st.packet_seconds = best_packet;
    st.packet_rays_per_second = double(count) / best_packet;
    st.packet_ratio = st.rays_per_second / st.packet_rays_per_second;
    st.packet_cpu_seconds = best_packet_cpu;
    st.packet_cpu_ratio = best_gen_cpu > 0 ? best_packet_cpu / best_gen_cpu : 0;
    return st;
}

}  // namespace lsnif::sampling
