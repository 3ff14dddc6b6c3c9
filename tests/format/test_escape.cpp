// The escape rule (lsnif_set_escape_points): on real assets, rays leaving the surface that
// stay within one face-connected run of at most N occupied voxels are misses, every other ray
// keeps its bits, and rays that enter the grid from outside never escape.
#include <doctest/doctest.h>
#include <lsnif/lsnif.h>
#include <lsnif/format/container.hpp>
#include <lsnif/format/forward.hpp>

#include "asset_rays.hpp"

#include <array>
#include <cmath>
#include <cstdlib>
#include <cstring>
#include <filesystem>
#include <random>
#include <string>
#include <vector>

namespace fs = std::filesystem;
namespace fmt = lsnif::format;
using lsnif_test::make_rays;
using lsnif_test::OpenModel;

namespace {

// The voxel coordinates of linear index v in a V^3 grid (x fastest).
std::array<int, 3> voxel_xyz(std::uint32_t v, std::uint32_t V) {
    return {int(v % V), int((v / V) % V), int(v / (V * V))};
}

// The rule as docs/model.md states it, from the trace: the ray starts inside its first
// occupied voxel, meets at most `limit` of them, and each is the previous one's face
// neighbour (coordinates one apart on one axis).
bool rule_takes(const fmt::RayPoints& pts, const lsnif_ray& ray, std::uint32_t limit, std::uint32_t V) {
    if (pts.count == 0 || pts.count > limit || pts.t[0] > ray.tmin) return false;
    for (std::uint32_t k = 1; k < pts.count; ++k) {
        const auto a = voxel_xyz(pts.voxel[k - 1], V), b = voxel_xyz(pts.voxel[k], V);
        if (std::abs(a[0] - b[0]) + std::abs(a[1] - b[1]) + std::abs(a[2] - b[2]) != 1) return false;
    }
    return true;
}

}  // namespace

TEST_CASE("the escape rule takes a ray's occupied voxels only as one run of face neighbours") {
    fmt::Geometry geo{};
    geo.V = 64;
    const auto index = [](std::uint32_t x, std::uint32_t y, std::uint32_t z) {
        return x + 64 * (y + 64 * z);
    };
    fmt::Ray ray{};
    ray.tmin = 0.25f;
    const auto trace = [&](std::initializer_list<std::uint32_t> voxels, float t0) {
        fmt::RayPoints pts;
        for (const std::uint32_t v : voxels) {
            pts.t[pts.count] = t0 + float(pts.count);
            pts.voxel[pts.count++] = v;
        }
        return pts;
    };
    const fmt::RayPoints run = trace({index(5, 7, 9), index(6, 7, 9), index(6, 7, 8)}, 0.25f);
    CHECK(fmt::escapes(geo, run, ray, 3));
    CHECK_FALSE(fmt::escapes(geo, run, ray, 2));  // more voxels than the limit
    CHECK_FALSE(fmt::escapes(geo, run, ray, 0));  // off
    CHECK_FALSE(fmt::escapes(geo, trace({index(5, 7, 9), index(6, 7, 9)}, 0.5f), ray, 3));  // starts outside
    CHECK_FALSE(
        fmt::escapes(geo, trace({index(5, 7, 9), index(7, 7, 9)}, 0.25f), ray, 3));  // an empty voxel between
    CHECK_FALSE(
        fmt::escapes(geo, trace({index(5, 7, 9), index(6, 8, 9)}, 0.25f), ray, 3));  // an edge, not a face
    // Linear indices one apart across a row's end are not neighbours.
    CHECK_FALSE(fmt::escapes(geo, trace({index(63, 7, 9), index(0, 8, 9)}, 0.25f), ray, 3));
    CHECK_FALSE(fmt::escapes(geo, trace({index(0, 63, 9), index(0, 0, 10)}, 0.25f), ray, 3));
    CHECK(fmt::escapes(geo, trace({index(0, 7, 9), index(0, 7, 10)}, 0.25f), ray, 3));
    CHECK_FALSE(fmt::escapes(geo, trace({}, 0.25f), ray, 3));  // meets no occupied voxel: culled, not escaped
    // A grid side that is not a power of two.
    geo.V = 48;
    const auto at48 = [](std::uint32_t x, std::uint32_t y, std::uint32_t z) { return x + 48 * (y + 48 * z); };
    CHECK(fmt::escapes(geo, trace({at48(46, 7, 9), at48(47, 7, 9), at48(47, 8, 9), at48(47, 8, 10)}, 0.25f),
                       ray, 4));
    CHECK_FALSE(fmt::escapes(geo, trace({at48(47, 7, 9), at48(0, 8, 9)}, 0.25f), ray, 3));
    CHECK_FALSE(fmt::escapes(geo, trace({at48(3, 47, 9), at48(3, 0, 10)}, 0.25f), ray, 3));
    CHECK_FALSE(fmt::escapes(geo, trace({at48(3, 7, 9), at48(3, 9, 9)}, 0.25f), ray, 3));
}

TEST_CASE(
    "the escape rule: rays leaving the surface within N occupied voxels miss, all others keep their bits") {
    for (const std::string name : {"armadillo_fp16.lsnif", "peterbilt_u8.lsnif"}) {
        CAPTURE(name);
        const fs::path path = fs::path(LSNIF_CONFORMANCE_DIR) / name;
        OpenModel m(path);
        lsnif_info info{};
        REQUIRE(lsnif_get_info(m.model, &info) == LSNIF_OK);
        CHECK(lsnif_get_escape_points(m.model) == 0);  // off as opened
        std::vector<lsnif_ray> outside, leaving;
        make_rays(m.model, outside, leaving);
        REQUIRE(leaving.size() > 1000);
        // Each ray's trace, from the same file, to know which rays the rule may take.
        const fmt::Runtime rt = lsnif_test::runtime_of(path);
        const auto traces = [&](const std::vector<lsnif_ray>& rays) {
            std::vector<fmt::RayPoints> pts(rays.size());
            std::vector<fmt::TraceStatus> status(rays.size());
            fmt::trace_points_batch(rt.geo, rt.occupancy,
                                    {reinterpret_cast<const fmt::Ray*>(rays.data()), rays.size()}, pts.data(),
                                    status.data());
            return pts;
        };
        const std::vector<fmt::RayPoints> pts_leaving = traces(leaving), pts_outside = traces(outside);
        for (const auto* set : {&outside, &leaving}) {
            const std::vector<lsnif_ray>& rays = *set;
            const std::vector<fmt::RayPoints>& pts = set == &outside ? pts_outside : pts_leaving;
            const std::string kind = set == &outside ? "rays from outside" : "rays leaving the surface";
            CAPTURE(kind);
            REQUIRE(lsnif_set_escape_points(m.model, 0) == LSNIF_OK);
            std::vector<lsnif_hit> exact(rays.size());
            REQUIRE(lsnif_intersect(m.model, rays.data(), rays.size(), exact.data()) == LSNIF_OK);
            for (const std::uint32_t limit : {1u, 2u, 3u}) {
                CAPTURE(limit);
                REQUIRE(lsnif_set_escape_points(m.model, limit) == LSNIF_OK);
                CHECK(lsnif_get_escape_points(m.model) == limit);
                std::vector<lsnif_hit> hits(rays.size());
                std::vector<std::uint8_t> occ(rays.size(), 7);
                REQUIRE(lsnif_intersect(m.model, rays.data(), rays.size(), hits.data()) == LSNIF_OK);
                REQUIRE(lsnif_occluded(m.model, rays.data(), rays.size(), occ.data()) == LSNIF_OK);
                std::size_t escaped = 0, changed = 0, wrong = 0, gapped = 0;
                for (std::size_t i = 0; i < rays.size(); ++i) {
                    const bool escapes = rule_takes(pts[i], rays[i], limit, info.grid_resolution);
                    escaped += escapes;
                    gapped +=
                        !escapes && pts[i].count > 1 && pts[i].count <= limit && pts[i].t[0] <= rays[i].tmin;
                    if (escapes) {
                        changed += exact[i].hit;
                        wrong += hits[i].hit != 0 || occ[i] != 0;
                    } else {
                        wrong += std::memcmp(&hits[i], &exact[i], sizeof(lsnif_hit)) != 0 ||
                                 occ[i] != exact[i].hit;
                    }
                }
                CHECK(wrong == 0);
                if (set == &outside) {
                    CHECK(escaped == 0);  // a ray entering the grid from outside never escapes
                } else {
                    CHECK(escaped > rays.size() / 20);  // the rule took real work
                    if (limit > 1) CHECK(gapped > 0);   // and left rays that meet a second surface
                    MESSAGE(name << ", limit " << limit << ": " << escaped << " of " << rays.size()
                                 << " rays leaving the surface escape (" << gapped
                                 << " more within the limit meet occupied voxels again after a gap); the "
                                    "network called "
                                 << changed << " of them hits");
                }
            }
        }
        CHECK(lsnif_set_escape_points(m.model, info.max_points) == LSNIF_OK);
        CHECK(lsnif_set_escape_points(m.model, info.max_points + 1) == LSNIF_ERR_INVALID_ARGUMENT);
        CHECK(lsnif_get_escape_points(m.model) == info.max_points);  // unchanged by the refused call
    }
    CHECK(lsnif_set_escape_points(nullptr, 1) == LSNIF_ERR_INVALID_ARGUMENT);
    CHECK(lsnif_get_escape_points(nullptr) == 0);
}
