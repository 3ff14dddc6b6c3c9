// The ground-truth ray: the one type the producer of training data (converter/sampling,
// Embree against the mesh) and its consumer (trainer/) share. Header-only apart from
// family_name(); depends on format/'s Ray and nothing else, so neither side includes the
// other (docs/architecture.md §2).
#pragma once

#include <lsnif/format/forward.hpp>

#include <cstddef>
#include <cstdint>
#include <vector>

namespace lsnif::samples {

// Ray families of docs/architecture.md §3.
enum class Family : std::uint8_t { outside = 0, surface = 1, interior = 2 };
inline constexpr int kFamilyCount = 3;
// "outside", "surface", "interior"; "?" for a value outside the enum.
const char* family_name(Family f);

// One ground-truth ray. t/normal/material are meaningful only when hit != 0.
struct Sample {
    format::Ray ray;
    float t;
    float normal[3];  // unit shading normal at the hit (orientation as in the mesh)
    std::uint32_t material;
    std::uint8_t hit;
    Family family;
};

// Where rays come from: Embree on a mesh in the converter (sampling::EmbreeSource),
// analytic spheres in tests and benchmarks (analytic::SpheresSource). generate() replaces
// `out` with `count` samples and must be deterministic for a given seed, whatever the
// thread count; successive seeds give independent draws.
class SampleSource {
public:
    virtual ~SampleSource() = default;
    virtual void generate(std::uint64_t seed, std::size_t count, std::vector<Sample>& out) = 0;
};

}  // namespace lsnif::samples
