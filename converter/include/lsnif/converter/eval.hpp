// `lsnif eval`: renders a converted scene twice and compares the images (docs/architecture.md §5,
// "Images"). Primary visibility always comes from the real meshes through Embree
// (standing in for the paper's rasterized G-buffer: vertex and face data stay exact);
// secondary rays — shadow rays to a point light, ambient-occlusion rays and mirror
// reflections — are traced
//   * reference: Embree for every mesh, and
//   * hybrid:    Embree for simple meshes, the LSNIF reader (lsnif_intersect_instance)
//                for complex ones, with each instance's transform applied at run time.
// Camera, light and instance transforms are inputs of the render, not of the conversion:
// they can change without touching the assets.
//
// Contract: never throws, exits or prints; failures are returned as "<file>: <problem>"
// lines in EvalResult::errors, and no image is left half-written (PNGs go through a
// temporary file and a rename).
#pragma once

#include <array>
#include <cstdint>
#include <memory>
#include <optional>
#include <span>
#include <string>
#include <utility>
#include <vector>

#include <lsnif/lsnif.h>
#include <lsnif/base/result.hpp>
#include <nlohmann/json.hpp>

namespace lsnif::converter {

struct EvalCamera {
    std::array<float, 3> eye{}, target{}, up{0.0f, 1.0f, 0.0f};
    float fov_deg = 40.0f;  // vertical field of view
};

struct EvalOptions {
    std::string outdir;                // a conversion's OUTDIR (manifest.json + assets)
    std::vector<std::string> sources;  // the converted inputs; empty = the manifest's paths
    std::string images_dir;            // where PNGs and report.json go; "" = OUTDIR/eval
    std::uint32_t width = 480, height = 360;
    std::optional<EvalCamera> camera;           // default frames the scene's bounds
    std::optional<std::array<float, 3>> light;  // point light; default above and in front
    std::uint32_t ao_samples = 16;              // cosine-distributed rays per pixel
    float ao_radius = 0.1f;                     // AO ray length, fraction of the scene diagonal
    std::uint32_t threads = 0;                  // 0 = hardware threads
    std::uint64_t seed = 1;
    // Run-time placement changes: instance index -> object-to-world 3x4 row-major matrix.
    std::vector<std::pair<std::uint32_t, std::array<float, 12>>> instance_transforms;
    bool write_images = true;
    lsnif_arithmetic arithmetic =
        LSNIF_ARITHMETIC_AUTO;  // LSNIF network arithmetic (auto: what lsnif_open picks)
    // Hybrid render only: secondary rays leaving an LSNIF instance's surface start this many of
    // its occupancy voxels (edge length in world units) away from the surface (tmin), the
    // runtime treatment docs/investigations/surface-leaving-rays.md measures; the
    // reference keeps tmin = 0, so the images show what it costs and what it fixes. 0 = off.
    float surface_tmin_voxels = 0.0f;
    // Times each row's secondary rays this many times per tracer (the two alternating) and
    // keeps each tracer's fastest: the time ratio then leaves out the stalls a shared host
    // puts into one run (docs/eval.md "Timing"). Both tracers are deterministic, so every
    // repeat gives the same images. >= 1.
    std::uint32_t timing_repeats = 3;
};

struct EvalResult {
    nlohmann::json report;            // see schema in docs and tests; empty on failure
    std::vector<std::string> errors;  // "<file>: <problem>"
    bool ok() const { return errors.empty(); }
};

// The whole of `lsnif eval`: loads the scene, renders reference and hybrid images of every
// effect, compares them (lsnif::image: FLIP, PSNR) and writes the PNGs when asked.
EvalResult render_and_compare(const EvalOptions& opt);

// ---- the two tracers, exposed for tests and examples ----------------------------------

// Closest-hit record of a world-space ray. `instance` indexes the manifest's instances;
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

// A loaded scene: the manifest's instances over re-imported source geometry, with both
// tracers built. Thread-safe for concurrent trace calls.
class EvalScene {
public:
    // Loads OUTDIR/manifest.json, re-imports the sources (checking that every mesh's
    // geometry hash matches the manifest), opens the complex meshes' assets and builds
    // Embree scenes. Returns nullptr and fills `error` on failure.
    static std::unique_ptr<EvalScene> load(const EvalOptions& opt, std::string& error);
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
    struct Impl;

private:
    explicit EvalScene(std::unique_ptr<Impl> impl);
    std::unique_ptr<Impl> impl_;
    friend EvalResult render_and_compare(const EvalOptions& opt);
    friend class ObjectViews;
};

// `lsnif eval OUTDIR --objects`: every converted object of a conversion alone, in the views of
// its visual check (ObjectViews), through its shipped asset: the report lists each object's
// FLIP and image files (IMAGES/objects/<asset file stem>/view<K>_{reference,hybrid,flip}.png),
// the close-ups a report page shows. Errors as render_and_compare's.
EvalResult render_objects(const EvalOptions& opt);

// ---- one object, judged by how it looks -------------------------------------------------

// The visual acceptance test of a conversion (docs/model.md "Judged by how it looks"): the
// object alone on a floor, seen from `views` views drawn from `seed` (one per sector of the
// circle around the vertical axis +Y, at a random azimuth within it and 15 to 55 degrees
// above the floor, each framing the object's bounding sphere, lit by a point light at a
// random angle to the side and 35 to 75 degrees up), rendered as `lsnif eval` renders a
// scene: primary visibility from the mesh, then shadow, ambient-occlusion and
// mirror-reflection rays traced by Embree (the reference, once) and through a candidate
// asset (the floor stays Embree's in both), compared with FLIP. The last view traces the
// primary rays through the asset as well, so that its silhouette and shading normals are
// judged. Two sets of views drawn from different seeds never share a camera: the
// conversion decides on one (the decision views) and reports the other (the held-out views).
struct ObjectViewOptions {
    std::uint32_t width = 160, height = 120;  // per view
    std::uint32_t views = 3;                  // the last one all through the asset
    std::uint32_t ao_samples = 8;
    std::uint32_t threads = 0;  // 0 = hardware threads; the images do not depend on it
    std::uint64_t seed = 1;     // draws the cameras, the lights and the AO directions
};

// FLIP (LDR-FLIP, lsnif::image) of a candidate's combined renders (AO, shadowed light, mirror
// coat) against the reference over a set of views. The object's pixels are those where the
// mesh or (in the view traced through the asset) the asset is what the camera sees; their
// errors are pooled over the views. The effects alone are not compared: the combined image
// holds them, and each comparison is a FLIP of every view.
struct ObjectFlip {
    double combined_object = 0;      // over the object's pixels: mean
    double combined_object_p95 = 0;  // and 95th percentile
    double combined = 0;  // over the whole frame, background and floor included: mean over the views
};

class ObjectViews {
public:
    // The object (object space: positions xyz, triangle indices, per-vertex shading normals,
    // as a converted mesh holds them) on its floor, with the reference images of every view.
    // Null with `error` when Embree cannot build it.
    static std::unique_ptr<ObjectViews> create(std::span<const float> positions,
                                               std::span<const std::uint32_t> indices,
                                               std::span<const float> normals,
                                               const ObjectViewOptions& options, std::string& error);
    ~ObjectViews();
    // The views traced through `asset` (a serialized .lsnif of this object), against the
    // reference; an error when the asset cannot be opened. Not for concurrent calls.
    base::Result<ObjectFlip, std::string> compare(std::span<const std::uint8_t> asset) const;
    // The same, and every view's combined images as PNGs in `dir` (created):
    // view<K>_reference.png, view<K>_hybrid.png, view<K>_flip.png (FLIP heat map), K from 0;
    // the last view's "hybrid" is traced all through the asset.
    base::Result<ObjectFlip, std::string> compare(std::span<const std::uint8_t> asset,
                                                  const std::string& dir) const;
    std::uint32_t view_count() const;

private:
    struct State;
    explicit ObjectViews(std::unique_ptr<State> state);
    std::unique_ptr<State> state_;
};

}  // namespace lsnif::converter
