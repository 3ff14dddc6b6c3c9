// The 16-lane voxel walk (trace_points_batch) against the scalar walk (trace_points): the
// same status, t_near / t_far and entry points, bit for bit, on rays chosen to hit the
// walk's edge cases. The accuracy test repeats the comparison on real assets.
#include <doctest/doctest.h>

#include <lsnif/format/container.hpp>
#include <lsnif/format/cpu.hpp>
#include <lsnif/format/forward.hpp>

#include <bit>
#include <cmath>
#include <cstring>
#include <limits>
#include <random>
#include <string>

using namespace lsnif::format;

namespace {

// Random rays that start outside, inside and on grid planes of the box [-1, 1]^3, with
// axis-aligned, nearly axis-aligned (a direction component far below a cell per unit t)
// and general directions, bounded and unbounded segments, and some invalid or degenerate
// rays. Each case is drawn at random per ray, so every case lands in every one of the
// walk's 16 lanes.
std::vector<Ray> edge_case_rays(std::uint32_t V, std::size_t n, std::uint32_t seed) {
    std::mt19937 rng(seed);
    std::uniform_real_distribution<float> u(-1.f, 1.f);
    auto one_in = [&](unsigned k) { return rng() % k == 0; };
    const float inf = std::numeric_limits<float>::infinity();
    std::vector<Ray> rays(n);
    for (Ray& r : rays) {
        r = Ray{};
        const float spread = one_in(2) ? 0.9f : 2.0f;  // inside the box, or also outside
        const bool on_planes = one_in(7), aligned = one_in(5), nearly = one_in(11);
        const int nearly_axis = int(rng() % 3);
        for (int k = 0; k < 3; ++k) {
            r.org[k] = u(rng) * spread;
            if (on_planes) r.org[k] = std::round(r.org[k] * V * 0.5f) / (V * 0.5f);
            r.dir[k] = u(rng);
            if (aligned) r.dir[k] = float(int(u(rng) * 2.0f));  // axis-aligned or diagonal
            if (nearly && k == nearly_axis) r.dir[k] = u(rng) * 1e-30f;
        }
        if (r.dir[0] == 0 && r.dir[1] == 0 && r.dir[2] == 0) r.dir[0] = 1;
        r.tmin = one_in(13) ? std::fabs(u(rng)) : 0.0f;
        r.tmax = one_in(3) ? std::fabs(u(rng)) * 3.0f : inf;
        switch (rng() % 97) {  // invalid or empty segments
            case 1: r.dir[0] = r.dir[1] = r.dir[2] = 0; break;
            case 2: r.org[1] = std::numeric_limits<float>::quiet_NaN(); break;
            case 3: r.tmax = -1.0f; break;
            case 4: r.tmin = std::numeric_limits<float>::quiet_NaN(); break;
            case 5: r.dir[2] = inf; break;
            case 6: r.dir[0] = r.dir[1] = r.dir[2] = 1e-45f; break;  // squared length 0
            case 7: r.dir[1] = 1e20f; break;                         // squared length inf
            default: break;
        }
    }
    return rays;
}

ModelDesc shell_desc(std::uint32_t V, std::uint32_t H) {
    ModelDesc d;
    d.grid_resolution = V;
    d.box_min = {-1.f, -1.f, -1.f};
    d.box_max = {1.f, 1.f, 1.f};
    d.max_points = H;
    return d;
}

// A spherical shell, dense random voxels in the x < V/2 half (walks there fill all H
// slots) and sparse ones in the other half (one in `sparse`: empty blocks beside occupied
// ones; one in 2000 leaves most 8^3 blocks there empty).
std::vector<std::uint8_t> shell_occupancy(const ModelDesc& d, std::uint32_t seed, std::uint32_t sparse = 97) {
    std::mt19937 rng(seed);
    const std::uint32_t V = d.grid_resolution;
    std::vector<std::uint8_t> bits((d.voxel_count() + 7) / 8, 0);
    for (std::uint64_t i = 0; i < d.voxel_count(); ++i) {
        const std::uint32_t x = i % V, y = (i / V) % V, z = std::uint32_t(i / (V * V));
        const float c = (V - 1) * 0.5f,
                    r = std::sqrt((x - c) * (x - c) + (y - c) * (y - c) + (z - c) * (z - c));
        const bool random = rng() % (x < V / 2 ? 4 : sparse) == 0;
        if (random || std::fabs(r - 0.3f * V) < 0.7f) bits[i >> 3] |= std::uint8_t(1u << (i & 7));
    }
    return bits;
}

}  // namespace

TEST_CASE("the 16-lane walk returns the scalar walk's points bit for bit") {
    const std::string path = cpu_features().avx512 ? "in use" : "not available: scalar on both sides";
    MESSAGE("16-lane AVX-512 walk " << path);
    // V = 7, 33 and 61 leave partial blocks at the far faces; V = 64 and 61 with a nearly
    // empty half skip 8^3 blocks; H = 1 stops walks after one point, H = 64 lets most walks
    // run to the box's far side.
    const std::pair<std::uint32_t, std::uint32_t> grids[] = {
        {7, 97}, {32, 97}, {33, 97}, {64, 2000}, {61, 2000}};
    for (const auto& [V, sparse] : grids)
        for (std::uint32_t H : {1u, 18u, 64u}) {
            CAPTURE(V);
            CAPTURE(H);
            const ModelDesc d = shell_desc(V, H);
            const Geometry geo = make_geometry(d);
            const OccupancyGrid occ(V, shell_occupancy(d, 5 + V, sparse));
            if (sparse > 97) {  // the case is there: voxels whose whole 8^3 block is empty
                std::size_t empty8 = 0;
                for (std::uint32_t z = 0; z < V; ++z)
                    for (std::uint32_t y = 0; y < V; ++y)
                        for (std::uint32_t x = 0; x < V; ++x)
                            empty8 += ((occ.blocks[occ.sub_block(x, y, z)] >> OccupancyGrid::kSuperBlockBit) &
                                       1u) == 0;
                CHECK(empty8 > d.voxel_count() / 10);
            }
            const auto rays = edge_case_rays(V, 6000, 17 + V + H);
            std::vector<RayPoints> got(rays.size());
            std::vector<TraceStatus> status(rays.size());
            trace_points_batch(geo, occ, rays, got.data(), status.data());
            std::size_t ok = 0, full = 0;
            RayPoints want;
            for (std::size_t i = 0; i < rays.size(); ++i) {
                CAPTURE(i);
                const TraceStatus s = trace_points(geo, occ, rays[i], want);
                REQUIRE(status[i] == s);
                ok += s == TraceStatus::ok;
                if (s == TraceStatus::invalid) continue;  // t_near / t_far are left alone
                REQUIRE(std::memcmp(&got[i].t_near, &want.t_near, sizeof want.t_near) == 0);
                REQUIRE(std::memcmp(&got[i].t_far, &want.t_far, sizeof want.t_far) == 0);
                REQUIRE(std::memcmp(got[i].dir, want.dir, sizeof want.dir) == 0);
                REQUIRE(got[i].count == want.count);
                full += want.count == H;
                for (std::uint32_t k = 0; k < want.count; ++k) {
                    REQUIRE(std::memcmp(&got[i].t[k], &want.t[k], sizeof want.t[k]) == 0);
                    REQUIRE(std::memcmp(got[i].g[k], want.g[k], sizeof want.g[k]) == 0);
                    REQUIRE(got[i].voxel[k] == want.voxel[k]);
                }
            }
            // The rays reach the cases they are meant to: hits, full point lists, misses.
            CHECK(ok > rays.size() / 5);
            if (H < V) CHECK(full > 0);  // a walk crosses up to ~3V voxels, half of them dense
            CHECK(ok < rays.size());
        }
}

TEST_CASE("the 16-lane walk handles batches shorter than its lanes and empty grids") {
    const ModelDesc d = shell_desc(32, 18);
    const Geometry geo = make_geometry(d);
    const auto rays = edge_case_rays(32, 40, 3);
    for (const bool empty : {false, true}) {
        const OccupancyGrid occ(
            32, empty ? std::vector<std::uint8_t>(d.voxel_count() / 8, 0) : shell_occupancy(d, 9));
        for (std::size_t n : {0u, 1u, 5u, 16u, 17u, 40u}) {
            CAPTURE(n);
            std::vector<RayPoints> got(n);
            std::vector<TraceStatus> status(n);
            trace_points_batch(geo, occ, std::span(rays).first(n), got.data(), status.data());
            RayPoints want;
            for (std::size_t i = 0; i < n; ++i) {
                REQUIRE(status[i] == trace_points(geo, occ, rays[i], want));
                REQUIRE(got[i].count == want.count);
                if (empty) CHECK(status[i] != TraceStatus::ok);
            }
        }
    }
}

namespace {

// Point i of a sequence of grid points of a V^3 grid for the corner tests: random, with
// coordinates on voxel faces (as entry points are) and on the far face (s == res) mixed in.
void corner_test_point(std::mt19937& rng, std::uint32_t V, int i, float g[3]) {
    std::uniform_real_distribution<float> u(0.f, float(V));
    std::uniform_int_distribution<int> plane(0, int(V));
    for (int a = 0; a < 3; ++a) g[a] = u(rng);
    for (int a = 0; a < 3; ++a)
        if ((i >> a) % 3 == 0) g[a] = float(plane(rng));  // on a voxel face
    if (i % 17 == 0) g[i % 3] = float(V);
}

}  // namespace

TEST_CASE("the vector corner computation matches the scalar reference bit for bit") {
    // Hashed levels (aligned and not), a dense level, and points on lattice planes, on the
    // grid's far faces (s == res) and at random.
    ModelDesc d = shell_desc(32, 18);
    d.level_resolution = {64, 128, 40, 8};
    d.log2_table_size = 12;  // 9^3 = 729 <= 4096: the res-8 level is dense
    const Geometry geo = make_geometry(d);
    REQUIRE(geo.levels[3].dense);
    REQUIRE(!geo.levels[0].dense);
    std::mt19937 rng(8);
    std::size_t sparse = 0;
    for (int i = 0; i < 20000; ++i) {
        float g[3];
        corner_test_point(rng, 32, i, g);
        for (std::uint32_t l = 0; l < geo.L; ++l) {
            Corners got, want;
            level_corners(geo, geo.levels[l], g, got);
            level_corners_reference(geo, geo.levels[l], g, want);
            REQUIRE(got.n == want.n);
            sparse += want.n < 8;
            REQUIRE(std::memcmp(got.index, want.index, want.n * sizeof want.index[0]) == 0);
            REQUIRE(std::memcmp(got.weight, want.weight, want.n * sizeof want.weight[0]) == 0);
        }
    }
    CHECK(sparse > 1000);  // the dropped-corner cases are exercised
}

TEST_CASE("sixteen points' corners at once equal level_corners point by point") {
    // The trainer's gradient scatter adds shares in level_corners' order from these: the
    // same corners, order and weights, for full and partial batches, on hashed (aligned and
    // not) and dense levels, with points on lattice planes and on the grid's far faces.
    ModelDesc d = shell_desc(64, 14);
    d.level_resolution = {16, 32, 128, 40};
    d.log2_table_size = 16;  // 17^3 and 33^3 rows fit: levels 16 and 32 are dense; 40 and 128 hash
    const Geometry geo = make_geometry(d);
    REQUIRE(geo.levels[0].dense);
    REQUIRE(!geo.levels[2].dense);
    std::mt19937 rng(9);
    std::size_t points = 0, four = 0;
    for (int batch = 0; batch < 2000; ++batch) {
        const std::uint32_t count = batch % 7 == 0 ? std::uint32_t(batch % 16) + 1 : 16;
        float x[16], y[16], z[16];
        for (std::uint32_t j = 0; j < count; ++j) {
            float g[3];
            corner_test_point(rng, 64, batch * 16 + int(j), g);
            x[j] = g[0], y[j] = g[1], z[j] = g[2];
        }
        for (std::uint32_t l = 0; l < geo.L; ++l) {
            Corners16 got;
            level_corners16(geo, geo.levels[l], x, y, z, count, got);
            for (std::uint32_t j = 0; j < 16; ++j) {
                if (j >= count) {
                    REQUIRE(got.n[j] == 0);
                    continue;
                }
                const float g[3] = {x[j], y[j], z[j]};
                Corners want;
                level_corners_reference(geo, geo.levels[l], g, want);
                REQUIRE(got.n[j] == want.n);
                four += want.n == 4;
                ++points;
                for (std::uint32_t s = 0; s < want.n; ++s) {
                    REQUIRE(got.index[s][j] == want.index[s]);
                    REQUIRE(std::bit_cast<std::uint32_t>(got.weight[s][j]) ==
                            std::bit_cast<std::uint32_t>(want.weight[s]));
                }
            }
        }
    }
    CHECK(points > 90000);
    CHECK(four > points / 10);  // face points with dropped corners are exercised
}
