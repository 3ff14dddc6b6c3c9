// Ground-truth training rays for `lsnif convert` (docs/architecture.md §3, "Training"): the three
// ray families, traced with Embree 3 against the original triangle mesh.
//
//   (a) outside   origin on a sphere of radius 0.75 x box diagonal around the box centre,
//                 aimed at a uniform point in the box;
//   (b) surface   leaving the mesh's own surface: a triangle picked with probability
//                 proportional to its area (alias table, Walker 1977 / Vose 1991), a
//                 uniform point on it (the square-root warp, Shirley 1990 / Pharr, Jakob,
//                 Humphreys, PBRT 3rd ed. §13.6.5), a side (front/back of the geometric
//                 normal, 50/50), the origin offset along that side's normal, and a
//                 direction cosine-weighted (half the rays) or uniform (the other half)
//                 over that side's hemisphere;
//   (c) interior  origin uniform in the box but outside the solid, direction uniform on
//                 the sphere. Candidates inside the solid are rejected when the mesh is
//                 closed (or closed after capping small holes): a classification grid
//                 settles most candidates, ray votes the rest (see InsideTest). Open
//                 meshes have no inside and reject nothing.
//
// Sample i belongs to family i % 3, so the families have equal shares. A configurable
// share of the rays (default 25 %) is shadow-like: tmax uniform in (0, box diagonal);
// the rest have tmax = +inf. tmin is always 0 and directions are unit length, so t is a
// distance in mesh units.
//
// Memory: besides Embree's scene, 128 bytes per triangle (two cache-line records; the
// alias table lives in the surface records) and a 2-bit classification grid (64 KiB at
// the default resolution).
//
// Throughput: rays are built and traced in batches of 256: their random table lookups
// are prefetched a pass ahead, and they are traced 16 at a time through Embree's packet
// interface (rtcIntersect16), which returns the same hits as rtcIntersect1.
//
// Determinism: every ray draws its random numbers from its own streams, derived from
// (seed, index) only (seeded by splitmix64, Steele et al. 2014, continued by wyrand): one
// for its construction, one for family (c)'s inside-test votes. The scene is immutable
// after construction, so generate() returns bit-identical samples for a seed whatever the
// thread count, and a shorter request is a prefix of a longer one.
//
// Errors: this library never throws on bad input and never exits. create() returns null
// and an error message for invalid meshes; Embree device errors are captured through
// rtcSetDeviceErrorFunction into last_error().
#pragma once

#include <lsnif/mesh/mesh.hpp>
#include <lsnif/samples/sample.hpp>

#include <array>
#include <cstddef>
#include <cstdint>
#include <memory>
#include <optional>
#include <span>
#include <string>
#include <vector>

namespace lsnif::sampling {

inline constexpr std::uint32_t kNoPrimitive = 0xFFFFFFFFu;

// The converter's one mesh view and box (lsnif/mesh/mesh.hpp). The spans only have to live
// during create() (what Embree and the samplers need is copied). Sampling requires the
// normals (unit shading normals, renormalized after interpolation; where they cancel, the
// faceted normal is used) and does not compute them: the scene importer supplies them
// (scene::compute_vertex_normals() where a file has none), so there is one definition.
// The box is the model box (docs/architecture.md §3: the mesh AABB, padded); every vertex
// must lie inside it.
using MeshView = mesh::MeshView;
using Box = mesh::Box;

struct SamplingConfig {
    std::uint32_t threads = 0;      // worker threads for generate(); 0 = hardware threads
    float shadow_fraction = 0.25f;  // share of rays with finite tmax, in [0, 1]
    // Surface-leaving origin offset along the side's geometric normal:
    //   offset = offset_diagonal x box diagonal + offset_relative x max_i |p_i|
    // The first term clears Embree's intersection error near the mesh's own scale, the
    // second one the float rounding of p itself when the mesh sits far from the origin
    // (one float ulp is 1.2e-7 x |p|).
    float offset_diagonal = 1e-4f;
    float offset_relative = 1e-5f;
    // Resolution of the inside/outside classification grid that settles most family (c)
    // candidates without a ray (cells crossed by no triangle are wholly inside or
    // outside). 0 disables the grid (every candidate origin is voted on by rays).
    std::uint32_t classify_resolution = 64;
    // Family (c) rejection sampling gives up after this many candidates and puts the
    // origin on the nearest box face instead (outside the solid, counted in counters()).
    std::uint32_t max_interior_attempts = 1000;
    // A mesh that is not closed but whose holes are small (every boundary loop's bounding
    // box diagonal <= max_hole_size x box diagonal) is closed for the inside test only:
    // each loop gets a triangle fan, stored as a second Embree geometry that ground-truth
    // rays never see (ray mask). Real scans and CAD exports often miss a few triangles;
    // without this their family (c) would start rays inside the solid. 0 disables it
    // (only meshes closed as given are rejection sampled).
    float max_hole_size = 0.05f;
    // Embree's instruction set (its device's `isa=` setting). Embree builds a different BVH
    // per ISA (4-wide nodes for SSE, 8-wide for AVX) and rounds its ray-triangle tests with
    // or without FMA, so a ray grazing an edge could hit on one ISA and miss on another, and
    // the BVH's bytes (which classification weighs) differ. Conversion pins AVX2, the
    // floor of the CPUs it runs on (x86-64-v3), so the ground truth is the same on every
    // such machine; create() refuses a CPU without AVX2 and FMA. Tests set others to
    // compare ("sse4.2", "avx", "avx512"); empty = Embree's own choice (the best it has).
    std::string embree_isa = "avx2";
};

// How family (c) decides that an origin is inside the solid (after the classification
// grid): not at all (open mesh), by the facing of the first hit (closed and consistently
// oriented, caps included: one closest-hit query per vote; a vote clear of edges and
// grazing angles decides alone; the first vote runs along the short segment to the centre
// of a classified neighbour cell, whose state it takes when it meets no surface), or by
// the parity of all crossings along the ray (closed but not consistently oriented: one
// all-hits traversal per vote). Votes that are not clear-cut are settled by the majority
// of three random directions.
enum class InsideTest : std::uint8_t { none, first_hit_facing, parity };

// Per-sample data samples::Sample has no field for (parallel to the samples).
struct SampleExtras {
    std::array<float, 3> geometric_normal{};        // unit normal of the hit triangle, right-hand
                                                    // rule on (v0, v1, v2); zero when no hit
    std::uint32_t primitive = kNoPrimitive;         // hit triangle, kNoPrimitive when no hit
    std::uint32_t source_primitive = kNoPrimitive;  // family (b): triangle left; else none
    std::int8_t side = 0;  // family (b): +1 front (along the geometric normal), -1 back
};

// The extras' geometric normals as the parallel array samples::held_out_metrics() takes.
std::vector<std::array<float, 3>> geometric_normals(std::span<const SampleExtras> extras);

// Counters of the last generate() call.
struct GenerateCounters {
    std::uint64_t interior_candidates = 0;  // family (c) origins drawn (accepted + rejected)
    std::uint64_t parity_queries = 0;       // inside-test rays traced (votes)
    std::uint64_t interior_fallbacks = 0;   // origins put on the box after max attempts
};

// Throughput of ground-truth generation against plain Embree tracing of the same rays.
struct GenerationStats {
    std::uint64_t rays = 0;
    std::uint32_t threads = 0;
    double seconds = 0;          // best of the repeats: generate() for `rays` rays
    double rays_per_second = 0;  // rays / seconds
    // The same rays (taken from generate()'s output) traced by a plain parallel
    // rtcIntersect1 loop with the same thread count and work split; best of the repeats.
    double plain_seconds = 0;
    double plain_rtcintersect_rays_per_second = 0;
    double ratio = 0;  // rays_per_second / plain_rtcintersect_rays_per_second (1 = free)
    // The same comparison in process CPU time (all threads), best of the repeats: less
    // sensitive than wall time to other processes competing for the cores.
    double cpu_seconds = 0, plain_cpu_seconds = 0;
    double cpu_ratio = 0;  // plain_cpu_seconds / cpu_seconds
    // For comparison only (not the baseline): the same rays traced through Embree's
    // 16-wide packet interface (rtcIntersect16), same threads and chunks, best of the
    // repeats; the ratios are generation against it, in wall and in CPU time.
    double packet_seconds = 0, packet_rays_per_second = 0, packet_ratio = 0;
    double packet_cpu_seconds = 0, packet_cpu_ratio = 0;
};

class EmbreeSource final : public samples::SampleSource {
public:
    // Validates the mesh, box and config against the contracts above (non-empty, sizes
    // consistent, normals one per vertex, finite, indices in range, inside the box,
    // positive total area), builds the Embree scene once (RTC_BUILD_QUALITY_HIGH,
    // RTC_SCENE_FLAG_ROBUST, plus RTC_SCENE_FLAG_CONTEXT_FILTER_FUNCTION if parity votes
    // are needed) and the samplers. Returns null and sets `error` ("sampling: ...") on
    // failure.
    static std::unique_ptr<EmbreeSource> create(const MeshView& mesh, const Box& box,
                                                const SamplingConfig& cfg, std::string& error);
    ~EmbreeSource() override;
    EmbreeSource(const EmbreeSource&) = delete;
    EmbreeSource& operator=(const EmbreeSource&) = delete;

    // samples::SampleSource: `count` samples of the three families (out is resized),
    // using threads() threads. Not to be called concurrently on one object (it records
    // counters()); trace() and inside_solid() may run concurrently with anything.
    void generate(std::uint64_t seed, std::size_t count, std::vector<samples::Sample>& out) override;
    // Same samples, plus the per-sample extras (resized to count) when `extras` != null.
    void generate(std::uint64_t seed, std::size_t count, std::vector<samples::Sample>& out,
                  std::vector<SampleExtras>* extras);

    // Ground truth for caller-made rays (e.g. held-out evaluation rays): fills t, normal,
    // material and hit of every sample from its ray; family is left alone. Thread-safe.
    void trace(std::span<samples::Sample> samples, std::span<SampleExtras> extras = {}) const;

    // The family (c) inside test (classification grid, then votes as inside_test() says;
    // hole caps included). A mesh that does not reject_interior() has no inside: false for
    // every point. Thread-safe.
    bool inside_solid(const std::array<float, 3>& p, std::uint64_t seed = 0) const;

    // Every undirected edge shared by exactly two triangles (positions welded by exact
    // value, degenerate triangles ignored).
    bool is_closed() const;
    // Family (c) origins are rejection-sampled against the solid: the mesh is closed, or
    // every edge is used an even number of times, or its small holes were capped.
    bool rejects_interior() const;
    std::size_t cap_triangle_count() const;  // triangles of the hole caps (0 if none)
    InsideTest inside_test() const;
    // Net bytes Embree allocated while committing the scene (BVH nodes and leaf
    // triangles; the few hole-cap triangles included), from the device memory monitor
    // (rtcSetDeviceMemoryMonitorFunction). Embree 3 has no public node count.
    std::size_t bvh_bytes() const;
    // All bytes the device holds for this scene (BVH plus Embree's copies of the vertex
    // and index buffers).
    std::size_t device_bytes() const;
    std::size_t triangle_count() const;
    float diagonal() const;
    // Worker threads for generate()/trace()/measure_throughput() (0 = hardware threads).
    // Not thread-safe against concurrent generate()/trace().
    void set_threads(std::uint32_t threads);
    std::uint32_t threads() const;
    const GenerateCounters& counters() const;  // of the last generate() call
    // Embree errors captured since creation ("" when none). Thread-safe.
    std::string last_error() const;

    struct Impl;

private:
    explicit EmbreeSource(std::unique_ptr<Impl> impl);
    std::unique_ptr<Impl> impl_;
    friend GenerationStats measure_throughput(EmbreeSource&, std::uint64_t, std::size_t, std::uint32_t);
};

// Bytes of the BVH Embree builds for `mesh` alone, with EmbreeSource's scene flags and build
// quality (net device allocations during the commit, as EmbreeSource::bvh_bytes() counts
// them, without hole caps): what a renderer's bottom-level BVH for a mesh that stays BVH
// costs. Any mesh with indices in range, including an empty one. Returns nullopt and sets
// `error` ("sampling: ...") on failure.
std::optional<std::size_t> measure_bvh_bytes(const MeshView& mesh, std::string& error);

// The compressed-BVH yardstick: the size of an 8-wide BVH in the compressed node format of
// Ylitie, Karras and Laine (2017, "Efficient Incoherent Ray Traversal on GPUs Through
// Compressed Wide BVHs"): 80 bytes per inner node, the estimate the LSNIF paper compares
// with. Leaf triangles are not counted, so it is a lower bound on what a GPU renderer holds.
// The node count is Embree's own BVH builder's (rtcBuildBVH: SAH, medium quality, at most
// 8 children and 3 triangles per leaf) on one thread, so it is the same on every run.
struct CompressedBvh {
    static constexpr std::uint64_t kInnerNodeBytes = 80;
    std::uint64_t inner_nodes = 0, leaves = 0;
    std::uint64_t bytes() const { return kInnerNodeBytes * inner_nodes; }
};
// For `mesh` (indices in range; an empty mesh has no nodes). Returns nullopt and sets
// `error` ("sampling: ...") on failure.
std::optional<CompressedBvh> measure_compressed_bvh(const MeshView& mesh, std::string& error);

// Times generate(seed, count) against a plain parallel rtcIntersect1 loop over the same
// rays, both with src.threads() threads and the same dynamic 1024-ray chunks; `repeats`
// alternating runs, best time of each. Also times the same rays through rtcIntersect16
// (packet_* fields), for comparison. Overwrites src.counters().
GenerationStats measure_throughput(EmbreeSource& src, std::uint64_t seed, std::size_t count,
                                   std::uint32_t repeats = 3);

}  // namespace lsnif::sampling
