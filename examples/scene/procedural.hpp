// Procedural geometry for the bundled example scene: boxes, a hairball of thin tubes, an
// OFF reader and one-step Loop subdivision.
//
// Everything here is deterministic across runs and, as far as IEEE-754 allows, across
// platforms: randomness comes from splitmix64 (never <random> distributions, whose
// algorithms differ between standard libraries), and the arithmetic uses only + - * / and
// sqrt (correctly rounded), no libm trigonometry. Build with -ffp-contract=off so the
// compiler does not fuse multiply-adds differently on different targets.
//
// Header-only; depends on the C++ standard library only. Functions never throw on bad
// input files and never exit: readers return false and fill an error message.
#pragma once

#include <lsnif/base/random.hpp>
#include <lsnif/base/vec3.hpp>

#include <algorithm>
#include <array>
#include <cmath>
#include <cstddef>
#include <cstdint>
#include <fstream>
#include <limits>
#include <sstream>
#include <string>
#include <tuple>
#include <vector>

namespace lsnif::examples {

// ---- small vector math ---------------------------------------------------------------

using Vec3 = base::Vec3d;  // lsnif/base/vec3.hpp: +, -, scalar *, dot, cross, length, normalize

// ---- triangle mesh ----------------------------------------------------------------------

// An indexed triangle mesh: counter-clockwise triangles (seen from outside) over a shared
// vertex array. Invariant: every index < positions.size(); indices.size() % 3 == 0.
struct TriMesh {
    std::vector<Vec3> positions;
    std::vector<std::uint32_t> indices;

    std::size_t triangle_count() const { return indices.size() / 3; }
};

struct Bounds {
    Vec3 min{std::numeric_limits<double>::infinity(), std::numeric_limits<double>::infinity(),
             std::numeric_limits<double>::infinity()};
    Vec3 max{-std::numeric_limits<double>::infinity(), -std::numeric_limits<double>::infinity(),
             -std::numeric_limits<double>::infinity()};
};

// Axis-aligned bounds of the positions (inverted infinities for an empty mesh).
inline Bounds mesh_bounds(const TriMesh& mesh) {
    Bounds b;
    for (const Vec3& p : mesh.positions) {
        b.min = {std::min(b.min.x, p.x), std::min(b.min.y, p.y), std::min(b.min.z, p.z)};
        b.max = {std::max(b.max.x, p.x), std::max(b.max.y, p.y), std::max(b.max.z, p.z)};
    }
    return b;
}

// Appends `part` to `mesh`, re-basing its indices.
inline void append_mesh(TriMesh& mesh, const TriMesh& part) {
    const auto base = static_cast<std::uint32_t>(mesh.positions.size());
    mesh.positions.insert(mesh.positions.end(), part.positions.begin(), part.positions.end());
    for (std::uint32_t i : part.indices) mesh.indices.push_back(base + i);
}

// ---- deterministic randomness -----------------------------------------------------------

// The toolchain's splitmix64 (lsnif/base/random.hpp) with the geometric draws the
// generators need. Same sequence on every platform, so the generated scenes are the same
// bytes everywhere.
class SplitMix64 {
public:
    explicit SplitMix64(std::uint64_t seed) : core_{seed} {}

    std::uint64_t next() { return core_.next(); }

    // Uniform in [0, 1) with 53 random bits.
    double uniform() { return core_.u01(); }

    // Uniform in [lo, hi).
    double uniform(double lo, double hi) { return lo + (hi - lo) * uniform(); }

    // Uniform in the unit ball (rejection sampling from the cube; no trigonometry).
    Vec3 in_unit_ball() {
        for (;;) {
            const Vec3 p{uniform(-1, 1), uniform(-1, 1), uniform(-1, 1)};
            if (dot(p, p) <= 1.0) return p;
        }
    }

    // Uniform on the unit sphere.
    Vec3 on_unit_sphere() {
        for (;;) {
            const Vec3 p{uniform(-1, 1), uniform(-1, 1), uniform(-1, 1)};
            const double d = dot(p, p);
            if (d <= 1.0 && d > 1e-6) return (1.0 / std::sqrt(d)) * p;
        }
    }

private:
    base::SplitMix64 core_;
};

// ---- boxes ------------------------------------------------------------------------------

// A closed axis-aligned box [lo, hi]: 8 shared corners and 12 outward-facing (CCW)
// triangles. Requires lo < hi componentwise.
inline TriMesh make_box(Vec3 lo, Vec3 hi) {
    TriMesh m;
    // Corner i has x = hi.x if (i & 1), y = hi.y if (i & 2), z = hi.z if (i & 4).
    for (int i = 0; i < 8; ++i) {
        m.positions.push_back({(i & 1) ? hi.x : lo.x, (i & 2) ? hi.y : lo.y, (i & 4) ? hi.z : lo.z});
    }
    // Each face as a quad (a, b, c, d) counter-clockwise seen from outside.
    static constexpr std::array<std::array<std::uint32_t, 4>, 6> kFaces{{
        {0, 4, 6, 2},  // -x
        {1, 3, 7, 5},  // +x
        {0, 1, 5, 4},  // -y
        {2, 6, 7, 3},  // +y
        {0, 2, 3, 1},  // -z
        {4, 5, 7, 6},  // +z
    }};
    for (const auto& q : kFaces) {
        m.indices.insert(m.indices.end(), {q[0], q[1], q[2], q[0], q[2], q[3]});
    }
    return m;
}

// A box of the given size resting on y = 0, centered on the y axis.
inline TriMesh make_box_on_floor(double size_x, double size_y, double size_z) {
    return make_box({-0.5 * size_x, 0.0, -0.5 * size_z}, {0.5 * size_x, size_y, 0.5 * size_z});
}

// ---- hairball ---------------------------------------------------------------------------

struct HairballParams {
    int tubes = 300;             // number of tubes, >= 1
    int segments = 20;           // segments per tube, >= 1
    double ball_radius = 0.5;    // outer radius of the shell the curves live in (size 1)
    double shell_inner = 0.70;   // inner radius of the shell, as a fraction of ball_radius
    double tube_radius = 0.004;  // radius of the hexagonal cross-section (0.004 of size 1)
    double step = 0.09;          // curve step length, as a fraction of ball_radius
    double wiggle = 0.35;        // random turn per step (0 = great-circle arcs)
    std::uint64_t seed = 0x15B1F5EEDull;
};

// Triangles a hairball with these parameters has: per tube, 6 sides * 2 * segments plus
// two hexagonal end caps of 4 triangles each.
inline std::size_t hairball_triangle_count(const HairballParams& p) {
    return std::size_t(p.tubes) * (std::size_t(p.segments) * 12 + 8);
}

// One smooth random curve with segments + 1 points: a random walk on a spherical shell
// whose heading turns a little each step (so it bends smoothly) and whose radius drifts
// smoothly between shell_inner and 1 (times ball_radius).
inline std::vector<Vec3> hairball_curve(const HairballParams& p, SplitMix64& rng) {
    std::vector<Vec3> points;
    Vec3 dir = rng.on_unit_sphere();  // unit position direction
    Vec3 heading = rng.on_unit_sphere();
    double r = rng.uniform(p.shell_inner, 1.0);
    double dr = 0.0;
    for (int i = 0; i <= p.segments; ++i) {
        points.push_back((p.ball_radius * r) * dir);
        // Heading: random turn, then kept tangent to the sphere at dir.
        heading = heading + p.wiggle * rng.in_unit_ball();
        heading = heading - dot(heading, dir) * dir;
        if (length(heading) < 1e-9)
            heading = cross(dir, std::abs(dir.x) < 0.5 ? Vec3{1, 0, 0} : Vec3{0, 1, 0});
        heading = normalize(heading);
        dir = normalize(dir + p.step * heading);
        // Radius: a damped random velocity, reflected at the shell's walls.
        dr = 0.7 * dr + 0.01 * rng.uniform(-1.0, 1.0);
        r += dr;
        if (r > 1.0) {
            r = 2.0 - r;
            dr = -dr;
        }
        if (r < p.shell_inner) {
            r = 2.0 * p.shell_inner - r;
            dr = -dr;
        }
    }
    return points;
}

// Sweeps a hexagon of radius `radius` along `curve` (>= 2 points) with a rotation-minimizing
// frame, and closes both ends with flat caps: a closed, consistently outward-oriented tube.
inline TriMesh sweep_tube(const std::vector<Vec3>& curve, double radius) {
    // Hexagon directions (cos, sin) of k * 60 degrees, exact up to sqrt's rounding.
    const double h = 0.5 * std::sqrt(3.0);
    const std::array<std::array<double, 2>, 6> hex{
        {{1, 0}, {0.5, h}, {-0.5, h}, {-1, 0}, {-0.5, -h}, {0.5, -h}}};
    const std::size_t n = curve.size();
    TriMesh m;
    Vec3 normal{};
    for (std::size_t i = 0; i < n; ++i) {
        const Vec3 t = normalize(curve[std::min(i + 1, n - 1)] - curve[i == 0 ? 0 : i - 1]);
        if (i == 0) {
            // Any unit vector perpendicular to t: cross with the least aligned axis.
            const Vec3 axis = std::abs(t.x) < 0.5 ? Vec3{1, 0, 0} : Vec3{0, 1, 0};
            normal = normalize(cross(t, axis));
        } else {
            // Project the previous normal onto the new normal plane (parallel transport).
            normal = normalize(normal - dot(normal, t) * t);
        }
        const Vec3 binormal = cross(t, normal);
        for (const auto& cs : hex) {
            m.positions.push_back(curve[i] + radius * (cs[0] * normal + cs[1] * binormal));
        }
    }
    // Side quads. Each ring runs counter-clockwise around +t (normal x binormal = t), so
    // (ring i, k) -> (ring i, k+1) -> (ring i+1, k+1) winds around the outward radial.
    for (std::uint32_t i = 0; i + 1 < n; ++i) {
        for (std::uint32_t k = 0; k < 6; ++k) {
            const std::uint32_t a = 6 * i + k, b = 6 * i + (k + 1) % 6;
            const std::uint32_t c = a + 6, d = b + 6;
            m.indices.insert(m.indices.end(), {a, b, d, a, d, c});
        }
    }
    // Caps: the start cap faces -t (clockwise around t), the end cap faces +t.
    const std::uint32_t last = 6 * static_cast<std::uint32_t>(n - 1);
    for (std::uint32_t k = 1; k + 1 < 6; ++k) {
        m.indices.insert(m.indices.end(), {0, k + 1, k});
        m.indices.insert(m.indices.end(), {last, last + k, last + k + 1});
    }
    return m;
}

// The hairball: `tubes` closed hexagonal tubes along random smooth curves inside a ball of
// radius ball_radius centered at the origin. Deterministic in the parameters (and seed).
// Requires tubes >= 1 and segments >= 1.
inline TriMesh make_hairball(const HairballParams& p) {
    SplitMix64 rng(p.seed);
    TriMesh m;
    m.positions.reserve(std::size_t(p.tubes) * std::size_t(p.segments + 1) * 6);
    m.indices.reserve(hairball_triangle_count(p) * 3);
    for (int t = 0; t < p.tubes; ++t) {
        append_mesh(m, sweep_tube(hairball_curve(p, rng), p.tube_radius));
    }
    return m;
}

// ---- OFF reading ------------------------------------------------------------------------

// Reads an ASCII OFF file ("OFF" header, optionally with the counts on the same line;
// '#' comments; per-vertex extra columns and per-face colours ignored). Polygons with more
// than 3 vertices are fan-triangulated, faces with fewer than 3 are skipped.
// Returns false with `error` set (and `out` unspecified) when the file cannot be opened,
// is not OFF, is truncated, or has a non-finite coordinate or an out-of-range index.
inline bool read_off(const std::string& path, TriMesh& out, std::string& error) {
    std::ifstream in(path);
    if (!in) {
        error = "cannot open '" + path + "'";
        return false;
    }
    // Tokens of all non-comment text, line by line (face lines must stay separate).
    std::vector<std::string> lines;
    for (std::string line; std::getline(in, line);) {
        if (const auto hash = line.find('#'); hash != std::string::npos) line.erase(hash);
        if (line.find_first_not_of(" \t\r") != std::string::npos) lines.push_back(line);
    }
    if (lines.empty()) {
        error = "'" + path + "' is empty";
        return false;
    }
    std::istringstream header(lines[0]);
    std::string magic;
    header >> magic;
    if (magic != "OFF") {
        error = "'" + path + "' is not an ASCII OFF file (header '" + magic + "')";
        return false;
    }
    std::size_t next = 1;
    long long nv = -1, nf = -1, ne = 0;
    if (!(header >> nv >> nf >> ne)) {
        if (next >= lines.size()) {
            error = "'" + path + "' has no element counts";
            return false;
        }
        std::istringstream counts(lines[next++]);
        if (!(counts >> nv >> nf)) nv = -1;
    }
    if (nv < 0 || nf < 0 || nv > (1ll << 31) || nf > (1ll << 31)) {
        error = "'" + path + "' has invalid element counts";
        return false;
    }
    if (lines.size() < next + std::size_t(nv) + std::size_t(nf)) {
        error = "'" + path + "' is truncated (expected " + std::to_string(nv) + " vertices and " +
                std::to_string(nf) + " faces)";
        return false;
    }
    out = TriMesh{};
    out.positions.reserve(std::size_t(nv));
    for (long long i = 0; i < nv; ++i) {
        std::istringstream ls(lines[next++]);
        Vec3 p;
        if (!(ls >> p.x >> p.y >> p.z) || !std::isfinite(p.x) || !std::isfinite(p.y) || !std::isfinite(p.z)) {
            error = "'" + path + "': bad vertex " + std::to_string(i);
            return false;
        }
        out.positions.push_back(p);
    }
    for (long long f = 0; f < nf; ++f) {
        std::istringstream ls(lines[next++]);
        long long count = 0;
        if (!(ls >> count) || count < 0 || count > 1'000'000) {
            error = "'" + path + "': bad face " + std::to_string(f);
            return false;
        }
        std::vector<std::uint32_t> poly;
        for (long long k = 0; k < count; ++k) {
            long long idx = -1;
            if (!(ls >> idx) || idx < 0 || idx >= nv) {
                error = "'" + path + "': face " + std::to_string(f) + " has a bad vertex index";
                return false;
            }
            poly.push_back(static_cast<std::uint32_t>(idx));
        }
        for (std::size_t k = 1; k + 1 < poly.size(); ++k) {
            out.indices.insert(out.indices.end(), {poly[0], poly[k], poly[k + 1]});
        }
    }
    return true;
}

// ---- Loop subdivision -------------------------------------------------------------------

// One step of Loop subdivision (Loop 1987) with Warren's simplified weights:
//  - every triangle becomes 4 (corner triangles keep the input's orientation);
//  - a new vertex on an interior edge (exactly 2 incident triangles) (a, b) with opposite
//    vertices c, d is 3/8 (a + b) + 1/8 (c + d); on any other edge (boundary, or
//    non-manifold with 3+ triangles) it is the midpoint;
//  - an old vertex whose edges are all interior, with valence n and neighbours q_j, moves to
//    (1 - n beta) v + beta sum q_j, beta = 3/16 for n = 3, 3 / (8 n) otherwise;
//  - an old vertex on exactly two boundary/non-manifold edges (a smooth boundary curve)
//    moves to 3/4 v + 1/8 (b0 + b1) with b0, b1 its neighbours along those edges;
//  - other vertices (corners, non-manifold junctions, isolated) stay put.
// Output: input vertices first (same order), then one vertex per unique edge in ascending
// (min index, max index) order. Degenerate triangles (repeated index) are subdivided as is.
inline TriMesh loop_subdivide(const TriMesh& in) {
    const std::size_t nv = in.positions.size();
    const std::size_t nt = in.triangle_count();

    // Half-edge records sorted by their undirected edge key -> unique edges.
    struct Corner {
        std::uint32_t lo, hi, opposite, slot;  // slot = 3 * triangle + edge number
    };
    std::vector<Corner> corners;
    corners.reserve(3 * nt);
    for (std::size_t t = 0; t < nt; ++t) {
        for (std::uint32_t k = 0; k < 3; ++k) {
            const std::uint32_t a = in.indices[3 * t + k];
            const std::uint32_t b = in.indices[3 * t + (k + 1) % 3];
            const std::uint32_t c = in.indices[3 * t + (k + 2) % 3];
            corners.push_back({std::min(a, b), std::max(a, b), c, static_cast<std::uint32_t>(3 * t + k)});
        }
    }
    std::sort(corners.begin(), corners.end(), [](const Corner& x, const Corner& y) {
        return std::tie(x.lo, x.hi, x.slot) < std::tie(y.lo, y.hi, y.slot);
    });

    struct Edge {
        std::uint32_t lo, hi;
        std::uint32_t faces = 0;      // incident triangles
        std::uint32_t opposite[2]{};  // the first two opposite vertices
    };
    std::vector<Edge> edges;
    std::vector<std::uint32_t> edge_of_slot(3 * nt);
    for (const Corner& c : corners) {
        if (edges.empty() || edges.back().lo != c.lo || edges.back().hi != c.hi)
            edges.push_back({c.lo, c.hi});
        Edge& e = edges.back();
        if (e.faces < 2) e.opposite[e.faces] = c.opposite;
        ++e.faces;
        edge_of_slot[c.slot] = static_cast<std::uint32_t>(edges.size() - 1);
    }

    // Per-vertex neighbour sums over all edges and over boundary/non-manifold edges.
    std::vector<Vec3> ring_sum(nv), crease_sum(nv);
    std::vector<std::uint32_t> valence(nv, 0), crease_count(nv, 0);
    for (const Edge& e : edges) {
        if (e.lo == e.hi) continue;  // from a degenerate triangle
        const Vec3 a = in.positions[e.lo], b = in.positions[e.hi];
        ring_sum[e.lo] = ring_sum[e.lo] + b;
        ring_sum[e.hi] = ring_sum[e.hi] + a;
        ++valence[e.lo];
        ++valence[e.hi];
        if (e.faces != 2) {
            crease_sum[e.lo] = crease_sum[e.lo] + b;
            crease_sum[e.hi] = crease_sum[e.hi] + a;
            ++crease_count[e.lo];
            ++crease_count[e.hi];
        }
    }

    TriMesh out;
    out.positions.resize(nv + edges.size());
    for (std::size_t v = 0; v < nv; ++v) {
        const Vec3 p = in.positions[v];
        const std::uint32_t n = valence[v];
        if (crease_count[v] == 0 && n >= 3) {
            const double beta = n == 3 ? 3.0 / 16.0 : 3.0 / (8.0 * n);
            out.positions[v] = (1.0 - n * beta) * p + beta * ring_sum[v];
        } else if (crease_count[v] == 2) {
            out.positions[v] = 0.75 * p + 0.125 * crease_sum[v];
        } else {
            out.positions[v] = p;
        }
    }
    for (std::size_t i = 0; i < edges.size(); ++i) {
        const Edge& e = edges[i];
        const Vec3 a = in.positions[e.lo], b = in.positions[e.hi];
        if (e.faces == 2) {
            const Vec3 c = in.positions[e.opposite[0]], d = in.positions[e.opposite[1]];
            out.positions[nv + i] = 0.375 * (a + b) + 0.125 * (c + d);
        } else {
            out.positions[nv + i] = 0.5 * (a + b);
        }
    }

    out.indices.reserve(12 * nt);
    for (std::size_t t = 0; t < nt; ++t) {
        const std::uint32_t a = in.indices[3 * t], b = in.indices[3 * t + 1], c = in.indices[3 * t + 2];
        const auto mid = [&](std::size_t k) {
            return static_cast<std::uint32_t>(nv + edge_of_slot[3 * t + k]);
        };
        const std::uint32_t ab = mid(0), bc = mid(1), ca = mid(2);
        out.indices.insert(out.indices.end(), {a, ab, ca, b, bc, ab, c, ca, bc, ab, bc, ca});
    }
    return out;
}

// Uniformly scales and translates `mesh` so its y extent is `height`, its lowest point is
// at y = 0 and its x/z bounding-box center is at the origin. Requires a non-flat mesh.
inline void fit_on_floor(TriMesh& mesh, double height) {
    const Bounds b = mesh_bounds(mesh);
    const double s = height / (b.max.y - b.min.y);
    const Vec3 center{0.5 * (b.min.x + b.max.x), b.min.y, 0.5 * (b.min.z + b.max.z)};
    for (Vec3& p : mesh.positions) p = s * (p - center);
}

}  // namespace lsnif::examples
