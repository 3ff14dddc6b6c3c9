// lsnif::voxelize against an exact oracle: CGAL's do_intersect on Epeck (exact rational
// constructions), with the voxel cells built exactly as box_min + k * (box_max - box_min) / V.
//
// Checked for every triangle: (1) no miss: every voxel the oracle says overlaps is marked;
// (2) every false positive is explained by the documented slack, i.e. the triangle meets the
// cell grown by 2 * tau_T (voxelize.hpp); (3) nothing is marked outside the triangle's
// AABB ± 1 voxel. False positives are counted and reported.
#include <lsnif/voxelize/voxelize.hpp>

#include "off_mesh.hpp"

#include <CGAL/Exact_predicates_exact_constructions_kernel.h>
#include <CGAL/intersections.h>
#include <doctest/doctest.h>

#include <algorithm>
#include <array>
#include <cmath>
#include <cstdint>
#include <cstdio>
#include <limits>
#include <random>
#include <string>
#include <utility>
#include <vector>

namespace vx = lsnif::voxelize;
using vx::testing::TriMesh;

namespace {

using K = CGAL::Exact_predicates_exact_constructions_kernel;
using FT = K::FT;
using Point = K::Point_3;
using Segment = K::Segment_3;
using Triangle = K::Triangle_3;
using Cuboid = K::Iso_cuboid_3;
using Vec3 = std::array<float, 3>;
using Tri = std::array<Vec3, 3>;

constexpr float kInf = std::numeric_limits<float>::infinity();

vx::MeshView view(const TriMesh& m) {
    return {m.positions, m.indices};
}

TriMesh soup(const std::vector<Tri>& tris) {
    TriMesh m;
    for (const Tri& t : tris) {
        for (const Vec3& p : t) {
            m.indices.push_back(std::uint32_t(m.positions.size() / 3));
            m.positions.insert(m.positions.end(), p.begin(), p.end());
        }
    }
    return m;
}

vx::Box cube_box(float lo, float hi) {
    return vx::Box{{lo, lo, lo}, {hi, hi, hi}};
}

// Exact voxel cells.
struct ExactGrid {
    std::array<std::vector<FT>, 3> plane;  // plane[a][k], k = 0..V
    std::array<FT, 3> cell;
    explicit ExactGrid(const vx::Box& box, std::uint32_t v) {
        for (int a = 0; a < 3; ++a) {
            const FT lo(double(box.min[a])), hi(double(box.max[a]));
            cell[a] = (hi - lo) / FT(int(v));
            for (std::uint32_t k = 0; k <= v; ++k) plane[a].push_back(lo + cell[a] * FT(int(k)));
        }
    }
    Cuboid cuboid(int x, int y, int z) const {
        return {Point(plane[0][x], plane[1][y], plane[2][z]),
                Point(plane[0][x + 1], plane[1][y + 1], plane[2][z + 1])};
    }
    // The cell grown by r cell widths on every side.
    Cuboid grown(int x, int y, int z, double r) const {
        const FT rr(r);
        return {Point(plane[0][x] - rr * cell[0], plane[1][y] - rr * cell[1], plane[2][z] - rr * cell[2]),
                Point(plane[0][x + 1] + rr * cell[0], plane[1][y + 1] + rr * cell[1],
                      plane[2][z + 1] + rr * cell[2])};
    }
};

// A triangle as a CGAL object of its true dimension: CGAL's Triangle_3 test assumes a
// non-degenerate triangle, so collinear inputs become a segment or a point.
struct ExactTri {
    enum Kind { kPoint, kSegment, kTriangle } kind;
    Point p;
    Segment s;
    Triangle t;
    explicit ExactTri(const Tri& tri) {
        Point q[3];
        for (int i = 0; i < 3; ++i) q[i] = Point(double(tri[i][0]), double(tri[i][1]), double(tri[i][2]));
        if (!CGAL::collinear(q[0], q[1], q[2])) {
            kind = kTriangle;
            t = Triangle(q[0], q[1], q[2]);
        } else if (q[0] == q[1] && q[1] == q[2]) {
            kind = kPoint;
            p = q[0];
        } else {
            kind = kSegment;
            int bi = 0, bj = 1;
            FT best = CGAL::squared_distance(q[0], q[1]);
            for (auto [i, j] : {std::pair{1, 2}, std::pair{0, 2}}) {
                const FT d = CGAL::squared_distance(q[i], q[j]);
                if (d > best) best = d, bi = i, bj = j;
            }
            s = Segment(q[bi], q[bj]);
        }
    }
    bool overlaps(const Cuboid& c) const {
        switch (kind) {
            case kPoint: return !c.has_on_unbounded_side(p);
            case kSegment: return CGAL::do_intersect(s, c);
            case kTriangle: return CGAL::do_intersect(t, c);
        }
        return true;
    }
};

// Voxel range [lo, hi] per axis certainly containing every voxel the triangle can touch
// (its grid-space AABB ± 1 voxel), or empty.
struct Range {
    int lo[3], hi[3];
    bool empty = false;
    bool contains(int x, int y, int z) const {
        return !empty && x >= lo[0] && x <= hi[0] && y >= lo[1] && y <= hi[1] && z >= lo[2] && z <= hi[2];
    }
};

struct Grid01 {
    double origin[3], scale[3];
    std::uint32_t v;
    Grid01(const vx::Box& box, std::uint32_t v_) : v(v_) {
        for (int a = 0; a < 3; ++a) {
            origin[a] = box.min[a];
            scale[a] = double(v) / (double(box.max[a]) - double(box.min[a]));
        }
    }
    Range range(const Tri& t) const {
        Range r;
        for (int a = 0; a < 3; ++a) {
            double lo = std::numeric_limits<double>::infinity(), hi = -lo;
            for (const Vec3& p : t) {
                const double g = (double(p[a]) - origin[a]) * scale[a];
                lo = std::min(lo, g), hi = std::max(hi, g);
            }
            const double l = std::floor(lo) - 1, h = std::floor(hi) + 1;
            if (h < 0 || l > double(v) - 1) {
                r.empty = true;
                return r;
            }
            r.lo[a] = int(std::max(l, 0.0));
            r.hi[a] = int(std::min(h, double(v) - 1));
        }
        return r;
    }
    // tau_T of voxelize.hpp.
    double tau(const Tri& t) const {
        double mag = v;
        for (const Vec3& p : t)
            for (int a = 0; a < 3; ++a) mag = std::max(mag, std::fabs((double(p[a]) - origin[a]) * scale[a]));
        return vx::kSlackFactor * (mag + 1.0);
    }
};

struct Stats {
    std::size_t triangles = 0, true_voxels = 0, marked = 0, misses = 0, false_positives = 0, unexplained = 0;
    std::string first_problem;
    void note(const std::string& what) {
        if (first_problem.empty()) first_problem = what;
    }
};

std::string describe(const Tri& t) {
    std::string s = "triangle";
    for (const Vec3& p : t) {
        char buf[128];
        std::snprintf(buf, sizeof buf, " (%.9g, %.9g, %.9g)", double(p[0]), double(p[1]), double(p[2]));
        s += buf;
    }
    return s;
}

std::string voxel_name(int x, int y, int z) {
    return "voxel (" + std::to_string(x) + ", " + std::to_string(y) + ", " + std::to_string(z) + ")";
}

// Voxelizes each triangle on its own and compares with the oracle on every voxel.
Stats check_each(const std::vector<Tri>& tris, const vx::Box& box, std::uint32_t v) {
    const ExactGrid grid(box, v);
    const Grid01 g01(box, v);
    Stats st;
    for (const Tri& tri : tris) {
        const TriMesh m = soup({tri});
        const auto occ = vx::voxelize(view(m), box, v, {1});
        REQUIRE_MESSAGE(occ.ok(), occ.error().message);
        const ExactTri et(tri);
        const Range r = g01.range(tri);
        const double slack = 2 * g01.tau(tri);
        ++st.triangles;
        for (int z = 0; z < int(v); ++z)
            for (int y = 0; y < int(v); ++y)
                for (int x = 0; x < int(v); ++x) {
                    const bool marked = occ->occupied(x, y, z);
                    st.marked += marked;
                    if (!r.contains(x, y, z)) {
                        if (marked) {
                            ++st.unexplained;
                            st.note(describe(tri) + ": marks far " + voxel_name(x, y, z));
                        }
                        continue;
                    }
                    const bool truth = et.overlaps(grid.cuboid(x, y, z));
                    st.true_voxels += truth;
                    if (truth && !marked) {
                        ++st.misses;
                        st.note(describe(tri) + ": misses " + voxel_name(x, y, z));
                    } else if (!truth && marked) {
                        ++st.false_positives;
                        if (!et.overlaps(grid.grown(x, y, z, slack))) {
                            ++st.unexplained;
                            st.note(describe(tri) + ": marks " + voxel_name(x, y, z) + " beyond the slack");
                        }
                    }
                }
    }
    return st;
}

// Voxelizes the whole mesh at once; the oracle runs on each triangle's AABB ± 1 voxel.
Stats check_mesh(const TriMesh& m, const vx::Box& box, std::uint32_t v, unsigned threads) {
    const auto occ = vx::voxelize(view(m), box, v, {threads});
    REQUIRE_MESSAGE(occ.ok(), occ.error().message);
    const ExactGrid grid(box, v);
    const Grid01 g01(box, v);
    const std::size_t nv = std::size_t(v) * v * v;
    std::vector<std::uint8_t> truth(nv, 0), near(nv, 0);
    std::vector<Tri> tris(m.triangle_count());
    Stats st;
    st.triangles = tris.size();
    for (std::size_t t = 0; t < tris.size(); ++t) {
        for (int i = 0; i < 3; ++i)
            for (int a = 0; a < 3; ++a) tris[t][i][a] = m.positions[3 * m.indices[3 * t + i] + a];
        const ExactTri et(tris[t]);
        const Range r = g01.range(tris[t]);
        if (r.empty) continue;
        for (int z = r.lo[2]; z <= r.hi[2]; ++z)
            for (int y = r.lo[1]; y <= r.hi[1]; ++y)
                for (int x = r.lo[0]; x <= r.hi[0]; ++x) {
                    const std::size_t i = vx::Occupancy::index(v, x, y, z);
                    near[i] = 1;
                    if (truth[i] || !et.overlaps(grid.cuboid(x, y, z))) continue;
                    truth[i] = 1;
                    if (!occ->occupied(x, y, z)) {
                        ++st.misses;
                        st.note(describe(tris[t]) + ": misses " + voxel_name(x, y, z));
                    }
                }
    }
    for (int z = 0; z < int(v); ++z)
        for (int y = 0; y < int(v); ++y)
            for (int x = 0; x < int(v); ++x) {
                const std::size_t i = vx::Occupancy::index(v, x, y, z);
                st.true_voxels += truth[i];
                if (!occ->occupied(x, y, z)) continue;
                ++st.marked;
                if (truth[i]) continue;
                ++st.false_positives;
                bool explained = false;
                for (std::size_t t = 0; t < tris.size() && near[i] && !explained; ++t) {
                    if (g01.range(tris[t]).contains(x, y, z))
                        explained = ExactTri(tris[t]).overlaps(grid.grown(x, y, z, 2 * g01.tau(tris[t])));
                }
                if (!explained) {
                    ++st.unexplained;
                    st.note("marked " + voxel_name(x, y, z) + " is not within the slack of any triangle");
                }
            }
    return st;
}

void report(const char* name, const Stats& st) {
    MESSAGE(std::string(name) << ": " << st.triangles << " triangles, " << st.true_voxels
                              << " overlapping voxels, " << st.marked << " marked, misses " << st.misses
                              << ", false positives " << st.false_positives << " (unexplained "
                              << st.unexplained << ")");
    CHECK_MESSAGE(st.misses == 0, st.first_problem);
    CHECK_MESSAGE(st.unexplained == 0, st.first_problem);
}

struct Rng {
    std::mt19937_64 gen;
    explicit Rng(std::uint64_t seed) : gen(seed) {}
    double uniform(double lo, double hi) { return std::uniform_real_distribution<double>(lo, hi)(gen); }
    int integer(int lo, int hi) { return std::uniform_int_distribution<int>(lo, hi)(gen); }
    bool coin() { return integer(0, 1) == 1; }
    Vec3 point(double lo, double hi) {
        return {float(uniform(lo, hi)), float(uniform(lo, hi)), float(uniform(lo, hi))};
    }
    Vec3 lattice(int lo, int hi, float step = 1.0f) {
        return {float(integer(lo, hi)) * step, float(integer(lo, hi)) * step, float(integer(lo, hi)) * step};
    }
    // A random triangle around `c` with edge lengths around `size`.
    Tri around(const Vec3& c, double size) {
        Tri t;
        for (Vec3& p : t)
            for (int a = 0; a < 3; ++a) p[a] = float(c[a] + uniform(-size, size));
        return t;
    }
};

float ulp_up(float f, int n = 1) {
    while (n-- > 0) f = std::nextafter(f, kInf);
    return f;
}
float ulp_down(float f, int n = 1) {
    while (n-- > 0) f = std::nextafter(f, -kInf);
    return f;
}

}  // namespace

TEST_CASE("random triangles of all sizes match the exact oracle") {
    Rng rng(1);
    for (const auto& [box, v] : {std::pair{cube_box(0, 8), 8u},
                                 std::pair{vx::Box{{-1.37f, 0.21f, -3.5f}, {2.91f, 0.26f, 7.25f}}, 7u}}) {
        std::vector<Tri> tris;
        for (int i = 0; i < 700; ++i) {
            Vec3 c;
            for (int a = 0; a < 3; ++a) c[a] = float(rng.uniform(box.min[a], box.max[a]));
            const double cell = (double(box.max[0]) - box.min[0]) / v;
            tris.push_back(rng.around(c, cell * std::exp(rng.uniform(std::log(1e-3), std::log(4.0)))));
        }
        const Stats st = check_each(tris, box, v);
        report("random", st);
        CHECK(st.false_positives == 0);  // nothing lands within 1e-10 voxel of a plane by chance
    }
}

TEST_CASE("lattice triangles: contacts at faces, edges and corners") {
    Rng rng(2);
    const vx::Box box = cube_box(0, 6);
    std::vector<Tri> tris;
    for (int i = 0; i < 1200; ++i) {  // integer vertices, including the box boundary and beyond
        tris.push_back({rng.lattice(-1, 7), rng.lattice(-1, 7), rng.lattice(-1, 7)});
    }
    for (int i = 0; i < 600; ++i) {  // small triangles on the half-integer lattice
        const Vec3 c = rng.lattice(0, 12, 0.5f);
        Tri t;
        for (Vec3& p : t)
            for (int a = 0; a < 3; ++a) p[a] = c[a] + 0.5f * float(rng.integer(-2, 2));
        tris.push_back(t);
    }
    report("lattice", check_each(tris, box, 6));
}

TEST_CASE("triangles lying in voxel face planes") {
    Rng rng(3);
    const vx::Box box = cube_box(0, 8);
    std::vector<Tri> tris;
    for (int i = 0; i < 900; ++i) {
        const int axis = rng.integer(0, 2);
        const float k = float(rng.integer(0, 8));  // includes the outer faces 0 and 8
        Tri t;
        const bool lattice = rng.coin();
        const Vec3 c = rng.point(0, 8);
        const double size = std::exp(rng.uniform(std::log(0.01), std::log(5.0)));
        for (Vec3& p : t) {
            p = lattice ? rng.lattice(-1, 9)
                        : Vec3{float(c[0] + rng.uniform(-size, size)), float(c[1] + rng.uniform(-size, size)),
                               float(c[2] + rng.uniform(-size, size))};
            p[axis] = k;
        }
        tris.push_back(t);
    }
    // Edge-on: the triangle stands perpendicular to a face plane with one edge in it.
    for (int i = 0; i < 300; ++i) {
        const float k = float(rng.integer(0, 8));
        Tri t = {rng.point(0, 8), rng.point(0, 8), rng.point(0, 8)};
        t[0][2] = t[1][2] = k;
        t[2][0] = t[0][0], t[2][1] = t[0][1];
        t[2][2] = k + (rng.coin() ? 1.0f : -1.0f) * float(rng.uniform(0.01, 3));
        tris.push_back(t);
    }
    report("face planes", check_each(tris, box, 8));
}

TEST_CASE("planes through voxel corners and edges only") {
    Rng rng(4);
    const vx::Box box = cube_box(0, 6);
    std::vector<Tri> tris;
    // x + y + z = s touches the cells whose minimum-corner sum is s at that corner only,
    // and the cells whose maximum-corner sum is s likewise.
    for (int s = -1; s <= 19; ++s) {
        const float f = float(s);
        tris.push_back({Vec3{f, 0, 0}, Vec3{0, f, 0}, Vec3{0, 0, f}});
        tris.push_back(
            {Vec3{f - 6, 3, 3}, Vec3{3, f - 6, 3}, Vec3{3, 3, f - 6}});  // same plane family, shifted
    }
    for (int i = 0; i < 600; ++i) {
        // Random lattice points on x + y + z = s, or (edge contacts) on x + y = s.
        const int s = rng.integer(0, 14);
        const bool corner = rng.coin();
        Tri t;
        for (Vec3& p : t) {
            const int x = rng.integer(-2, 8), y = corner ? rng.integer(-2, 8) : s - x;
            const int z = corner ? s - x - y : rng.integer(-2, 8);
            p = {float(x), float(y), float(z)};
        }
        tris.push_back(t);
    }
    // Small triangles whose vertex sits exactly on a voxel corner or edge, pointing away.
    for (int i = 0; i < 600; ++i) {
        Vec3 c = rng.lattice(0, 6);
        if (rng.coin()) c[rng.integer(0, 2)] += float(rng.uniform(0, 1));  // on an edge instead
        Tri t = {c, c, c};
        for (int j = 1; j < 3; ++j)
            for (int a = 0; a < 3; ++a) t[j][a] += float(rng.uniform(0.0, 0.9)) * (rng.coin() ? 1.0f : 0.0f);
        tris.push_back(t);
    }
    report("corners and edges", check_each(tris, box, 6));
}

TEST_CASE("slivers, needles and near-degenerate triangles") {
    Rng rng(5);
    const vx::Box box = cube_box(0, 8);
    std::vector<Tri> tris;
    for (int i = 0; i < 400; ++i) {  // two vertices a hair apart, third far away
        const Vec3 a = rng.point(-1, 9), c = rng.point(-1, 9);
        Vec3 b = a;
        const int axis = rng.integer(0, 2);
        b[axis] = ulp_up(b[axis], rng.integer(1, 1000));
        tris.push_back({a, b, c});
    }
    for (int i = 0; i < 400; ++i) {  // third vertex a hair off the segment between the others
        const Vec3 a = rng.lattice(-1, 9), b = rng.lattice(-1, 9);
        Vec3 m = {0.5f * (a[0] + b[0]), 0.5f * (a[1] + b[1]), 0.5f * (a[2] + b[2])};
        const int axis = rng.integer(0, 2);
        m[axis] = rng.coin() ? ulp_up(m[axis], rng.integer(1, 4)) : ulp_down(m[axis], rng.integer(1, 4));
        tris.push_back({a, b, m});
    }
    for (int i = 0; i < 400; ++i) {  // needles along voxel edges, slightly tilted
        const float y = float(rng.integer(0, 8)), z = float(rng.integer(0, 8));
        Tri t = {Vec3{float(rng.uniform(-1, 9)), y, z}, Vec3{float(rng.uniform(-1, 9)), y, z},
                 Vec3{float(rng.uniform(-1, 9)), y, z}};
        t[2][1] = rng.coin() ? ulp_up(y) : ulp_down(y);
        tris.push_back(t);
    }
    report("slivers", check_each(tris, box, 8));
}

TEST_CASE("degenerate triangles: segments and points") {
    Rng rng(6);
    const vx::Box box = cube_box(0, 6);
    std::vector<Tri> tris;
    for (int i = 0; i < 500; ++i) {  // exactly collinear lattice points (zero area)
        const Vec3 a = rng.lattice(-1, 7);
        const Vec3 d = rng.lattice(-2, 2, 0.5f);
        const float s = float(rng.integer(1, 3)), u = float(rng.integer(-2, 2));
        tris.push_back({a, Vec3{a[0] + s * d[0], a[1] + s * d[1], a[2] + s * d[2]},
                        Vec3{a[0] + u * d[0], a[1] + u * d[1], a[2] + u * d[2]}});
    }
    for (int i = 0; i < 400; ++i) {  // repeated vertex: a segment, random or on the lattice
        const Vec3 a = rng.coin() ? rng.lattice(-1, 7, 0.5f) : rng.point(-1, 7);
        const Vec3 b = rng.coin() ? rng.lattice(-1, 7, 0.5f) : rng.point(-1, 7);
        tris.push_back({a, b, a});
    }
    for (int i = 0; i < 600; ++i) {  // single points: lattice corners, edges, faces, anywhere
        Vec3 p = rng.lattice(-1, 7);
        const int free_axes = rng.integer(0, 3);
        for (int a = 0; a < free_axes; ++a) p[a] += float(rng.uniform(0, 1));
        tris.push_back({p, p, p});
    }
    report("degenerate", check_each(tris, box, 6));
}

TEST_CASE("huge triangles spanning the grid") {
    Rng rng(7);
    std::vector<Tri> tris;
    // Centroid inside the box, vertices r = 1 to 1e5 box sizes away.
    auto through = [&](const vx::Box& box, double r_max) {
        Vec3 q;
        for (int k = 0; k < 3; ++k) q[k] = float(rng.uniform(box.min[k], box.max[k]));
        const double r = (double(box.max[0]) - box.min[0]) * std::exp(rng.uniform(0.0, std::log(r_max)));
        const Vec3 a = rng.point(-r, r), b = rng.point(-r, r);
        Tri t;
        for (int k = 0; k < 3; ++k)
            t[0][k] = q[k] + a[k], t[1][k] = q[k] + b[k], t[2][k] = q[k] - a[k] - b[k];
        return t;
    };
    for (int i = 0; i < 300; ++i) tris.push_back(through(cube_box(0, 8), 1e5));
    const Stats big = check_each(tris, cube_box(0, 8), 8);
    report("huge V=8", big);
    CHECK(big.true_voxels > 10000);
    const vx::Box odd{{-0.5f, 1.0f, -2.0f}, {8.5f, 7.0f, 9.0f}};
    std::vector<Tri> few;
    for (int i = 0; i < 8; ++i) few.push_back(through(odd, 10.0));
    const Stats st = check_each(few, odd, 24);
    report("huge V=24", st);
    CHECK(st.true_voxels > 1000);
}

TEST_CASE("vertices exactly on, and one ulp beside, grid planes") {
    Rng rng(8);
    // (a) a box whose planes are floats: min -2, max 2, V 8, cell 0.5.
    {
        std::vector<Tri> tris;
        for (int i = 0; i < 800; ++i) {
            Tri t;
            for (Vec3& p : t) {
                p = rng.lattice(-5, 5, 0.5f);
                if (rng.integer(0, 3) == 0) p[rng.integer(0, 2)] = float(rng.uniform(-2.5, 2.5));
            }
            tris.push_back(t);
        }
        report("float planes", check_each(tris, cube_box(-2, 2), 8));
    }
    // (b) a box whose planes are not floats: vertices are the nearest floats around them.
    {
        const vx::Box box{{-1.3f, -0.7f, 0.1f}, {2.9f, 3.3f, 1.7f}};
        const std::uint32_t v = 7;
        auto near_plane = [&](int a, int k) {
            const double exact = double(box.min[a]) + k * ((double(box.max[a]) - double(box.min[a])) / v);
            const float f = float(exact);
            const int r = rng.integer(0, 2);
            return r == 0 ? f : r == 1 ? ulp_up(f) : ulp_down(f);
        };
        std::vector<Tri> tris;
        for (int i = 0; i < 800; ++i) {
            Tri t;
            for (Vec3& p : t)
                for (int a = 0; a < 3; ++a)
                    p[a] = rng.integer(0, 4) == 0 ? float(rng.uniform(box.min[a], box.max[a]))
                                                  : near_plane(a, rng.integer(0, 7));
            tris.push_back(t);
        }
        report("near planes, odd box", check_each(tris, box, v));
    }
    // (c) planes that are floats (-1.25 + 0.75 k) under a grid scale that is not (V / 4.5):
    //     exact contacts whose computed grid coordinates are rounded off the plane.
    {
        const vx::Box box = cube_box(-1.25f, 3.25f);
        std::vector<Tri> tris;
        for (int i = 0; i < 1500; ++i) {
            Tri t;
            for (Vec3& p : t) {
                p = rng.lattice(-2, 14);
                for (float& c : p) c = -1.25f + 0.375f * c;  // planes and half-cell points
                if (rng.integer(0, 3) == 0) p[rng.integer(0, 2)] = float(rng.uniform(-1.5, 3.5));
            }
            tris.push_back(t);
        }
        report("float planes, inexact scale", check_each(tris, box, 6));
    }
    // (d) integer planes, vertices 1-3 ulps off them (closer than the slack: false positives
    //     are expected here and must all be explained).
    {
        std::vector<Tri> tris;
        for (int i = 0; i < 800; ++i) {
            const Vec3 c = rng.lattice(0, 8);
            Tri t;
            for (Vec3& p : t) {
                p = c;
                for (int a = 0; a < 3; ++a) {
                    const int r = rng.integer(0, 4);
                    if (r == 0) p[a] = ulp_up(p[a], rng.integer(1, 3));
                    if (r == 1) p[a] = ulp_down(p[a], rng.integer(1, 3));
                    if (r == 2) p[a] += float(rng.uniform(-0.7, 0.7));
                }
            }
            tris.push_back(t);
        }
        report("ulp off planes", check_each(tris, cube_box(0, 8), 8));
    }
}

TEST_CASE("extreme magnitudes: huge and subnormal boxes and coordinates") {
    Rng rng(11);
    auto wild = [&](double scale) {
        // Random sign, exponent spread over 2^-20..2^20 of `scale`, or exactly 0.
        if (rng.integer(0, 9) == 0) return 0.0f;
        const double m = std::ldexp(rng.uniform(0.5, 1.0), rng.integer(-20, 20));
        return float((rng.coin() ? 1 : -1) * m * scale);
    };
    const std::vector<std::pair<vx::Box, std::uint32_t>> boxes = {
        {cube_box(-1e30f, 1e30f), 5},
        {cube_box(-3e-39f, 4e-39f), 6},                     // subnormal-scale box
        {vx::Box{{0, 0, 0}, {1e-44f, 1e-44f, 1e-44f}}, 3},  // a few denormal ulps wide
        {vx::Box{{-3.4e38f, -1, 1e20f}, {3.4e38f, 1, 1.0001e20f}}, 4},
    };
    for (const auto& [box, v] : boxes) {
        std::vector<Tri> tris;
        for (int i = 0; i < 200; ++i) {
            Tri t;
            for (Vec3& p : t)
                for (int a = 0; a < 3; ++a) {
                    const double mid = 0.5 * (double(box.min[a]) + double(box.max[a]));
                    const double ext = double(box.max[a]) - double(box.min[a]);
                    p[a] = float(std::clamp(mid + double(wild(float(ext))), -3.4e38, 3.4e38));
                }
            tris.push_back(t);
        }
        report("extreme", check_each(tris, box, v));
    }
}

TEST_CASE("triangles outside the box or touching its boundary") {
    Rng rng(9);
    const vx::Box box = cube_box(0, 4);
    std::vector<Tri> tris;
    for (int i = 0; i < 500; ++i) {
        const int axis = rng.integer(0, 2);
        const bool high = rng.coin();
        Tri t = {rng.point(-2, 6), rng.point(-2, 6), rng.point(-2, 6)};
        for (Vec3& p : t) {  // push the triangle outside, one vertex exactly on the face
            p[axis] = high ? 4.0f + float(rng.uniform(0, 2)) : -float(rng.uniform(0, 2));
        }
        if (rng.coin()) t[0][axis] = high ? 4.0f : 0.0f;
        tris.push_back(t);
    }
    const Stats st = check_each(tris, box, 4);
    report("outside", st);

    // Wholly outside: nothing marked.
    const TriMesh far = soup({Tri{Vec3{5, 5, 5}, Vec3{6, 5, 5}, Vec3{5, 6, 5}},
                              Tri{Vec3{-1, 2, 2}, Vec3{-1, 3, 2}, Vec3{-0.5f, 2, 3}}});
    const auto occ = vx::voxelize(view(far), box, 4);
    REQUIRE(occ.ok());
    CHECK(occ->count() == 0);
}

TEST_CASE("real meshes at V=32 against the oracle, and thread-count independence") {
    for (const char* name : {"ChineseDragon-10kv.off", "armadillo.off"}) {
        std::string err;
        const auto mesh = vx::testing::read_off(std::string(LSNIF_VOXELIZE_MESH_DIR) + "/" + name, err);
        REQUIRE_MESSAGE(mesh.has_value(), err);
        const auto box = vx::padded_box(view(*mesh));
        REQUIRE_MESSAGE(box.ok(), box.error().message);
        const Stats st = check_mesh(*mesh, *box, 32, 2);
        report(name, st);
        CHECK(st.false_positives == 0);
        CHECK(st.true_voxels > 1000);

        const auto one = vx::voxelize(view(*mesh), *box, 32, {1});
        const auto two = vx::voxelize(view(*mesh), *box, 32, {2});
        const auto five = vx::voxelize(view(*mesh), *box, 32, {5});
        REQUIRE((one.ok() && two.ok() && five.ok()));
        CHECK(one->bits == two->bits);
        CHECK(one->bits == five->bits);
    }
}

TEST_CASE("bit layout follows FORMAT.md §6.3") {
    const vx::Box box = cube_box(0, 3);  // V = 3: 27 bits in 4 bytes, 5 unused
    // A tiny triangle strictly inside voxel (2, 1, 0): index 2 + 3 * 1 = 5.
    const TriMesh one = soup({Tri{Vec3{2.4f, 1.4f, 0.4f}, Vec3{2.6f, 1.4f, 0.4f}, Vec3{2.4f, 1.6f, 0.6f}}});
    auto occ = vx::voxelize(view(one), box, 3);
    REQUIRE(occ.ok());
    CHECK(occ->resolution == 3);
    CHECK(occ->bits == std::vector<std::uint8_t>{0x20, 0, 0, 0});
    CHECK(occ->occupied(2, 1, 0));
    CHECK(occ->count() == 1);

    // One tiny triangle per voxel: every used bit set, the unused high bits of byte 3 clear.
    std::vector<Tri> all;
    for (int z = 0; z < 3; ++z)
        for (int y = 0; y < 3; ++y)
            for (int x = 0; x < 3; ++x)
                all.push_back({Vec3{x + 0.5f, y + 0.5f, z + 0.5f}, Vec3{x + 0.6f, y + 0.5f, z + 0.5f},
                               Vec3{x + 0.5f, y + 0.6f, z + 0.5f}});
    occ = vx::voxelize(view(soup(all)), box, 3);
    REQUIRE(occ.ok());
    CHECK(occ->bits == std::vector<std::uint8_t>{0xFF, 0xFF, 0xFF, 0x07});
    CHECK(occ->count() == 27);

    // z varies slowest: a point in voxel (0, 0, 2) is bit 18 = byte 2, bit 2.
    occ = vx::voxelize(
        view(soup({Tri{Vec3{0.5f, 0.5f, 2.5f}, Vec3{0.5f, 0.5f, 2.5f}, Vec3{0.5f, 0.5f, 2.5f}}})), box, 3);
    REQUIRE(occ.ok());
    CHECK(occ->bits == std::vector<std::uint8_t>{0, 0, 0x04, 0});

    // V = 1 and V = 256 are accepted.
    CHECK(vx::voxelize(view(one), box, 1)->bits == std::vector<std::uint8_t>{0x01});
    const auto big = vx::voxelize(view(one), box, 256);
    REQUIRE(big.ok());
    CHECK(big->bits.size() == 256u * 256u * 256u / 8u);
    CHECK(big->count() > 0);
}

TEST_CASE("many triangles: same bits for every thread count") {
    Rng rng(10);
    std::vector<Tri> tris;
    for (int i = 0; i < 60000; ++i)
        tris.push_back(rng.around(rng.point(0, 1), std::exp(rng.uniform(std::log(1e-4), std::log(0.3)))));
    const TriMesh m = soup(tris);
    const vx::Box box = cube_box(0, 1);
    const auto ref = vx::voxelize(view(m), box, 32, {1});
    REQUIRE(ref.ok());
    for (unsigned threads : {0u, 2u, 3u, 8u}) {
        const auto occ = vx::voxelize(view(m), box, 32, {threads});
        REQUIRE(occ.ok());
        CHECK(occ->bits == ref->bits);
    }
    // Validation runs inside the parallel passes; the reported problem is still the first.
    TriMesh bad = m;
    bad.indices[3 * 40000 + 1] = 900000;
    bad.indices[3 * 50000 + 2] = 800000;
    for (unsigned threads : {1u, 2u, 3u}) {
        const auto occ = vx::voxelize(view(bad), box, 32, {threads});
        REQUIRE_FALSE(occ.ok());
        CHECK(occ.error().message == "triangle 40000: index 900000 is out of range (180000 vertices)");
    }
    bad.positions[3 * 170000 + 2] = std::nanf("");
    bad.positions[3 * 20000] = kInf;
    for (unsigned threads : {1u, 2u, 3u}) {
        const auto occ = vx::voxelize(view(bad), box, 32, {threads});
        REQUIRE_FALSE(occ.ok());
        CHECK(occ.error().message == "vertex 20000: coordinate x is infinite");
    }
}

TEST_CASE("padded_box") {
    SUBCASE("pads by 1/64 of the largest extent and strictly contains the vertices") {
        const TriMesh m = soup({Tri{Vec3{0, 0, 0}, Vec3{64, 0, 0}, Vec3{0, 32, 16}}});
        const auto box = vx::padded_box(view(m));
        REQUIRE(box.ok());
        CHECK(box->min == Vec3{-1, -1, -1});
        CHECK(box->max == Vec3{65, 33, 17});
    }
    SUBCASE("ignores unreferenced vertices") {
        TriMesh m = soup({Tri{Vec3{0, 0, 0}, Vec3{64, 0, 0}, Vec3{0, 64, 64}}});
        m.positions.insert(m.positions.end(), {1000, 1000, 1000});
        const auto box = vx::padded_box(view(m));
        REQUIRE(box.ok());
        CHECK(box->max == Vec3{65, 65, 65});
    }
    SUBCASE("a flat mesh gets the minimum thickness") {
        const TriMesh m = soup({Tri{Vec3{0, 0, 5}, Vec3{64, 0, 5}, Vec3{0, 64, 5}}});
        const auto box = vx::padded_box(view(m), {0.0, 1.0 / 16});
        REQUIRE(box.ok());
        CHECK(box->min == Vec3{-std::nextafter(0.0f, 1.0f), -std::nextafter(0.0f, 1.0f), 3});
        CHECK(box->max[2] == 7);
        const auto def = vx::padded_box(view(m));
        REQUIRE(def.ok());
        CHECK(def->max[2] - def->min[2] == 4);  // default: max(2 * 1/64, 1/16) * 64
    }
    SUBCASE("a mesh collapsed to a point, and padding below float resolution") {
        const TriMesh pt = soup({Tri{Vec3{3, 3, 3}, Vec3{3, 3, 3}, Vec3{3, 3, 3}}});
        const auto box = vx::padded_box(view(pt));
        REQUIRE(box.ok());
        for (int a = 0; a < 3; ++a)
            CHECK((box->min[a] < 3 && box->max[a] > 3 && box->max[a] - box->min[a] < 0.01f));

        const TriMesh far =
            soup({Tri{Vec3{1e30f, 1e30f, 1e30f}, Vec3{1e30f, 1e30f, 1e30f}, Vec3{1e30f, 1e30f, 1e30f}}});
        const auto fbox = vx::padded_box(view(far), {0.0, 1e-30});
        REQUIRE(fbox.ok());
        for (int a = 0; a < 3; ++a) CHECK((fbox->min[a] < 1e30f && fbox->max[a] > 1e30f));
    }
    SUBCASE("on a real mesh the padding is about half a voxel at V=32") {
        std::string err;
        const auto mesh =
            vx::testing::read_off(std::string(LSNIF_VOXELIZE_MESH_DIR) + "/ChineseDragon-10kv.off", err);
        REQUIRE_MESSAGE(mesh.has_value(), err);
        const auto box = vx::padded_box(view(*mesh));
        REQUIRE(box.ok());
        for (int a = 0; a < 3; ++a) {
            float lo = kInf, hi = -kInf;
            for (std::size_t i = std::size_t(a); i < mesh->positions.size(); i += 3)
                lo = std::min(lo, mesh->positions[i]), hi = std::max(hi, mesh->positions[i]);
            const double cell = (double(box->max[a]) - box->min[a]) / 32;
            CHECK((double(lo) - box->min[a]) / cell > 0.45);
            CHECK((double(box->max[a]) - hi) / cell > 0.45);
            CHECK((double(lo) - box->min[a]) / cell < 1.0);
        }
    }
    SUBCASE("errors") {
        CHECK(vx::padded_box(vx::MeshView{}).error().message == "mesh has no triangles");
        const TriMesh m = soup({Tri{Vec3{0, 0, 0}, Vec3{1, 0, 0}, Vec3{0, 1, 0}}});
        CHECK_FALSE(vx::padded_box(view(m), {-1.0, 0.1}).ok());
        CHECK_FALSE(vx::padded_box(view(m), {0.1, 0.0}).ok());
        CHECK_FALSE(vx::padded_box(view(m), {std::nan(""), 0.1}).ok());
        const TriMesh huge = soup({Tri{Vec3{-3.35e38f, 0, 0}, Vec3{3.35e38f, 0, 0}, Vec3{0, 1, 0}}});
        const auto r = vx::padded_box(view(huge));
        REQUIRE_FALSE(r.ok());
        CHECK(r.error().message.find("overflows float") != std::string::npos);
    }
}

TEST_CASE("invalid input is reported, never crashes") {
    const vx::Box box = cube_box(0, 1);
    TriMesh m = soup(
        {Tri{Vec3{0, 0, 0}, Vec3{1, 0, 0}, Vec3{0, 1, 0}}, Tri{Vec3{0, 0, 1}, Vec3{1, 0, 1}, Vec3{0, 1, 1}}});
    REQUIRE(vx::voxelize(view(m), box, 4).ok());

    auto error_of = [&](const TriMesh& mesh, const vx::Box& b, std::uint32_t v) {
        const auto r = vx::voxelize(view(mesh), b, v);
        REQUIRE_FALSE(r.ok());
        return r.error().message;
    };
    TriMesh bad = m;
    bad.positions[4] = std::nanf("");
    CHECK(error_of(bad, box, 4) == "vertex 1: coordinate y is NaN");
    CHECK(vx::padded_box(view(bad)).error().message == "vertex 1: coordinate y is NaN");
    bad = m;
    bad.positions.insert(bad.positions.end(), {0.5f, kInf, 0.5f});  // unreferenced, still rejected
    CHECK(error_of(bad, box, 4) == "vertex 6: coordinate y is infinite");
    bad = m;
    bad.positions[17] = -kInf;
    CHECK(error_of(bad, box, 4) == "vertex 5: coordinate z is infinite");
    bad = m;
    bad.indices[4] = 6;
    CHECK(error_of(bad, box, 4) == "triangle 1: index 6 is out of range (6 vertices)");
    CHECK(vx::padded_box(view(bad)).error().message == "triangle 1: index 6 is out of range (6 vertices)");
    bad.indices[4] = 0xFFFFFFFFu;
    CHECK(error_of(bad, box, 4) == "triangle 1: index 4294967295 is out of range (6 vertices)");
    const std::vector<std::uint32_t> zero_tri = {0, 0, 0};
    const auto no_vertices = vx::voxelize(vx::MeshView{{}, zero_tri}, box, 4);
    REQUIRE_FALSE(no_vertices.ok());
    CHECK(no_vertices.error().message == "triangle 0: index 0 is out of range (0 vertices)");
    bad = m;
    bad.indices.pop_back();
    CHECK(error_of(bad, box, 4).find("not a multiple of 3") != std::string::npos);
    bad = m;
    bad.positions.pop_back();
    CHECK(error_of(bad, box, 4).find("not a multiple of 3") != std::string::npos);

    CHECK(error_of(m, box, 0) == "resolution 0 is outside [1, 256]");
    CHECK(error_of(m, box, 257) == "resolution 257 is outside [1, 256]");
    CHECK(error_of(m, vx::Box{{0, 0, 0}, {1, 0, 1}}, 4).find("box: empty on axis y") == 0);
    CHECK(error_of(m, vx::Box{{0, 0, 2}, {1, 1, 1}}, 4).find("box: empty on axis z") == 0);
    CHECK(error_of(m, vx::Box{{std::nanf(""), 0, 0}, {1, 1, 1}}, 4) == "box: x bound is not finite");
    CHECK(error_of(m, vx::Box{{0, 0, 0}, {1, kInf, 1}}, 4) == "box: y bound is not finite");

    // An empty mesh is valid: nothing is occupied.
    const auto empty = vx::voxelize(vx::MeshView{}, box, 5);
    REQUIRE(empty.ok());
    CHECK(empty->bits == std::vector<std::uint8_t>(16, 0));
}
