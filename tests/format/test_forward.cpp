// Forward pass: DDA against a brute-force reference, encoding, the MLP kernel, decode,
// and the C intersect API with instance transforms.
#include <doctest/doctest.h>

#include <lsnif/lsnif.h>
#include <lsnif/format/container.hpp>
#include <lsnif/format/cpu.hpp>
#include <lsnif/format/forward.hpp>
#include <lsnif/format/half.hpp>

#include <algorithm>
#include <cmath>
#include <cstring>
#include <random>
#include <tuple>

using namespace lsnif::format;

namespace {

ModelDesc desc_with(std::uint32_t V, std::array<float, 3> lo, std::array<float, 3> hi) {
    ModelDesc d;
    d.grid_resolution = V;
    d.box_min = lo;
    d.box_max = hi;
    return d;
}

// Reference: every voxel tested on its own with the slab rule of forward.hpp, using the
// same plane_t values; then sorted by entry.
std::vector<std::pair<float, std::uint32_t>> brute_force(const Geometry& geo, const Ray& ray) {
    std::vector<std::pair<float, std::uint32_t>> out;
    RayGrid rg;
    float t_near, t_far;
    if (make_ray_grid(geo, ray, rg, t_near, t_far) != TraceStatus::ok) return out;
    const int V = int(geo.V);
    for (int z = 0; z < V; ++z)
        for (int y = 0; y < V; ++y)
            for (int x = 0; x < V; ++x) {
                const int c[3] = {x, y, z};
                float enter = -INFINITY, exit = INFINITY;
                bool inside = true;
                for (int a = 0; a < 3; ++a) {
                    if (rg.gd[a] == 0) {
                        // Half-open [c, c+1), the last cell closed at V.
                        const float g = rg.go[a];
                        const bool in = (g >= c[a] && g < c[a] + 1) || (c[a] == V - 1 && g == V);
                        inside = inside && in;
                        continue;
                    }
                    const float t0 = rg.plane_t(a, rg.gd[a] > 0 ? c[a] : c[a] + 1);
                    const float t1 = rg.plane_t(a, rg.gd[a] > 0 ? c[a] + 1 : c[a]);
                    enter = std::max(enter, t0);
                    exit = std::min(exit, t1);
                }
                if (!inside) continue;
                const float lo = std::max(t_near, enter);
                if (lo <= t_far && lo < exit) out.push_back({lo, std::uint32_t(x + V * (y + V * z))});
            }
    std::stable_sort(out.begin(), out.end(), [](auto& a, auto& b) { return a.first < b.first; });
    return out;
}

void check_against_brute_force(const Geometry& geo, const Ray& ray, const char* what) {
    std::vector<std::uint32_t> vox;
    std::vector<float> ts;
    trace_all_voxels(geo, ray, vox, ts);
    const auto ref = brute_force(geo, ray);
    INFO(what << " org " << ray.org[0] << "," << ray.org[1] << "," << ray.org[2] << " dir " << ray.dir[0]
              << "," << ray.dir[1] << "," << ray.dir[2] << " t [" << ray.tmin << "," << ray.tmax << "]");
    REQUIRE(vox.size() == ref.size());
    for (std::size_t i = 0; i < ref.size(); ++i) {
        REQUIRE(vox[i] == ref[i].second);
        REQUIRE(ts[i] == ref[i].first);
        if (i) REQUIRE(ts[i] > ts[i - 1]);  // strictly ordered: no voxel entered twice at once
    }
}

}  // namespace

TEST_CASE("DDA visits exactly the brute-force voxel sequence on random rays") {
    std::mt19937 rng(7);
    std::uniform_real_distribution<float> u(-1.f, 1.f);
    for (std::uint32_t V : {1u, 5u, 8u, 32u}) {
        const Geometry geo = make_geometry(desc_with(V, {-1.f, -0.5f, 0.25f}, {2.f, 0.75f, 0.5f}));
        const int n = V == 32 ? 300 : 1500;
        for (int i = 0; i < n; ++i) {
            Ray r{};
            for (int a = 0; a < 3; ++a) {
                const float c = 0.5f * (geo.box_min[a] + geo.box_max[a]);
                const float e = geo.box_max[a] - geo.box_min[a];
                r.org[a] = c + u(rng) * e * (i % 2 ? 0.45f : 1.5f);  // inside, or mostly outside
                r.dir[a] = u(rng);
            }
            r.tmin = i % 3 == 0 ? u(rng) : 0.0f;
            r.tmax = i % 5 == 0 ? std::abs(u(rng)) * 2.0f : INFINITY;
            check_against_brute_force(geo, r, "random");
        }
    }
}

TEST_CASE(
    "a direction that moves along no axis of a huge box's grid, or overflows in it, is invalid in both "
    "walks") {
    // Cells of 2e28 units: a direction of 1e-22 is normalizable (squared length 1e-44, a
    // subnormal) but is 0 once divided by the cell, so no voxel boundary is ever reached.
    const std::uint32_t V = 100;
    const Geometry geo = make_geometry(desc_with(V, {-1e30f, -1e30f, -1e30f}, {1e30f, 1e30f, 1e30f}));
    const Ray still{{0.f, 0.f, 0.f}, 0.f, {1e-22f, 0.f, 0.f}, INFINITY};
    REQUIRE(normalizable(still.dir));
    std::vector<std::uint32_t> vox;
    std::vector<float> ts;
    CHECK(trace_all_voxels(geo, still, vox, ts) == TraceStatus::invalid);
    std::vector<std::uint8_t> bits((std::uint64_t(V) * V * V + 7) / 8, 0xFF);
    const OccupancyGrid occ(V, bits);
    // A component of 2e-12 is 1e-40 cells per unit t, subnormal in grid units, and its
    // reciprocal overflows: on the grid plane x = 50 through the origin, plane_t would be
    // 0 * inf = NaN.
    const Ray overflowing{{0.f, 0.f, 0.f}, 0.f, {2e-12f, 1.0f, 0.f}, INFINITY};
    CHECK(trace_all_voxels(geo, overflowing, vox, ts) == TraceStatus::invalid);
    std::vector<Ray> rays(17, still);
    rays[3].dir[0] = 1.0f;  // a moving ray among them
    rays[5] = overflowing;
    std::vector<RayPoints> pts(rays.size());
    std::vector<TraceStatus> status(rays.size());
    trace_points_batch(geo, occ, rays, pts.data(), status.data());
    for (std::size_t i = 0; i < rays.size(); ++i)
        CHECK(status[i] == (i == 3 ? TraceStatus::ok : TraceStatus::invalid));
}

TEST_CASE("DDA hard cases: axis-parallel, on boundaries, edges and corners, tmax inside") {
    const std::uint32_t V = 8;
    const Geometry geo = make_geometry(desc_with(V, {0.f, 0.f, 0.f}, {8.f, 8.f, 8.f}));  // cell = 1
    std::mt19937 rng(11);
    std::uniform_int_distribution<int> k(0, int(V));
    std::uniform_int_distribution<int> s(-1, 1);
    int checked = 0;
    for (int i = 0; i < 4000; ++i) {
        Ray r{};
        // Origins on lattice points, planes or cell centers; directions with zero and
        // unit components, so rays run along faces and through edges and corners.
        for (int a = 0; a < 3; ++a) {
            const int mode = (i / 3 + a) % 3;
            r.org[a] = mode == 0 ? float(k(rng)) : mode == 1 ? float(k(rng)) + 0.5f : float(k(rng)) - 3.0f;
            r.dir[a] = float(s(rng));
        }
        if (r.dir[0] == 0 && r.dir[1] == 0 && r.dir[2] == 0) r.dir[i % 3] = 1;
        if (i % 4 == 1) r.dir[i % 3] *= 2.0f;  // 1:1:2 diagonals also hit lattice points exactly
        r.tmin = 0.0f;
        r.tmax = i % 7 == 0 ? float(k(rng)) * 0.5f : INFINITY;  // shadow-like, often ending on a plane
        check_against_brute_force(geo, r, "lattice");
        ++checked;
    }
    CHECK(checked == 4000);

    // Axis-parallel ray along the face plane x = 3 between voxels 2 and 3: takes cell 3.
    Ray along{{3.f, 0.5f, -1.f}, 0.f, {0.f, 0.f, 1.f}, INFINITY};
    std::vector<std::uint32_t> vox;
    std::vector<float> ts;
    REQUIRE(trace_all_voxels(geo, along, vox, ts) == TraceStatus::ok);
    REQUIRE(vox.size() == V);
    CHECK(vox[0] % V == 3);
    CHECK(ts[0] == 1.0f);
    // Through the exact corner (4,4,4) on the main diagonal: 8 cells, no side steps.
    Ray diag{{-1.f, -1.f, -1.f}, 0.f, {1.f, 1.f, 1.f}, INFINITY};
    trace_all_voxels(geo, diag, vox, ts);
    CHECK(vox.size() == V);
    for (std::uint32_t i = 0; i < V; ++i) CHECK(vox[i] == i + V * (i + V * i));
    // Starting inside a voxel, ending inside another.
    Ray inside{{0.5f, 0.5f, 0.5f}, 0.f, {1.f, 0.f, 0.f}, 2.25f};
    trace_all_voxels(geo, inside, vox, ts);
    REQUIRE(vox.size() == 3);
    CHECK(ts[0] == 0.0f);
    CHECK(ts[2] == 1.5f);
    // Grazing the box along its edge x = 0, y = 0.
    Ray edge{{0.f, 0.f, -5.f}, 0.f, {0.f, 0.f, 1.f}, INFINITY};
    trace_all_voxels(geo, edge, vox, ts);
    CHECK(vox.size() == V);
    // Degenerate rays are rejected, not traced.
    Ray zero{{1.f, 1.f, 1.f}, 0.f, {0.f, 0.f, 0.f}, INFINITY};
    CHECK(trace_all_voxels(geo, zero, vox, ts) == TraceStatus::invalid);
    Ray nan{{NAN, 1.f, 1.f}, 0.f, {1.f, 0.f, 0.f}, INFINITY};
    CHECK(trace_all_voxels(geo, nan, vox, ts) == TraceStatus::invalid);
    // Directions FORMAT.md §8.2 calls invalid: one whose squared length rounds to 0 (it
    // cannot be normalized), one whose squared length overflows.
    Ray tiny{{1.f, 1.f, 1.f}, 0.f, {1e-45f, 1e-45f, 0.f}, INFINITY};
    CHECK(trace_all_voxels(geo, tiny, vox, ts) == TraceStatus::invalid);
    Ray huge{{1.f, 1.f, 1.f}, 0.f, {1e20f, 0.f, 0.f}, INFINITY};
    CHECK(trace_all_voxels(geo, huge, vox, ts) == TraceStatus::invalid);
    Ray missing{{-1.f, 9.f, 1.f}, 0.f, {1.f, 0.f, 0.f}, INFINITY};
    CHECK(trace_all_voxels(geo, missing, vox, ts) == TraceStatus::miss);
    Ray behind{{-1.f, 1.f, 1.f}, 0.f, {-1.f, 0.f, 0.f}, INFINITY};
    CHECK(trace_all_voxels(geo, behind, vox, ts) == TraceStatus::miss);
}

TEST_CASE("trace_points keeps the first H occupied voxels with face-snapped entry points") {
    ModelDesc d = desc_with(8, {0.f, 0.f, 0.f}, {8.f, 8.f, 8.f});
    d.max_points = 3;
    auto m = make_empty_model(d).value();
    // Occupy x = 1, 3, 4, 6 along the row y = 2, z = 5.
    for (std::uint32_t x : {1u, 3u, 4u, 6u}) {
        const std::uint32_t i = x + 8 * (2 + 8 * 5);
        m.occupancy[i >> 3] |= std::uint8_t(1u << (i & 7));
    }
    const Geometry geo = make_geometry(d);
    RayPoints pts;
    Ray r{{-2.f, 2.25f, 5.5f}, 0.f, {2.f, 0.f, 0.f}, INFINITY};  // |dir| = 2: t is half the distance
    REQUIRE(trace_points(geo, m.occupancy.data(), r, pts) == TraceStatus::ok);
    REQUIRE(pts.count == 3);
    CHECK(pts.t[0] == 1.5f);
    CHECK(pts.t[1] == 2.5f);
    CHECK(pts.t[2] == 3.0f);
    CHECK(pts.g[0][0] == 1.0f);  // exactly on the entry face
    CHECK(pts.g[1][0] == 3.0f);
    CHECK(pts.g[0][1] == 2.25f);
    CHECK(pts.voxel[2] == 4 + 8 * (2 + 8 * 5));
    // A shadow ray ending before the second voxel sees only one.
    r.tmax = 2.0f;
    REQUIRE(trace_points(geo, m.occupancy.data(), r, pts) == TraceStatus::ok);
    CHECK(pts.count == 1);
    // A ray through no occupied voxel is culled.
    Ray empty{{-2.f, 6.5f, 5.5f}, 0.f, {1.f, 0.f, 0.f}, INFINITY};
    CHECK(trace_points(geo, m.occupancy.data(), empty, pts) == TraceStatus::miss);
}

TEST_CASE("empty-block skipping returns exactly the points of the plain walk") {
    std::mt19937 rng(21);
    std::uniform_real_distribution<float> u(-1.f, 1.f);
    for (std::uint32_t V : {7u, 32u}) {
        ModelDesc d = desc_with(V, {-1.f, -1.f, -1.f}, {1.f, 1.f, 1.f});
        d.max_points = 18;
        auto m = make_empty_model(d).value();
        // Sparse random voxels plus a shell: empty blocks next to occupied ones.
        for (std::uint64_t i = 0; i < d.voxel_count(); ++i) {
            const std::uint32_t x = i % V, y = (i / V) % V, z = i / (V * V);
            const float c = (V - 1) * 0.5f,
                        r = std::sqrt((x - c) * (x - c) + (y - c) * (y - c) + (z - c) * (z - c));
            if (rng() % 97 == 0 || std::fabs(r - 0.3f * V) < 0.7f)
                m.occupancy[i >> 3] |= std::uint8_t(1u << (i & 7));
        }
        const Geometry geo = make_geometry(d);
        const OccupancyGrid grid(V, m.occupancy);
        RayPoints a, b;
        for (int i = 0; i < 20000; ++i) {
            Ray r{};
            for (int k = 0; k < 3; ++k) {
                r.org[k] = u(rng) * (i % 2 ? 0.9f : 2.0f);
                r.dir[k] = i % 5 == 0 ? float(int(u(rng) * 2.0f)) : u(rng);               // some axis-aligned
                if (i % 7 == 0) r.org[k] = std::round(r.org[k] * V * 0.5f) / (V * 0.5f);  // on planes
            }
            if (r.dir[0] == 0 && r.dir[1] == 0 && r.dir[2] == 0) r.dir[0] = 1;
            r.tmax = i % 3 == 0 ? std::fabs(u(rng)) * 3.0f : INFINITY;
            const auto sa = trace_points(geo, m.occupancy.data(), r, a);
            const auto sb = trace_points(geo, grid, r, b);
            REQUIRE(sa == sb);
            REQUIRE(a.count == b.count);
            for (std::uint32_t k = 0; k < a.count; ++k) {
                REQUIRE(a.t[k] == b.t[k]);
                REQUIRE(a.voxel[k] == b.voxel[k]);
                REQUIRE(std::memcmp(a.g[k], b.g[k], sizeof a.g[k]) == 0);
            }
        }
    }
}

TEST_CASE("encoding: aligned levels touch 4 corners on faces; trilinear weights are exact") {
    ModelDesc d = desc_with(32, {0.f, 0.f, 0.f}, {1.f, 1.f, 1.f});
    d.level_resolution = {64, 128, 40};  // 40 is not a multiple of 32: faces fall inside cells
    d.log2_table_size = 17;
    const Geometry geo = make_geometry(d);
    std::mt19937 rng(3);
    std::uniform_real_distribution<float> u(0.f, 32.f);
    std::uniform_int_distribution<int> plane(0, 32);
    for (int i = 0; i < 2000; ++i) {
        float g[3] = {u(rng), u(rng), u(rng)};
        const int axis = i % 4;  // 3 = no face
        if (axis < 3) g[axis] = float(plane(rng));
        for (std::uint32_t l = 0; l < 3; ++l) {
            Corners c;
            level_corners(geo, geo.levels[l], g, c);
            float sum = 0;
            for (std::uint32_t k = 0; k < c.n; ++k) {
                sum += c.weight[k];
                CHECK(c.weight[k] > 0.0f);
                CHECK(c.index[k] < d.level_entries(l));
            }
            CHECK(sum == doctest::Approx(1.0f).epsilon(1e-6));
            if (axis < 3 && geo.levels[l].aligned) CHECK(c.n <= 4);
        }
    }
    // Dense level: index and weights against a direct computation.
    ModelDesc dd = desc_with(4, {0.f, 0.f, 0.f}, {1.f, 1.f, 1.f});
    dd.level_resolution = {8};
    dd.log2_table_size = 10;  // 9^3 = 729 <= 1024: dense
    const Geometry gd = make_geometry(dd);
    REQUIRE(gd.levels[0].dense);
    const float p[3] = {1.25f, 2.0f, 3.875f};  // lattice coords 2.5, 4, 7.75
    Corners c;
    level_corners(gd, gd.levels[0], p, c);
    REQUIRE(c.n == 4);
    CHECK(c.index[0] == 2 + 9 * (4 + 9 * 7));
    CHECK(c.weight[0] == doctest::Approx(0.5f * 0.25f));
    CHECK(c.index[3] == 3 + 9 * (4 + 9 * 8));
    CHECK(c.weight[3] == doctest::Approx(0.5f * 0.75f));
    // Hashed index: (x*1 ^ y*2654435761 ^ z*805459861) mod T.
    const float q[3] = {2.0f, 3.0f, 5.0f};
    level_corners(geo, geo.levels[0], q, c);  // level res 64, scale 2: lattice (4, 6, 10)
    REQUIRE(c.n == 1);
    CHECK(c.index[0] == ((4u * 1u) ^ (6u * 2654435761u) ^ (10u * 805459861u)) % (1u << 17));
}

TEST_CASE(
    "the 16-point encoder equals the per-ray encoder bit for bit on f32, fp16 and u8 tables, "
    "first points shared between neighbouring rays included") {
    // Levels: aligned and hashed (64), not aligned (40), dense (8: 9^3 <= 2^12 entries).
    ModelDesc d = desc_with(32, {-1.f, 0.5f, 2.f}, {3.f, 1.5f, 4.5f});
    d.level_resolution = {64, 40, 8};
    d.log2_table_size = 12;
    d.ray_inputs = kRayInputDirection | kRayInputEntryOffsets;
    // H = 7, 16 (the widest whose entry offsets take one vector), 18 and 37 points per ray.
    for (const std::uint32_t H : {7u, 16u, 18u, 37u}) {
        CAPTURE(H);
        d.max_points = H;
        std::mt19937 rng(11 + H);
        std::uniform_real_distribution<float> u(0.f, 32.f), value(-2.f, 2.f);
        std::uniform_int_distribution<int> plane(0, 32), byte(0, 255), count(0, int(H));
        // Rays whose points lie on voxel faces (one coordinate an integer, 0 and V included),
        // inside cells, and on lattice vertices; counts from 0 to H, in a scrambled order.
        std::vector<RayPoints> pts(203);
        for (std::size_t r = 0; r < pts.size(); ++r) {
            RayPoints& p = pts[r];
            p.count = std::uint32_t(count(rng));
            for (std::uint32_t h = 0; h < p.count; ++h) {
                for (int a = 0; a < 3; ++a) p.g[h][a] = u(rng);
                const int kind = int((r + h) % 5);
                if (kind < 3) p.g[h][kind] = float(plane(rng));
                if (kind == 3)
                    for (int a = 0; a < 3; ++a) p.g[h][a] = float(plane(rng));
                p.t[h] = float(h);
            }
            const float dir[3] = {value(rng), value(rng), value(rng)};
            unit_direction(Ray{{0, 0, 0}, 0, {dir[0], dir[1], dir[2] + 3.f}, 1}, p.dir);
        }
        // Runs of rays leaving one point (the encoder encodes such a first point once): rays
        // 3k+1 and 3k+2 start where ray 3k does (their other points differ); ray 3k's first
        // point differs from ray 3k-1's in one coordinate only (x, y or z in turn), which a
        // comparison of fewer than the three would take for a shared point.
        std::size_t runs = 0;
        for (std::size_t r = 1; r < pts.size(); ++r) {
            if (!pts[r].count || !pts[r - 1].count) continue;
            if (r % 3) {
                std::copy(pts[r - 1].g[0], pts[r - 1].g[0] + 3, pts[r].g[0]);
                ++runs;
            } else {
                for (int a = 0; a < 3; ++a)
                    if (a != int(r / 3 % 3)) pts[r].g[0][a] = pts[r - 1].g[0][a];
            }
        }
        REQUIRE(runs > 50);
        // Every ray, scrambled, one twice; and every ray but each 4th, so some rays' neighbours
        // that share their first point are missing from the batch.
        std::vector<std::uint32_t> all(pts.size()), some;
        for (std::size_t j = 0; j < all.size(); ++j) all[j] = std::uint32_t((j * 89) % pts.size());
        all.push_back(5);
        for (const std::uint32_t r : all)
            if (r % 4) some.push_back(r);

        for (const std::uint32_t F : {1u, 2u, 3u, 4u}) {
            d.features_per_level = F;
            const Geometry geo = make_geometry(d);
            REQUIRE(geo.levels[2].dense);
            REQUIRE_FALSE(geo.levels[1].aligned);
            std::vector<std::vector<float>> f32(geo.L);
            std::vector<std::vector<std::uint16_t>> f16(geo.L);
            std::vector<std::vector<std::uint8_t>> u8(geo.L);
            // fp16 and u8 tables as Runtime keeps them (F per entry, then the tail pad) and
            // with rows padded to 4 elements: the encoder reads both the same way.
            std::vector<GridView> f32_views, f16_views, u8_views, f16_row4_views, u8_row4_views;
            for (std::uint32_t l = 0; l < geo.L; ++l) {
                const std::size_t entries = d.level_entries(l);
                for (std::size_t e = 0; e < entries * F; ++e) f32[l].push_back(value(rng));
                for (std::size_t e = 0; e < entries * 4; ++e) f16[l].push_back(float_to_half(value(rng)));
                for (std::size_t e = 0; e < entries * 4; ++e) u8[l].push_back(std::uint8_t(byte(rng)));
                const float scale = 0.0123f * float(l + 1);
                f32_views.push_back({f32[l].data(), F, GridElement::f32});
                f16_views.push_back({f16[l].data(), F, GridElement::f16});
                u8_views.push_back({u8[l].data(), F, GridElement::u8, scale, -1.5f});
                f16_row4_views.push_back({f16[l].data(), 4, GridElement::f16});
                u8_row4_views.push_back({u8[l].data(), 4, GridElement::u8, scale, -1.5f});
            }
            for (const auto* views : {&f32_views, &f16_views, &u8_views, &f16_row4_views, &u8_row4_views})
                for (const auto* batch : {&all, &some}) {
                    const std::vector<std::uint32_t>& which = *batch;
                    CAPTURE(F);
                    CAPTURE(int((*views)[0].element));
                    CAPTURE(which.size());
                    std::vector<float> rows(which.size() * geo.input_width, -7.0f), row(geo.input_width);
                    encode_batch(geo, views->data(), pts.data(), which, rows.data());
                    std::size_t same = 0;
                    for (std::size_t j = 0; j < which.size(); ++j) {
                        encode_points(geo, views->data(), pts[which[j]], row.data());
                        same += std::memcmp(row.data(), rows.data() + j * geo.input_width,
                                            row.size() * sizeof(float)) == 0;
                    }
                    CHECK(same == which.size());
                }
        }
    }
}

// Runs as its own CTest test, skipped on CPUs without AVX-512 BF16 (tests/CMakeLists.txt).
TEST_CASE("the bf16 product skips the zero columns ZeroColumns names, with the same results") {
    REQUIRE_MESSAGE(cpu_features().avx512_bf16, "no AVX-512 BF16: the skipping kernel does not exist here");
    std::mt19937 rng(5);
    std::uniform_real_distribution<float> u(-1.f, 1.f);
    // The inference shapes (129 inputs: 108 point features, then 21 ray inputs) and ragged
    // ones: odd lead and tail, rows not a multiple of the 6-row block, leads in any order.
    // A second zero run from rest_start + rest[r] to the end (the entry offsets; 0 = none).
    struct Shape {
        std::size_t m, n, in, tail, rest_start;
    };
    for (const Shape sh : {Shape{256, 128, 129, 108, 111}, Shape{37, 128, 129, 108, 0},
                           Shape{13, 48, 71, 51, 52}, Shape{7, 16, 33, 33, 0}}) {
        CAPTURE(sh.m);
        CAPTURE(sh.in);
        CAPTURE(sh.rest_start);
        const std::size_t kp = round_up(sh.in, 32), n = sh.n;
        std::vector<std::uint32_t> lead(sh.m), rest(sh.m);
        std::vector<float> A(sh.m * sh.in), W(sh.in * n), bias(round_up(n, 16));
        for (std::size_t r = 0; r < sh.m; ++r) {
            lead[r] = std::uint32_t(rng() % (sh.tail + 1));
            rest[r] = sh.rest_start ? std::uint32_t(rng() % (sh.in - sh.rest_start + 1)) : 0;
            if (r % 3 == 0 && r > 0) {  // runs of equal leads, as sorted rows have
                lead[r] = lead[r - 1];
                rest[r] = rest[r - 1];
            }
            for (std::size_t c = 0; c < sh.in; ++c) {
                const bool zero =
                    (c >= lead[r] && c < sh.tail) || (sh.rest_start && c >= sh.rest_start + rest[r]);
                A[r * sh.in + c] = zero ? 0.0f : u(rng);
            }
        }
        for (float& w : W) w = u(rng);
        for (float& b : bias) b = u(rng);
        std::vector<Bf16> a(sh.m * kp), b(kp / 2 * 2 * round_up(n, 16));
        pack_rows(A.data(), sh.m, sh.in, sh.in, a.data(), kp, sh.m);
        pack_vnni(W.data(), sh.in, n, n, b.data(), 2 * round_up(n, 16), kp);
        const ZeroColumns zeros{lead.data(), sh.tail, sh.rest_start ? rest.data() : nullptr, sh.rest_start};
        for (const bool relu : {true, false}) {
            std::vector<float> full(sh.m * n), skipped(sh.m * n);
            gemm_bf16_dp(sh.m, n, kp, a.data(), kp, b.data(), 2 * round_up(n, 16), full.data(), n,
                         {bias.data(), relu, false});
            gemm_bf16_dp(sh.m, n, round_up(sh.in, 2), a.data(), kp, b.data(), 2 * round_up(n, 16),
                         skipped.data(), n, {bias.data(), relu, false}, &zeros);
            std::size_t same = 0;
            for (std::size_t i = 0; i < full.size(); ++i) same += full[i] == skipped[i];
            CHECK(same == full.size());
        }
    }
}

TEST_CASE("narrow layers (16 to 48 outputs) equal the wide kernel's columns bit for bit") {
    // dense_layer takes an 8-row kernel below 64 padded outputs; the same weights padded
    // to 64 outputs go through the wide kernel, whose first columns must be identical.
    std::mt19937 rng(12);
    std::uniform_real_distribution<float> u(-1.f, 1.f);
    for (const std::size_t n : {std::size_t(1), std::size_t(7), std::size_t(8), std::size_t(133)})
        for (const std::size_t op : {std::size_t(16), std::size_t(48)})
            for (const bool relu : {false, true}) {
                const std::size_t in = 128, lda = in + 4, wide = 64;
                std::vector<float> A(n * lda), wt(in * op), wt_wide(in * wide, 0.f), bias(op),
                    bias_wide(wide, 0.f);
                for (auto& x : A) x = u(rng);
                for (std::size_t i = 0; i < in; ++i)
                    for (std::size_t o = 0; o < op; ++o) wt[i * op + o] = wt_wide[i * wide + o] = u(rng);
                for (std::size_t o = 0; o < op; ++o) bias[o] = bias_wide[o] = u(rng);
                std::vector<float> got(n * op), want(n * wide);
                dense_layer(A.data(), n, in, lda, wt.data(), bias.data(), op, relu, got.data());
                dense_layer(A.data(), n, in, lda, wt_wide.data(), bias_wide.data(), wide, relu, want.data());
                CAPTURE(n);
                CAPTURE(op);
                for (std::size_t r = 0; r < n; ++r)
                    REQUIRE(std::memcmp(&got[r * op], &want[r * wide], op * sizeof(float)) == 0);
            }
}

TEST_CASE("fp16 weights, widened on load, give the fp32 kernels' bits for every width and row count") {
    // A model's network stores W^T in fp16 and the fp32 arithmetic reads it directly: the
    // wide (64+ outputs) and narrow kernels, full and partial row blocks, with and without
    // ReLU and zero-column skipping, must equal the same values stored in fp32. Includes
    // subnormal and signed-zero halves, which the widening must keep exactly.
    std::mt19937 rng(14);
    std::uniform_real_distribution<float> u(-1.f, 1.f);
    for (const std::size_t n : {std::size_t(1), std::size_t(5), std::size_t(6), std::size_t(133)})
        for (const std::size_t op : {std::size_t(16), std::size_t(48), std::size_t(80), std::size_t(128)})
            for (const bool relu : {false, true}) {
                CAPTURE(n);
                CAPTURE(op);
                const std::size_t in = 61, lda = in + 3;
                std::vector<float> A(n * lda), wt32(in * op), bias(op);
                std::vector<std::uint16_t> wt16(in * op);
                for (auto& x : A) x = u(rng);
                for (std::size_t j = 0; j < wt16.size(); ++j) {
                    wt16[j] = j % 97 == 0   ? std::uint16_t(0x0001 + j % 5)  // subnormals
                              : j % 89 == 0 ? std::uint16_t(0x8000)          // -0
                                            : float_to_half(u(rng));
                    wt32[j] = half_to_float(wt16[j]);
                }
                for (auto& b : bias) b = u(rng);
                // Row r is zero in columns [lead[r], in - 4), as the empty point slots are.
                std::vector<std::uint32_t> lead(n);
                for (std::size_t r = 0; r < n; ++r) {
                    lead[r] = std::uint32_t(in - 30 + r % 7);
                    for (std::size_t c = lead[r]; c < in - 4; ++c) A[r * lda + c] = 0.f;
                }
                const ZeroColumns zeros{lead.data(), in - 4};
                std::vector<float> got(n * op), want(n * op);
                dense_layer_strided(A.data(), n, in, lda, wt16.data(), op, bias.data(), op, relu, got.data(),
                                    op, &zeros);
                dense_layer_strided(A.data(), n, in, lda, wt32.data(), op, bias.data(), op, relu, want.data(),
                                    op, &zeros);
                REQUIRE(std::memcmp(got.data(), want.data(), got.size() * sizeof(float)) == 0);
            }
}

TEST_CASE("the output layer kernel equals dense_layer on the real outputs bit for bit") {
    // Rows in vector lanes for blocks of 16 rows (only the real outputs computed), the
    // narrow kernel for the rest: every row count around the block size, inputs that are
    // and are not a multiple of 16, and output counts with and without a specialization.
    std::mt19937 rng(13);
    std::uniform_real_distribution<float> u(-1.f, 1.f);
    for (const std::size_t n : {std::size_t(1), std::size_t(15), std::size_t(16), std::size_t(17),
                                std::size_t(47), std::size_t(256)})
        for (const std::size_t in : {std::size_t(128), std::size_t(37)})
            for (const std::size_t outs : {std::size_t(5), std::size_t(8), std::size_t(9)}) {
                CAPTURE(n);
                CAPTURE(in);
                CAPTURE(outs);
                const std::size_t op = 16, lda = in + 3;
                std::vector<float> A(n * lda), wt(in * op, 0.f), bias(op, 0.f);
                for (auto& x : A) x = u(rng);
                for (std::size_t i = 0; i < in; ++i)
                    for (std::size_t o = 0; o < outs; ++o) wt[i * op + o] = u(rng);
                for (std::size_t o = 0; o < outs; ++o) bias[o] = u(rng);
                std::vector<float> got(n * op, -1.f), want(n * op);
                dense_output_layer(A.data(), n, in, lda, wt.data(), bias.data(), op, outs, got.data());
                dense_layer(A.data(), n, in, lda, wt.data(), bias.data(), op, false, want.data());
                std::size_t same = 0;
                for (std::size_t r = 0; r < n; ++r)
                    same += std::memcmp(&got[r * op], &want[r * op], outs * sizeof(float)) == 0;
                CHECK(same == n);
            }
}

TEST_CASE("dense_layer matches a naive reference, including ragged sizes") {
    std::mt19937 rng(5);
    std::uniform_real_distribution<float> u(-1.f, 1.f);
    const int shapes[][3] = {{1, 3, 5}, {7, 108, 128}, {13, 17, 40}, {64, 128, 128}};
    for (const auto& shape : shapes) {
        const int n = shape[0], in = shape[1], out = shape[2];
        const std::size_t op = (out + 15) / 16 * 16;
        std::vector<float> A(n * in), wt(in * op, 0.f), bias(op, 0.f), C(n * op);
        for (auto& x : A) x = u(rng);
        for (int i = 0; i < in; ++i)
            for (int o = 0; o < out; ++o) wt[i * op + o] = u(rng);
        for (int o = 0; o < out; ++o) bias[o] = u(rng);
        for (bool relu : {false, true}) {
            dense_layer(A.data(), n, in, in, wt.data(), bias.data(), op, relu, C.data());
            for (int r = 0; r < n; ++r)
                for (int o = 0; o < out; ++o) {
                    double ref = bias[o];
                    for (int i = 0; i < in; ++i) ref += double(A[r * in + i]) * wt[i * op + o];
                    if (relu) ref = std::max(ref, 0.0);
                    REQUIRE(C[r * op + o] == doctest::Approx(ref).epsilon(1e-4).scale(1.0));
                }
        }
    }
}

// The canonical arithmetic (docs/pipeline.md "The same bytes everywhere"): each output is its
// bias, then one fused multiply-add per input in input order. CTest runs this under every
// LSNIF_ISA cap (format, format_isa_avx2, format_isa_generic), so the AVX-512, AVX2 and
// portable kernels are each held to the same definition, computed here with std::fma.
// dense_layer_strided with ReLU skips the inputs ZeroColumns names and may compute a prefix
// of the columns from strided weights: the same bits again.
TEST_CASE("dense_layer is bias then fused multiply-adds in input order, bit for bit, skipping zeros or not") {
    std::mt19937 rng(11);
    std::uniform_real_distribution<float> u(-1.f, 1.f);
    // (rows, inputs, outputs): the training shapes (143 inputs: 126 point features, 3
    // directions, 14 offsets), narrow and ragged ones.
    const int shapes[][3] = {{1, 3, 16}, {7, 143, 128}, {13, 17, 48}, {130, 143, 128}, {25, 40, 64}};
    for (const auto& shape : shapes) {
        const int n = shape[0], in = shape[1], out = shape[2];
        CAPTURE(n);
        CAPTURE(in);
        CAPTURE(out);
        const std::size_t op = (out + 15) / 16 * 16;
        // Zero runs as the trainer's first layer has them: features [lead, tail), then
        // offsets from rest_start + rest on; lead and rest per row.
        const std::size_t tail = std::size_t(in) * 7 / 8, rest_start = tail + (in > 8 ? 3 : 0);
        std::vector<std::uint32_t> lead(n), rest(n);
        std::vector<float> A(std::size_t(n) * in), wt(std::size_t(in) * op), bias(op), C(n * op), S(n * op);
        for (int r = 0; r < n; ++r) {
            lead[r] = std::uint32_t(rng() % (tail + 1));
            rest[r] = std::uint32_t(rng() % (std::size_t(in) - std::min<std::size_t>(in, rest_start) + 1));
            for (int i = 0; i < in; ++i) {
                const bool zero = (std::size_t(i) >= lead[r] && std::size_t(i) < tail) ||
                                  std::size_t(i) >= rest_start + rest[r];
                A[std::size_t(r) * in + i] = zero ? (rng() % 2 ? 0.0f : -0.0f) : u(rng);
            }
        }
        for (auto& x : wt) x = u(rng);
        for (auto& x : bias) x = u(rng);
        const ZeroColumns zeros{lead.data(), tail, rest.data(), rest_start};
        for (const bool relu : {false, true}) {
            CAPTURE(relu);
            dense_layer(A.data(), n, in, in, wt.data(), bias.data(), op, relu, C.data());
            for (int r = 0; r < n; ++r)
                for (std::size_t o = 0; o < op; ++o) {
                    float want = bias[o];
                    for (int i = 0; i < in; ++i)
                        want = std::fma(A[std::size_t(r) * in + i], wt[i * op + o], want);
                    if (relu) want = want > 0.0f ? want : 0.0f;
                    REQUIRE(std::memcmp(&C[r * op + o], &want, sizeof want) == 0);
                }
            // The first 16 columns, weights strided, zero columns skipped.
            std::fill(S.begin(), S.end(), 7.0f);
            dense_layer_strided(A.data(), n, in, in, wt.data(), op, bias.data(), 16, relu, S.data(), 16,
                                &zeros);
            for (int r = 0; r < n; ++r)
                REQUIRE(std::memcmp(&S[std::size_t(r) * 16], &C[r * op], 16 * sizeof(float)) == 0);
            if (op > 16) {
                dense_layer_strided(A.data(), n, in, in, wt.data(), op, bias.data(), op, relu, S.data(), op,
                                    &zeros);
                REQUIRE(std::memcmp(S.data(), C.data(), n * op * sizeof(float)) == 0);
            }
        }
    }
}

namespace {

// An empty model over the box [-1, 1]^3 (V = 8, H = 4, one level, 16 hidden units) with
// `ray_inputs`, the central 4x4x4 voxel block occupied: x, y, z in [-0.5, 0.5].
ModelData block_model(std::uint32_t ray_inputs) {
    ModelDesc d = desc_with(8, {-1.f, -1.f, -1.f}, {1.f, 1.f, 1.f});
    d.max_points = 4;
    d.level_resolution = {16};
    d.log2_table_size = 10;
    d.hidden_width = {16};
    d.ray_inputs = ray_inputs;
    auto m = make_empty_model(d).value();
    m.metadata_json = "{}";
    for (std::uint32_t z = 2; z < 6; ++z)
        for (std::uint32_t y2 = 2; y2 < 6; ++y2)
            for (std::uint32_t x = 2; x < 6; ++x) {
                const std::uint32_t i = x + 8 * (y2 + 8 * z);
                m.occupancy[i >> 3] |= std::uint8_t(1u << (i & 7));
            }
    return m;
}

// A model whose MLP ignores its input: weights zero, biases fixed, so every ray that
// reaches the network gets the same outputs and decode can be checked exactly.
std::vector<std::uint8_t> constant_model_bytes(float logit, float y, std::array<float, 3> n) {
    auto m = block_model(0);
    m.biases[1][0] = float_to_half(logit);
    m.biases[1][1] = float_to_half(y);
    for (int a = 0; a < 3; ++a) m.biases[1][2 + a] = float_to_half(n[a]);
    return serialize(m).value();
}

// The instance transform of the intersect tests: rotate 90 degrees about z, scale 3,
// translate. to_world maps an object-space ray by it.
constexpr float kInstance[12] = {0.f, -3.f, 0.f, 10.f,  //
                                 3.f, 0.f,  0.f, -2.f,  //
                                 0.f, 0.f,  3.f, 5.f};
lsnif_ray to_world(const lsnif_ray& r) {
    const float* M = kInstance;
    lsnif_ray w{};
    for (int a = 0; a < 3; ++a) {
        w.org[a] = M[4 * a] * r.org[0] + M[4 * a + 1] * r.org[1] + M[4 * a + 2] * r.org[2] + M[4 * a + 3];
        w.dir[a] = M[4 * a] * r.dir[0] + M[4 * a + 1] * r.dir[1] + M[4 * a + 2] * r.dir[2];
    }
    w.tmin = r.tmin;
    w.tmax = r.tmax;
    return w;
}

// constant_model_bytes' block with both ray inputs (FORMAT.md §8): hidden unit 0 is
// ReLU(dir_x) of the ray's unit direction and the visibility logit 8 h0 - 6, so a ray hits
// iff its normalized x component exceeds 0.75; hidden unit 1 is the entry offset of slot 2
// and the distance output equals it, so a hit lies at the third occupied voxel's entry.
// Every other weight is zero.
std::vector<std::uint8_t> ray_inputs_model_bytes() {
    auto m = block_model(kRayInputDirection | kRayInputEntryOffsets);
    const ModelDesc& d = m.desc;
    const std::uint32_t in = d.input_width(), dir_x = d.point_feature_width(), offset_2 = dir_x + 3 + 2;
    m.weights[0][0 * in + dir_x] = float_to_half(1.0f);
    m.weights[0][1 * in + offset_2] = float_to_half(1.0f);
    m.weights[1][0 * 16 + 0] = float_to_half(8.0f);
    m.weights[1][1 * 16 + 1] = float_to_half(1.0f);
    m.biases[1][0] = float_to_half(-6.0f);
    m.biases[1][4] = float_to_half(1.0f);
    return serialize(m).value();
}

}  // namespace

TEST_CASE("ray inputs feed the unit direction in object space and the entry offsets to the MLP") {
    const auto bytes = ray_inputs_model_bytes();
    lsnif_model* model = nullptr;
    REQUIRE(lsnif_open_memory(bytes.data(), bytes.size(), &model, nullptr) == LSNIF_OK);
    // The wiring is what is checked, in the reference arithmetic: the 8-bit hidden layers
    // lsnif_open picks on CPUs with AVX-512 VNNI move t by ~0.3 % on this hand-made model.
    REQUIRE(lsnif_set_arithmetic(model, LSNIF_ARITHMETIC_FP32, nullptr) == LSNIF_OK);
    lsnif_ray rays[5] = {
        {{-3.f, 0.1f, 0.1f}, 0.f, {1.f, 0.f, 0.f}, INFINITY},    // dir_x 1: hit
        {{-3.f, 0.1f, 0.1f}, 0.f, {0.25f, 0.f, 0.f}, INFINITY},  // short, still dir_x 1: hit
        {{3.f, 0.1f, 0.1f}, 0.f, {-1.f, 0.f, 0.f}, INFINITY},    // dir_x -1: miss
        {{-3.f, -2.9f, 0.1f}, 0.f, {1.f, 1.f, 0.f}, INFINITY},   // dir_x 0.707 < 0.75: miss
        {{-3.f, -0.75f, 0.1f}, 0.f, {4.f, 1.f, 0.f}, INFINITY},  // dir_x 0.970: hit
    };
    lsnif_hit hits[5];
    REQUIRE(lsnif_intersect(model, rays, 5, hits) == LSNIF_OK);
    CHECK(hits[0].hit == 1);
    CHECK(hits[1].hit == 1);
    // Entries at x = -0.5, -0.25, 0, 0.25: slot 2's offset is 0.5 / diagonal, so t is the
    // entry at x = 0 (t = 3 for |d| = 1, 12 for |d| = 0.25).
    CHECK(hits[0].t == doctest::Approx(3.0f).epsilon(2e-3));
    CHECK(hits[1].t == doctest::Approx(12.0f).epsilon(2e-3));
    CHECK(hits[2].hit == 0);
    CHECK(hits[3].hit == 0);
    CHECK(hits[4].hit == 1);
    // Under an instance the direction is the object-space one: a world ray that maps to +x
    // hits whatever the instance's rotation and scale.
    const lsnif_ray world[2] = {to_world(rays[0]), to_world(rays[2])};
    lsnif_hit wh[2];
    REQUIRE(lsnif_intersect_instance(model, kInstance, world, 2, wh) == LSNIF_OK);
    CHECK(wh[0].hit == 1);
    CHECK(wh[1].hit == 0);
    lsnif_close(model);

    // unit_direction: the ray direction over its length, the same bits from both walks.
    const Geometry geo = make_geometry(desc_with(8, {-1.f, -1.f, -1.f}, {1.f, 1.f, 1.f}));
    const Ray r{{-0.3f, -0.4f, -1.2f}, 0.f, {3.f, 4.f, 12.f}, INFINITY};
    float u[3];
    unit_direction(r, u);
    CHECK(u[0] == 3.f / 13.f);
    CHECK(u[1] == 4.f / 13.f);
    CHECK(u[2] == 12.f / 13.f);
    RayPoints p;
    std::vector<std::uint8_t> all(8 * 8 * 8 / 8, 0xFF);
    REQUIRE(trace_points(geo, all.data(), r, p) == TraceStatus::ok);
    CHECK(std::memcmp(p.dir, u, sizeof u) == 0);
    // entry_offsets: the distance along the ray from the first entry, over the diagonal.
    REQUIRE(p.count > 3);
    std::vector<float> offsets(geo.H, -1.0f);
    entry_offsets(geo, p, offsets.data());
    for (std::uint32_t k = 0; k < geo.H; ++k)
        if (k < p.count)
            CHECK(offsets[k] == doctest::Approx((p.t[k] - p.t[0]) * 13.0f / geo.diagonal).epsilon(1e-5));
        else
            CHECK(offsets[k] == 0.0f);
}

TEST_CASE("C API intersect: occupancy early-out, decode, and instance transforms") {
    const auto bytes = constant_model_bytes(2.0f, 0.25f, {0.f, 0.f, 2.f});
    lsnif_model* model = nullptr;
    REQUIRE(lsnif_open_memory(bytes.data(), bytes.size(), &model, nullptr) == LSNIF_OK);
    const float diag = 2.0f * std::sqrt(3.0f);
    lsnif_ray rays[4] = {
        {{-3.f, 0.1f, 0.1f}, 0.f, {1.f, 0.f, 0.f}, INFINITY},  // crosses the block: enters at x = -0.5
        {{-3.f, 0.9f, 0.1f}, 0.f, {1.f, 0.f, 0.f}, INFINITY},  // only empty voxels: culled
        {{-3.f, 0.1f, 0.1f}, 0.f, {0.f, 0.f, 0.f}, INFINITY},  // invalid
        {{-3.f, 0.1f, 0.1f}, 0.f, {2.f, 0.f, 0.f}, 1.0f},      // ends before the block
    };
    lsnif_hit hits[4];
    REQUIRE(lsnif_intersect(model, rays, 4, hits) == LSNIF_OK);
    CHECK(hits[0].hit == 1);
    CHECK(hits[0].t == doctest::Approx(2.5f + 0.25f * diag));
    CHECK(hits[0].normal[2] == 1.0f);
    CHECK(hits[1].hit == 0);
    CHECK(std::isinf(hits[1].t));
    CHECK(hits[2].hit == 0);
    CHECK(hits[3].hit == 0);

    // Instance (kInstance): world rays are object rays mapped.
    lsnif_ray world[1] = {to_world(rays[0])};
    lsnif_hit wh[1];
    REQUIRE(lsnif_intersect_instance(model, kInstance, world, 1, wh) == LSNIF_OK);
    CHECK(wh[0].hit == 1);
    CHECK(wh[0].t == doctest::Approx(hits[0].t).epsilon(1e-5));  // same parameter in both spaces
    CHECK(wh[0].normal[2] == doctest::Approx(1.0f));             // z-axis normal stays z under this map
    const float singular[12] = {1, 0, 0, 0, 0, 0, 0, 0, 0, 0, 1, 0};
    CHECK(lsnif_intersect_instance(model, singular, world, 1, wh) == LSNIF_ERR_INVALID_ARGUMENT);
    CHECK(lsnif_intersect(nullptr, rays, 1, hits) == LSNIF_ERR_INVALID_ARGUMENT);
    lsnif_close(model);
}
