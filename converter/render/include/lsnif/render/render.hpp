// Images of a scene through both tracers (scene.hpp), as `lsnif eval` renders them
// (docs/eval.md "The renders"): primary visibility from the real meshes through Embree
// (standing in for the paper's rasterized G-buffer: vertex and face data stay exact), or
// through the assets too; then shadow rays to a point light, ambient-occlusion rays and
// mirror reflections traced by the reference and the hybrid tracer; the effects one at a
// time and combined, compared with FLIP and PSNR (lsnif::image). Camera, light and
// instance transforms are inputs of the render, not of the conversion: they can change
// without touching the assets.
//
// Contract: never throws, exits or prints; failures are returned as `error` text, and no
// image is left half-written (PNGs go through a temporary file and a rename).
#pragma once

#include <lsnif/image/flip.hpp>
#include <lsnif/render/scene.hpp>

#include <array>
#include <cstdint>
#include <filesystem>
#include <optional>
#include <string>
#include <vector>

namespace lsnif::render {

using Vec3 = std::array<float, 3>;

struct Camera {
    Vec3 eye{}, target{}, up{0.0f, 1.0f, 0.0f};
    float fov_deg = 40.0f;  // vertical field of view
};

// What a render looks like and how it is timed.
struct RenderOptions {
    std::uint32_t width = 480, height = 360;
    std::optional<Camera> camera;   // default frames the bounds given to make_view
    std::optional<Vec3> light;      // point light; default above and in front
    std::uint32_t ao_samples = 16;  // cosine-distributed rays per pixel
    float ao_radius = 0.1f;         // AO ray length, fraction of the bounds' diagonal
    std::uint32_t threads = 0;      // 0 = hardware threads
    std::uint64_t seed = 1;         // the AO directions
    // Times each row's secondary rays this many times per tracer (the two alternating) and
    // keeps each tracer's fastest: the time ratio then leaves out the stalls a shared host
    // puts into one run (docs/eval.md "Timing"). Both tracers are deterministic, so every
    // repeat gives the same images. >= 1.
    std::uint32_t timing_repeats = 3;
};

// The three effects one at a time, then their combination (docs/eval.md "The renders").
enum Effect { kShadow, kAo, kReflection, kCombined, kEffects };
inline constexpr int kSeparateEffects = kCombined;  // what a comparison's flip_mean averages
inline constexpr const char* kEffectNames[kEffects] = {"shadow", "ao", "reflection", "combined"};

// The camera and light of a render: the options' or, by default, framing the bounds given.
struct View {
    Camera cam;
    Vec3 light, fwd, right, up;
    float tan_half, aspect;
    float diag;  // the bounds' diagonal
    std::uint32_t W, H;
};
View make_view(const RenderOptions& opt, const std::array<float, 6>& bounds);

// Primary visibility: position, camera-facing shading normal, instance (-1: background) and
// secondary-ray offset of every pixel. From the real meshes through Embree (standing in for a
// rasterized G-buffer), or with `through_assets` from the hybrid tracer: the meshes with an
// asset answered by it, the others by Embree (the paper's "all types of rays").
struct GBuffer {
    std::vector<Vec3> p, n;
    std::vector<std::int32_t> inst;
    std::vector<float> eps;
    double trace_seconds = 0;  // tracing the primary rays, summed over threads
};
GBuffer render_primary(const EvalScene& scene, const View& v, std::uint32_t threads,
                       bool through_assets = false);

// The three families of secondary rays, in the order a row traces them.
inline constexpr int kRayFamilies = 3;
inline constexpr const char* kRayFamilyNames[kRayFamilies] = {"shadow", "ao", "reflection"};
using SecondaryProfile = std::array<TraceProfile, kRayFamilies>;

// Linear RGB images of the effects from one tracer, and the time its secondary rays took
// (summed over threads).
struct EffectImages {
    std::vector<float> rgb[kEffects];
    double trace_seconds = 0;
    SecondaryProfile profile;  // of the traces trace_seconds counts (each row's fastest)
};
struct BothImages {
    EffectImages reference, hybrid;
};
// Which tracers render_secondary runs: both (lsnif eval), or one of them (a reference
// rendered once, then one hybrid per candidate model).
enum class Tracers { both, reference, hybrid };
// The three effect images and their combination, traced row by row with the tracers asked
// for: the reference (Embree only) and the hybrid (the reader for meshes with an asset),
// whose secondary rays from asset pixels start `surface_tmin` (per instance, world units;
// empty = at the surface) from it. The traces of a row run back to back on one thread,
// alternating between the tracers RenderOptions::timing_repeats times, and each tracer's
// fastest counts: the machine's drifts (shared hosts, frequency) hit both sides of the time
// ratio alike, and a stall that hits one trace is left out.
BothImages render_secondary(const EvalScene& scene, const GBuffer& gb, const View& v,
                            const RenderOptions& opt, const std::vector<float>& surface_tmin,
                            std::uint32_t threads, Tracers tracers = Tracers::both);

// Secondary rays leaving an asset instance's surface started `voxels` of its occupancy
// voxels (edge length in world units: the model box's largest extent over its grid
// resolution, times the instance transform's largest axis scale) away from it: the runtime
// treatment docs/investigations/surface-leaving-rays.md measures, per instance for
// render_secondary (0 for instances not traced through an asset). Empty when `voxels` is 0:
// the option is off.
std::vector<float> surface_tmins(const EvalScene& scene, float voxels);

// One effect's reference and test images compared (sRGB-encoded): FLIP over the frame,
// PSNR (infinite for identical images), FLIP over the asset pixels (their statistics, none
// when there are none, and the errors themselves, so that several views pool them), and the
// PNG files written (reference, test, FLIP heat map), if any.
struct EffectComparison {
    image::FlipStats flip;
    double psnr_db = 0;
    std::optional<image::FlipStats> flip_lsnif_pixels;
    std::vector<float> lsnif_pixel_errors;
    std::vector<std::string> files;
};
struct Comparison {
    EffectComparison effect[kEffects];
    double flip_mean = 0;  // over the separate effects (shadow, AO, reflection)
};
// Compares effect `e` (kShadow ... kCombined) into `c`; writes its PNGs into `images` when
// write_images, named as compare_effects names them. False with `error` when FLIP or a file
// fails.
bool compare_effect(const EffectImages& reference, const EffectImages& test, const View& v, int e,
                    const std::vector<std::uint8_t>& lsnif_pixels, const std::filesystem::path& images,
                    bool write_images, EffectComparison& c, std::string& error,
                    const std::string& label = "hybrid");
// Compares every effect; writes the PNGs into `images` when write_images, named
// reference_<effect>.png, <label>_<effect>.png and flip_<effect>.png (flip_<label>_<effect>.png
// for a label other than "hybrid"). False with `error` when FLIP or a file fails.
bool compare_effects(const EffectImages& reference, const EffectImages& test, const View& v,
                     const std::vector<std::uint8_t>& lsnif_pixels, const std::filesystem::path& images,
                     bool write_images, Comparison& out, std::string& error,
                     const std::string& label = "hybrid");

// 1 for the pixels whose primary hit is an instance the hybrid tracer traces through an asset.
std::vector<std::uint8_t> lsnif_pixel_mask(const GBuffer& gb, const EvalScene& scene);
// The pixels either mask selects: an object's pixels where the mesh and its asset, each
// seen by its own primary rays, may disagree on its silhouette.
std::vector<std::uint8_t> mask_union(const std::vector<std::uint8_t>& a, const std::vector<std::uint8_t>& b);

}  // namespace lsnif::render
