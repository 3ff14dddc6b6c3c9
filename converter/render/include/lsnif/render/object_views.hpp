// One object, judged by how it looks: the visual acceptance test of a conversion
// (docs/model.md "Judged by how it looks"). The object alone on a floor, seen from `views`
// views drawn from `seed` (one per sector of the circle around the vertical axis +Y, at a
// random azimuth within it and 15 to 55 degrees above the floor, each framing the object's
// bounding sphere, lit by a point light at a random angle to the side and 35 to 75 degrees
// up), rendered as `lsnif eval` renders a scene (render.hpp): primary visibility from the
// mesh, then shadow, ambient-occlusion and mirror-reflection rays traced by Embree (the
// reference, once) and through a candidate asset (the floor stays Embree's in both),
// compared with FLIP. The last view traces the primary rays through the asset as well, so
// that its silhouette and shading normals are judged. Two sets of views drawn from different
// seeds never share a camera: the conversion decides on one (the decision views) and reports
// the other (the held-out views).
#pragma once

#include <lsnif/base/result.hpp>

#include <cstdint>
#include <memory>
#include <span>
#include <string>

namespace lsnif::render {

struct ObjectViewOptions {
    std::uint32_t width = 160, height = 120;  // per view
    std::uint32_t views = 3;                  // the last one all through the asset
    std::uint32_t ao_samples = 8;
    std::uint32_t threads = 0;  // 0 = hardware threads; the images do not depend on it
    std::uint64_t seed = 1;     // draws the cameras, the lights and the AO directions
    // Embree's instruction set (its device's `isa=`): AVX2, the floor of the CPUs conversion
    // runs on, as sampling::SamplingConfig::embree_isa; tests set others ("sse4.2",
    // "avx512") to show the images do not depend on Embree's kernels.
    std::string embree_isa = "avx2";
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

}  // namespace lsnif::render
