// The two tracers of a scene whose complex meshes have LSNIF assets (docs/architecture.md §5,
// "Images"):
//   * reference: Embree for every mesh, and
//   * hybrid:    Embree for the meshes without an asset, the LSNIF reader
//                (lsnif_intersect_instance) for those with one, with each instance's
//                transform applied at run time.
// `lsnif eval` builds one from a conversion's manifest (lsnif::eval), a conversion's visual
// check one per object (ObjectViews, object_views.hpp).
//
// Contract: never throws, exits or prints; failures are returned as "<file>: <problem>" or
// "<what>: <problem>" in `error`.
#pragma once

#include <lsnif/lsnif.h>

#include <array>
#include <cstdint>
#include <memory>
#include <span>
#include <string>

namespace lsnif::render {

// Closest-hit record of a world-space ray. `instance` indexes the scene's instances;
// -1 = miss. `normal` is the unit world-space shading normal (interpolated vertex normals
// for Embree hits, the network's normal for LSNIF hits).
struct TraceHit {
    float t = 0.0f;
    std::array<float, 3> normal{};
    std::int32_t instance = -1;
};

// Where trace calls spent their time (EvalScene::closest and occluded add to it when given
// one): totals over every call that shared it. One per thread; `lsnif eval` reports it per
// tracer and ray family (docs/eval.md "Where the secondary rays' time goes").
struct TraceProfile {
    double seconds = 0;          // the calls, whole
    double embree_seconds = 0;   // Embree traversing the meshes: all of the reference's time
    double reader_seconds = 0;   // the reader's calls (hybrid); the rest is box tests and batching
    std::uint64_t rays = 0;      // rays traced
    std::uint64_t box_hits = 0;  // (ray, asset instance) pairs whose ray reaches the box: the reader's rays
    std::uint64_t reader_calls = 0;  // reader calls, batches of at most 256 rays
    std::uint64_t reader_hits = 0;   // of the reader's rays, those it reported hitting the asset
    TraceProfile& operator+=(const TraceProfile& o);
};

// The assets of a scene held in memory against the BVHs they replace.
struct AssetMemory {
    std::uint64_t lsnif_resident_bytes = 0;  // the opened assets' lsnif_info.decoded_bytes
    std::uint64_t bvh_bytes_replaced = 0;    // Embree's BVHs of their meshes, measured in the scene's device
    lsnif_arithmetic arithmetic = LSNIF_ARITHMETIC_FP32;  // what the assets trace with (all the same)
};

// A scene with both tracers built (SceneBuilder). Thread-safe for concurrent trace calls.
class EvalScene {
public:
    ~EvalScene();
    EvalScene(const EvalScene&) = delete;
    EvalScene& operator=(const EvalScene&) = delete;

    // `hybrid` selects the tracer. Rays use the reader's struct (world space, t in
    // [tmin, tmax]); `hits`/`occluded` have rays.size() entries.
    // `profile`, when given, is added to.
    void closest(bool hybrid, std::span<const lsnif_ray> rays, std::span<TraceHit> hits,
                 TraceProfile* profile = nullptr) const;
    void occluded(bool hybrid, std::span<const lsnif_ray> rays, std::span<std::uint8_t> occluded,
                  TraceProfile* profile = nullptr) const;

    std::size_t instance_count() const;
    std::size_t lsnif_instance_count() const;   // instances traced through the reader in hybrid
    std::array<float, 6> world_bounds() const;  // min xyz, max xyz
    std::array<float, 6> instance_bounds(std::size_t instance) const;
    AssetMemory asset_memory() const;

    // The tracers' state: complete only inside lsnif::render (its src/scene_impl.hpp), which
    // renders and compares images of the scene (render.hpp).
    struct Impl;
    const Impl& impl() const { return *impl_; }

private:
    explicit EvalScene(std::unique_ptr<Impl> impl);
    std::unique_ptr<Impl> impl_;
    friend class SceneBuilder;
    friend class ObjectViews;
};

// One mesh of a scene: object-space triangles with per-vertex shading normals, borrowed for
// the call that adds it (the scene keeps a copy).
struct SceneMesh {
    std::string name;
    std::span<const float> positions;        // xyz per vertex
    std::span<const std::uint32_t> indices;  // three per triangle
    std::span<const float> normals;          // xyz per vertex, unit length
    // A .lsnif file of this mesh: the hybrid tracer traces its instances through it instead
    // of the mesh. Empty: Embree in both tracers.
    std::string asset;
};

// How the scene opens its assets: the network's arithmetic, the escape rule's limit
// (lsnif_set_escape_points; 0 = off, at most each asset's entry points per ray) and the
// enclosed rule (lsnif_set_enclosed_rule).
struct AssetSettings {
    lsnif_arithmetic arithmetic = LSNIF_ARITHMETIC_AUTO;
    std::uint32_t escape_points = 0;
    bool enclosed_rule = false;  // lsnif_set_enclosed_rule: occlusion queries only
};

// How Embree traces its part of a trace call (every mesh in the reference, the meshes without
// an asset in the hybrid): `packets16` in 16-wide packets of consecutive rays
// (rtcIntersect16, rtcOccluded16), which a renderer tracing a pixel's ambient-occlusion rays
// or a row's shadow rays together gets; `single` one ray per call (rtcIntersect1,
// rtcOccluded1). The same hits but for the rare ray Embree's packet and single-ray kernels
// decide differently.
enum class EmbreeRoute { packets16, single };
const char* embree_route_name(EmbreeRoute route);  // "packets16", "single"

// Builds an EvalScene: every mesh first, then the instances, then finish(). Each step
// returns false with `error` set on failure; the builder is then of no further use.
class SceneBuilder {
public:
    SceneBuilder();
    ~SceneBuilder();
    SceneBuilder(const SceneBuilder&) = delete;
    SceneBuilder& operator=(const SceneBuilder&) = delete;

    // The Embree device, with Embree's default configuration, and the route both tracers'
    // Embree part takes. First.
    bool open(std::string& error, EmbreeRoute route = EmbreeRoute::packets16);
    // Mesh number mesh_count(): uploaded to an Embree scene of its own (its BVH bytes
    // measured), its asset opened with `settings` when it has one.
    bool add_mesh(const SceneMesh& mesh, const AssetSettings& settings, std::string& error);
    std::size_t mesh_count() const;
    // Instance number instance_count() of mesh `mesh` (< mesh_count()), object to world by
    // `transform` (3x4 row-major): an error for a singular or non-finite transform.
    bool add_instance(std::uint32_t mesh, const std::array<float, 12>& transform, std::string& error);
    std::size_t instance_count() const;
    // Commits the scenes; null with `error` when Embree reported an error on the way.
    std::unique_ptr<EvalScene> finish(std::string& error);

private:
    std::unique_ptr<EvalScene::Impl> impl_;
};

}  // namespace lsnif::render
