// Analytic ground truth: a set of spheres with exact ray intersection, conservative
// occupancy and shading normals. Test and benchmark support: lets the trainer be tested
// (tests/trainer) and benchmarked (lsnif bench train|infer) end to end without Embree or a
// mesh. The converter feeds the trainer from Embree through the same SampleSource.
#pragma once

#include <lsnif/format/container.hpp>
#include <lsnif/format/forward.hpp>
#include <lsnif/samples/sample.hpp>

#include <array>
#include <cstdint>

#include <vector>

namespace lsnif::analytic {

struct Sphere {
    float center[3];
    float radius;
};

class SpheresSource final : public samples::SampleSource {
public:
    // `box_min/box_max` is the model box; spheres must lie inside it. `shadow_fraction`
    // of the rays get a finite tmax (shadow-like rays).
    SpheresSource(std::vector<Sphere> spheres, std::array<float, 3> box_min, std::array<float, 3> box_max,
                  float shadow_fraction = 0.25f);

    // Families cycle per index: outside, surface, interior (docs/architecture.md §3 "Training").
    void generate(std::uint64_t seed, std::size_t count, std::vector<samples::Sample>& out) override;

    // Exact nearest hit in [tmin, tmax]; returns false on a miss.
    bool intersect(const format::Ray& ray, float& t, float normal[3]) const;

    // Conservative occupancy of the sphere surfaces on desc's grid (closed voxels).
    std::vector<std::uint8_t> occupancy(const format::ModelDesc& desc) const;

    const std::vector<Sphere>& spheres() const { return spheres_; }

private:
    std::vector<Sphere> spheres_;
    std::array<float, 3> lo_, hi_;
    float shadow_fraction_;
};

}  // namespace lsnif::analytic
