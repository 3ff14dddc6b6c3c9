// The enclosed rule (lsnif_set_enclosed_rule): the voxels a closed shell shuts in, and on real
// assets the occlusion rays whose walk crosses into them after an occupied voxel are
// occluded, checked against every voxel each ray crosses; every other answer keeps its bits.
#include <doctest/doctest.h>
#include <lsnif/lsnif.h>
#include <lsnif/format/container.hpp>
#include <lsnif/format/forward.hpp>

#include "asset_rays.hpp"

#include <cstring>
#include <filesystem>
#include <span>
#include <string>
#include <vector>

namespace fs = std::filesystem;
namespace fmt = lsnif::format;
using lsnif_test::make_rays;
using lsnif_test::OpenModel;

namespace {

// An OCCU bit array of a V^3 grid whose occupied voxels are the surface of the cube [lo, hi]^3
// (the voxels with a coordinate on lo or hi), less the voxel `hole` (none: V^3).
std::vector<std::uint8_t> cube_shell(std::uint32_t V, std::uint32_t lo, std::uint32_t hi,
                                     std::uint64_t hole) {
    std::vector<std::uint8_t> bits((std::uint64_t(V) * V * V + 7) / 8, 0);
    for (std::uint32_t z = lo; z <= hi; ++z)
        for (std::uint32_t y = lo; y <= hi; ++y)
            for (std::uint32_t x = lo; x <= hi; ++x) {
                const bool surface = x == lo || x == hi || y == lo || y == hi || z == lo || z == hi;
                const std::uint64_t i = x + std::uint64_t(V) * (y + std::uint64_t(V) * z);
                if (surface && i != hole) bits[i >> 3] |= std::uint8_t(1u << (i & 7));
            }
    return bits;
}

std::uint64_t count_bits(const std::vector<std::uint64_t>& words) {
    std::uint64_t n = 0;
    for (const std::uint64_t w : words) n += std::uint64_t(__builtin_popcountll(w));
    return n;
}

// The rule from every voxel the ray crosses, one by one (no block skipped): among the voxels
// before its H-th occupied one, an enclosed one (OccupancyGrid::enclosed) after an occupied
// one, and none before the first occupied one.
bool crosses_into_enclosed(const fmt::Geometry& geo, const fmt::OccupancyGrid& occ, const fmt::Ray& ray) {
    std::vector<std::uint32_t> voxels;
    std::vector<float> entry_t;
    if (fmt::trace_all_voxels(geo, ray, voxels, entry_t) != fmt::TraceStatus::ok) return false;
    const std::uint32_t V = geo.V;
    std::uint32_t met = 0;
    for (std::size_t j = 0; j < voxels.size() && met < geo.H; ++j) {
        const std::uint32_t x = voxels[j] % V, y = voxels[j] / V % V, z = voxels[j] / V / V;
        if (occ.occupied(x, y, z))
            ++met;
        else if (occ.enclosed(x, y, z))
            return met > 0;
    }
    return false;
}

// Every empty voxel of the grid the enclosed rule stops at.
std::uint64_t marked_voxels(const fmt::OccupancyGrid& occ) {
    std::uint64_t n = 0;
    for (std::uint32_t z = 0; z < occ.V; ++z)
        for (std::uint32_t y = 0; y < occ.V; ++y)
            for (std::uint32_t x = 0; x < occ.V; ++x) n += occ.enclosed(x, y, z);
    return n;
}

}  // namespace

TEST_CASE("enclosed voxels are the empty ones a closed shell shuts in, and none once it has a hole") {
    for (const std::uint32_t V : {16u, 12u}) {
        CAPTURE(V);
        // A shell away from the grid's boundary whose inside is whole 2^3 blocks.
        const std::uint32_t lo = 3, hi = V - 4;
        fmt::OccupancyGrid closed(V, cube_shell(V, lo, hi, std::uint64_t(V) * V * V));
        const std::vector<std::uint64_t> inside = fmt::enclosed_voxels(closed);
        const std::uint32_t n = hi - lo - 1;
        CHECK(count_bits(inside) == std::uint64_t(n) * n * n);
        for (std::uint32_t z = 0; z < V; ++z)
            for (std::uint32_t y = 0; y < V; ++y)
                for (std::uint32_t x = 0; x < V; ++x) {
                    const bool interior = x > lo && x < hi && y > lo && y < hi && z > lo && z < hi;
                    if (fmt::voxel_bit(inside.data(), x + V * (y + V * z)) != interior) {
                        FAIL_CHECK("voxel " << x << "," << y << "," << z << " misclassified");
                        break;
                    }
                }
        CHECK(marked_voxels(closed) == 0);  // until the rule marks them
        closed.mark_enclosed(true);
        CHECK(marked_voxels(closed) == std::uint64_t(n) * n * n);
        CHECK(closed.occupied_voxels() ==
              fmt::OccupancyGrid(V, cube_shell(V, lo, hi, V * V * V)).occupied_voxels());
        // Rays along x through the shell's middle, on a grid of unit voxels from the origin.
        fmt::Geometry geo{};
        geo.V = V;
        geo.H = 14;
        for (int a = 0; a < 3; ++a) {
            geo.box_min[a] = 0.0f;
            geo.box_max[a] = float(V);
            geo.cell[a] = 1.0f;
        }
        const float mid = 0.5f * float(lo + hi) + 0.3f;
        // Whether the walk stops in the inside, by the scalar walk and by the batch of two
        // rays (the 16-lane walk where the CPU has it), which must agree.
        const auto takes = [&](float x0, float tmax) {
            const fmt::Ray ray{{x0, mid, mid + 0.1f}, 0.0f, {1.0f, 0.0f, 0.0f}, tmax};
            fmt::RayPoints pts, both[2];
            const fmt::TraceStatus st = fmt::trace_points(geo, closed, ray, pts, true);
            const fmt::Ray pair[2] = {ray, ray};
            fmt::TraceStatus batch[2];
            fmt::trace_points_batch(geo, closed, pair, both, batch, true);
            CHECK(batch[0] == st);
            CHECK(both[1].count == pts.count);
            CHECK(fmt::trace_points(geo, closed, ray, pts) != fmt::TraceStatus::enclosed);  // only if asked
            return st == fmt::TraceStatus::enclosed;
        };
        CHECK(takes(-1.0f, INFINITY));                     // from outside: through the shell into it
        CHECK_FALSE(takes(-1.0f, float(lo) + 1.5f));       // the segment ends in the shell voxel
        CHECK_FALSE(takes(float(lo + hi) / 2, INFINITY));  // from inside: it may stay inside
        CHECK(takes(float(lo) + 0.5f, INFINITY));          // from the shell voxel itself
        closed.mark_enclosed(false);
        CHECK(marked_voxels(closed) == 0);
        CHECK_FALSE(takes(-1.0f, INFINITY));
        // One shell voxel less: the inside joins the outside through it.
        const std::uint64_t hole =
            lo + std::uint64_t(V) * ((lo + hi) / 2 + std::uint64_t(V) * ((lo + hi) / 2));
        CHECK(count_bits(fmt::enclosed_voxels(fmt::OccupancyGrid(V, cube_shell(V, lo, hi, hole)))) == 0);
    }
}

TEST_CASE(
    "the enclosed rule: occlusion rays that cross into shut-in voxels are occluded, the rest keep their "
    "bits") {
    for (const std::string name : {"armadillo_fp16.lsnif", "peterbilt_u8.lsnif"}) {
        CAPTURE(name);
        const fs::path path = fs::path(LSNIF_CONFORMANCE_DIR) / name;
        OpenModel m(path);
        CHECK(lsnif_get_enclosed_rule(m.model) == 0);  // off as opened
        lsnif_info off_info{};
        REQUIRE(lsnif_get_info(m.model, &off_info) == LSNIF_OK);
        std::vector<lsnif_ray> outside, leaving;
        make_rays(m.model, outside, leaving);
        fmt::Runtime rt = lsnif_test::runtime_of(path);
        rt.occupancy.mark_enclosed(true);
        for (const auto* set : {&outside, &leaving}) {
            const std::vector<lsnif_ray>& rays = *set;
            CAPTURE((set == &outside ? "rays from outside" : "rays leaving the surface"));
            const std::span<const fmt::Ray> object_rays(reinterpret_cast<const fmt::Ray*>(rays.data()),
                                                        rays.size());
            std::vector<fmt::RayPoints> pts(rays.size());
            std::vector<fmt::TraceStatus> status(rays.size());
            fmt::trace_points_batch(rt.geo, rt.occupancy, object_rays, pts.data(), status.data(), true);
            REQUIRE(lsnif_set_enclosed_rule(m.model, 0) == LSNIF_OK);
            std::vector<lsnif_hit> exact(rays.size());
            std::vector<std::uint8_t> exact_occ(rays.size());
            REQUIRE(lsnif_intersect(m.model, rays.data(), rays.size(), exact.data()) == LSNIF_OK);
            REQUIRE(lsnif_occluded(m.model, rays.data(), rays.size(), exact_occ.data()) == LSNIF_OK);
            REQUIRE(lsnif_set_enclosed_rule(m.model, 1) == LSNIF_OK);
            CHECK(lsnif_get_enclosed_rule(m.model) == 1);
            std::vector<lsnif_hit> hits(rays.size());
            std::vector<std::uint8_t> occ(rays.size(), 7);
            REQUIRE(lsnif_intersect(m.model, rays.data(), rays.size(), hits.data()) == LSNIF_OK);
            REQUIRE(lsnif_occluded(m.model, rays.data(), rays.size(), occ.data()) == LSNIF_OK);
            std::size_t taken = 0, disagree = 0, scalar_differs = 0, wrong = 0, turned = 0;
            for (std::size_t i = 0; i < rays.size(); ++i) {
                const bool rule = status[i] == fmt::TraceStatus::enclosed;
                taken += rule;
                disagree += rule != crosses_into_enclosed(rt.geo, rt.occupancy, object_rays[i]);
                fmt::RayPoints one;
                const fmt::TraceStatus st =
                    fmt::trace_points(rt.geo, rt.occupancy, object_rays[i], one, true);
                scalar_differs += st != status[i] || one.count != pts[i].count;
                wrong +=
                    std::memcmp(&hits[i], &exact[i], sizeof(lsnif_hit)) != 0;  // intersections never change
                wrong += occ[i] != (rule ? 1 : exact_occ[i]);
                turned += rule && !exact_occ[i];
            }
            CHECK(wrong == 0);
            CHECK(disagree == 0);
            CHECK(scalar_differs == 0);
            if (set == &leaving && name == "armadillo_fp16.lsnif") CHECK(taken > rays.size() / 50);
            MESSAGE(name << ": the rule takes " << taken << " of " << rays.size() << " rays (" << turned
                         << " the network called misses)");
        }
        // The rule's marks live in the occupancy's spare bits: no memory while it is on.
        lsnif_info on_info{};
        REQUIRE(lsnif_get_info(m.model, &on_info) == LSNIF_OK);
        CHECK(on_info.decoded_bytes == off_info.decoded_bytes);
        REQUIRE(lsnif_set_enclosed_rule(m.model, 0) == LSNIF_OK);
        CHECK(lsnif_get_enclosed_rule(m.model) == 0);
    }
    CHECK(lsnif_set_enclosed_rule(nullptr, 1) == LSNIF_ERR_INVALID_ARGUMENT);
    CHECK(lsnif_get_enclosed_rule(nullptr) == 0);
}
