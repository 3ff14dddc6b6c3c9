// Held-out metrics (docs/architecture.md §5): how well a model answers ground-truth rays
// it was not trained on, per ray family and pooled. Runs the reader's forward pass
// (format::intersect), so the numbers are what a renderer will see.
#pragma once

#include <lsnif/format/forward.hpp>
#include <lsnif/samples/sample.hpp>

#include <array>
#include <cstdint>
#include <span>

namespace lsnif::samples {

struct FamilyMetrics {
    std::uint64_t rays = 0;    // rays that reached the network
    std::uint64_t culled = 0;  // rays culled by occupancy (certain misses)
    double visibility_accuracy = 0;
    double false_hit_rate = 0;       // predicted hit among true misses
    double false_miss_rate = 0;      // predicted miss among true hits
    double distance_median_pct = 0;  // |Δt| in % of the box diagonal, on true & predicted hits
    double distance_p95_pct = 0;
    double normal_median_deg = 0;  // against the shading normal
    double normal_p95_deg = 0;
    double geometric_normal_median_deg = 0;  // against the faceted normal, when provided
    double culled_fraction = 0;              // culled / (culled + rays)
    std::uint64_t culled_true_hits = 0;      // must be 0: a culled ray that truly hits
};

struct Metrics {
    FamilyMetrics family[kFamilyCount];
    FamilyMetrics pooled;  // the three families in equal shares
};

// Runs the reader-side forward pass on `samples` with `threads` threads (0 = all hardware
// threads) and compares it against their ground truth. `geometric_normals` (optional, one
// per sample, parallel to `samples`) adds the error against the faceted normal, reported
// beside the shading one. The result depends on the samples only, not on the thread count.
Metrics held_out_metrics(const format::Runtime& rt, std::span<const Sample> samples,
                         std::uint32_t threads = 0,
                         std::span<const std::array<float, 3>> geometric_normals = {});

}  // namespace lsnif::samples
