// `lsnif eval`: renders a converted scene twice and compares the images (docs/architecture.md §5,
// "Images"), with the tracers and renders of lsnif::render: the reference traces every
// mesh with Embree, the hybrid the converted meshes through their assets.
//
// Contract: never throws, exits or prints; failures are returned as "<file>: <problem>"
// lines in EvalResult::errors, and no image is left half-written (PNGs go through a
// temporary file and a rename).
#pragma once

#include <lsnif/lsnif.h>
#include <lsnif/render/object_views.hpp>
#include <lsnif/render/render.hpp>
#include <lsnif/render/scene.hpp>

#include <nlohmann/json.hpp>

#include <array>
#include <cstdint>
#include <memory>
#include <optional>
#include <string>
#include <utility>
#include <vector>

namespace lsnif::eval {

// The render's settings (camera, light, size, AO, threads, seed, timing) and the conversion
// it renders.
struct EvalOptions : render::RenderOptions {
    std::string outdir;                // a conversion's OUTDIR (manifest.json + assets)
    std::vector<std::string> sources;  // the converted inputs; empty = the manifest's paths
    std::string images_dir;            // where PNGs and report.json go; "" = OUTDIR/eval
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
    // Both renders: every asset's escape rule (lsnif_set_escape_points; docs/model.md "The
    // escape rule"); none = the limit conversion chose for each asset (its manifest's
    // metrics.escape_points, 0 when absent); 0 = off.
    std::optional<std::uint32_t> escape_points;
    // Hybrid render only: every asset's enclosed rule (lsnif_set_enclosed_rule; docs/model.md
    // "The enclosed rule").
    bool enclosed_rule = true;
    // Both tracers: how Embree traces its part (render::EmbreeRoute; docs/eval.md "Timing").
    render::EmbreeRoute embree_route = render::EmbreeRoute::packets16;
};

// Seconds of each trace, summed over threads, each the fastest of the timing repeats.
struct EvalTimings {
    double primary = 0, primary_neural = 0;  // primary rays from the meshes / through the assets
    double secondary_reference = 0, secondary_hybrid = 0, secondary_neural = 0;
};

// What `lsnif eval` rendered and measured (docs/eval.md). eval_report_json writes it
// (report.json, --json); eval_report_text is what the command prints.
struct EvalReport {
    // How it rendered.
    render::AssetMemory memory;  // the opened assets against the BVHs they replace, their arithmetic
    std::uint32_t width = 0, height = 0;
    std::uint32_t ao_samples = 0;
    float ao_radius = 0;  // AO ray length, world units
    float surface_tmin_voxels = 0;
    std::optional<std::uint32_t> escape_points;                         // as EvalOptions::escape_points
    bool enclosed_rule = true;                                          // as EvalOptions::enclosed_rule
    render::EmbreeRoute embree_route = render::EmbreeRoute::packets16;  // as EvalOptions::embree_route
    std::uint32_t timing_repeats = 0;
    render::Camera camera;
    render::Vec3 light{};
    std::size_t instances = 0, lsnif_instances = 0;
    // What it measured: the hybrid render and the all-neural one (primary rays through the
    // assets too), each against the reference, over the frame and over their asset pixels.
    render::Comparison hybrid, neural;
    std::size_t lsnif_pixels = 0, neural_lsnif_pixels = 0;
    EvalTimings timings;
    render::SecondaryProfile reference_profile, hybrid_profile;
    std::string images_dir;

    double secondary_time_ratio() const;  // hybrid over reference secondary-ray time; 0 unmeasured
    double neural_time_ratio() const;     // all-neural over reference, primary and secondary; 0 unmeasured
};
nlohmann::json eval_report_json(const EvalReport& report);
std::string eval_report_text(const EvalReport& report);

struct EvalResult {
    std::optional<EvalReport> report;  // none on failure
    std::vector<std::string> errors;   // "<file>: <problem>"
    bool ok() const { return errors.empty(); }
};

// The whole of `lsnif eval`: loads the scene, renders reference and hybrid images of every
// effect, compares them (lsnif::image: FLIP, PSNR) and writes the PNGs when asked.
EvalResult render_and_compare(const EvalOptions& opt);

// The converted scene of opt.outdir with both tracers built: the manifest's instances (moved
// by opt.instance_transforms) over re-imported source geometry (every mesh's geometry hash
// checked against the manifest), the complex meshes traced through their shipped assets in
// opt.arithmetic by the hybrid tracer. Null with `error` on failure.
std::unique_ptr<render::EvalScene> load_scene(const EvalOptions& opt, std::string& error);

// `lsnif eval OUTDIR --objects`: every converted object of a conversion alone, in the views of
// its visual check (render::ObjectViews), through its shipped asset: the report lists each
// object's FLIP and image files (IMAGES/objects/<asset file stem>/view<K>_{reference,hybrid,flip}.png),
// the close-ups a report page shows. Errors as render_and_compare's.
struct ObjectImages {
    std::string name;        // the mesh's
    std::uint64_t mesh = 0;  // its id in the manifest
    std::string asset;       // its asset file, relative to OUTDIR
    render::ObjectFlip flip;
    std::vector<std::array<std::string, 3>>
        views;  // per view: reference, hybrid and FLIP PNG, relative to images_dir
};
struct ObjectsReport {
    std::vector<ObjectImages> objects;
    std::string images_dir;
    std::uint32_t views = 0, width = 0, height = 0, ao_samples = 0;
};
nlohmann::json objects_report_json(const ObjectsReport& report);
std::string objects_report_text(const ObjectsReport& report);
struct ObjectsResult {
    std::optional<ObjectsReport> report;  // none on failure
    std::vector<std::string> errors;      // "<file>: <problem>"
    bool ok() const { return errors.empty(); }
};
ObjectsResult render_objects(const EvalOptions& opt);

}  // namespace lsnif::eval
