// Procedural "hard geometry" for LSNIF (docs/failure-modes.md): shapes on which a
// neural intersection function is known or expected to struggle, so the converter's gate
// can be shown to catch them. Used by lsnif_make_example_scene --hard-case and by the tests.
//
// Same rules as procedural.hpp: deterministic (splitmix64, + - * / sqrt only), header-only,
// standard library only. Every case fits a box of size ~1 centred on the origin (y up)
// before `scale` is applied, so the cases are comparable; scale_mesh() applies the scale.
#pragma once

#include "procedural.hpp"

#include <map>
#include <string>
#include <string_view>
#include <utility>
#include <vector>

namespace lsnif::examples {

// ---- building blocks ---------------------------------------------------------------------

// A regular grid of (nu + 1) x (nv + 1) vertices p(u, v), u, v in [0, 1], as 2 nu nv
// triangles, counter-clockwise when (dp/du x dp/dv) points at the viewer. Open surface.
template <class F>
TriMesh make_grid_surface(int nu, int nv, F&& p) {
    TriMesh m;
    for (int j = 0; j <= nv; ++j)
        for (int i = 0; i <= nu; ++i) m.positions.push_back(p(double(i) / nu, double(j) / nv));
    const auto at = [&](int i, int j) { return std::uint32_t(j * (nu + 1) + i); };
    for (int j = 0; j < nv; ++j)
        for (int i = 0; i < nu; ++i) {
            m.indices.insert(m.indices.end(), {at(i, j), at(i + 1, j), at(i + 1, j + 1)});
            m.indices.insert(m.indices.end(), {at(i, j), at(i + 1, j + 1), at(i, j + 1)});
        }
    return m;
}

// Unit icosphere (closed, outward): the icosahedron midpoint-subdivided `levels`
// times with vertices pushed to the sphere (20 * 4^levels triangles).
inline TriMesh make_icosphere(int levels) {
    const double t = (1.0 + std::sqrt(5.0)) / 2.0;
    TriMesh m;
    for (const Vec3 v :
         {Vec3{-1, t, 0}, Vec3{1, t, 0}, Vec3{-1, -t, 0}, Vec3{1, -t, 0}, Vec3{0, -1, t}, Vec3{0, 1, t},
          Vec3{0, -1, -t}, Vec3{0, 1, -t}, Vec3{t, 0, -1}, Vec3{t, 0, 1}, Vec3{-t, 0, -1}, Vec3{-t, 0, 1}})
        m.positions.push_back(normalize(v));
    m.indices = {0, 11, 5,  0, 5,  1, 0, 1, 7, 0, 7,  10, 0, 10, 11, 1, 5, 9, 5, 11,
                 4, 11, 10, 2, 10, 7, 6, 7, 1, 8, 3,  9,  4, 3,  4,  2, 3, 2, 6, 3,
                 6, 8,  3,  8, 9,  4, 9, 5, 2, 4, 11, 6,  2, 10, 8,  6, 7, 9, 8, 1};
    for (int l = 0; l < levels; ++l) {
        std::vector<std::uint32_t> next;
        std::map<std::pair<std::uint32_t, std::uint32_t>, std::uint32_t> edges;  // (lo, hi) -> mid
        auto mid = [&](std::uint32_t a, std::uint32_t b) {
            const auto [it, added] =
                edges.try_emplace({std::min(a, b), std::max(a, b)}, std::uint32_t(m.positions.size()));
            if (added) m.positions.push_back(normalize(0.5 * (m.positions[a] + m.positions[b])));
            return it->second;
        };
        for (std::size_t f = 0; f < m.indices.size(); f += 3) {
            const std::uint32_t a = m.indices[f], b = m.indices[f + 1], c = m.indices[f + 2];
            const std::uint32_t ab = mid(a, b), bc = mid(b, c), ca = mid(c, a);
            next.insert(next.end(), {a, ab, ca, b, bc, ab, c, ca, bc, ab, bc, ca});
        }
        m.indices = std::move(next);
    }
    return m;
}

inline void transform_mesh(TriMesh& m, Vec3 scale, Vec3 offset) {
    for (Vec3& p : m.positions) p = Vec3{p.x * scale.x, p.y * scale.y, p.z * scale.z} + offset;
}

// Uniform scale about the origin (the cases are centred on it).
inline void scale_mesh(TriMesh& m, double s) {
    transform_mesh(m, {s, s, s}, {0, 0, 0});
}

// A lumpy closed blob: an icosphere whose radius is modulated by a few smooth random
// bumps (sums of x*y*z products, no trigonometry), radius in about [0.35, 0.5].
inline TriMesh make_blob(int levels, std::uint64_t seed) {
    TriMesh m = make_icosphere(levels);
    SplitMix64 rng(seed);
    std::vector<Vec3> centres(7);
    for (Vec3& c : centres) c = rng.on_unit_sphere();
    for (Vec3& p : m.positions) {
        double r = 0.42;
        for (const Vec3& c : centres) {
            const double d = dot(p, c);  // in [-1, 1]
            r += 0.08 * d * d * d * d * d * d * d * d - 0.01;
        }
        p = std::max(0.3, std::min(0.5, r)) * p;
    }
    return m;
}

// ---- the cases ------------------------------------------------------------------------------

// Thin cards like foliage: `cards` quads of 0.08 x 0.03 (2 triangles each, zero thickness:
// foliage is single-layer geometry rendered two-sided), randomly oriented inside a ball of
// radius 0.5.
inline TriMesh make_cards(int cards, std::uint64_t seed) {
    SplitMix64 rng(seed);
    TriMesh m;
    for (int k = 0; k < cards; ++k) {
        const Vec3 c = 0.45 * rng.in_unit_ball();
        const Vec3 u = rng.on_unit_sphere();
        Vec3 v = rng.on_unit_sphere();
        v = v - dot(v, u) * u;
        if (length(v) < 1e-6) v = cross(u, std::abs(u.x) < 0.5 ? Vec3{1, 0, 0} : Vec3{0, 1, 0});
        v = normalize(v);
        const Vec3 a = 0.04 * u, b = 0.015 * v;
        const auto base = std::uint32_t(m.positions.size());
        for (const Vec3 p : {c - a - b, c + a - b, c + a + b, c - a + b}) m.positions.push_back(p);
        m.indices.insert(m.indices.end(), {base, base + 1, base + 2, base, base + 2, base + 3});
    }
    return m;
}

// An open single-sided sheet draped like cloth: a 1 x 1 grid with two crossing folds.
inline TriMesh make_cloth(int n) {
    return make_grid_surface(n, n, [](double u, double v) {
        const double x = u - 0.5, z = v - 0.5;
        // Smooth folds from polynomials (no libm): a ridge along x = z and a sag in the middle.
        const double d = x - z, s = x * x + z * z;
        const double ridge = std::max(0.0, 1.0 - 8.0 * d * d);
        const double y = 0.12 * ridge * ridge - 0.25 * s;
        return Vec3{x, y, z};
    });
}

// A fine lattice: n x n x n cells of thin square struts (boxes) along every grid edge of a
// unit cube, strut width 0.1 / n.
inline TriMesh make_lattice(int n) {
    TriMesh m;
    const double w = 0.05 / n;
    for (int i = 0; i <= n; ++i)
        for (int j = 0; j <= n; ++j) {
            const double a = double(i) / n - 0.5, b = double(j) / n - 0.5;
            append_mesh(m, make_box({-0.5, a - w, b - w}, {0.5, a + w, b + w}));  // along x
            append_mesh(m, make_box({a - w, -0.5, b - w}, {a + w, 0.5, b + w}));  // along y
            append_mesh(m, make_box({a - w, b - w, -0.5}, {a + w, b + w, 0.5}));  // along z
        }
    return m;
}

// A statue-like object standing on a floor: a blob body on a pedestal with two arms, its
// base at y = -0.5. The floor is a separate mesh (make_statue_floor) whose top is y = -0.5,
// so rays leaving the floor start inside the statue's box.
inline TriMesh make_statue() {
    TriMesh m = make_blob(4, 0x57A7E0ull);
    transform_mesh(m, {0.8, 1.2, 0.8}, {0, 0.05, 0});
    append_mesh(m, make_box({-0.3, -0.5, -0.3}, {0.3, -0.38, 0.3}));
    for (const double side : {-1.0, 1.0}) {
        std::vector<Vec3> arm;
        for (int k = 0; k <= 8; ++k) {
            const double t = k / 8.0;
            arm.push_back({side * (0.25 + 0.2 * t), 0.15 + 0.3 * t - 0.25 * t * t, 0.05 * t});
        }
        append_mesh(m, sweep_tube(arm, 0.05));
    }
    return m;
}

inline TriMesh make_statue_floor() {
    return make_box({-3, -0.6, -3}, {3, -0.5, 3});
}

// A very flat closed object: the blob squashed to 1/500 of its width.
inline TriMesh make_flat() {
    TriMesh m = make_blob(4, 0xF1A7ull);
    transform_mesh(m, {1.0, 0.002, 1.0}, {0, 0, 0});
    return m;
}

// One triangle.
inline TriMesh make_single_triangle() {
    TriMesh m;
    m.positions = {{-0.5, -0.3, 0.0}, {0.5, -0.3, 0.0}, {0.0, 0.5, 0.1}};
    m.indices = {0, 1, 2};
    return m;
}

// The hairball of the example scene at unit size.
inline TriMesh make_hard_hairball() {
    return make_hairball(HairballParams{});
}

// The reference object of the scale sweep: a smooth closed blob (20,480 triangles).
inline TriMesh make_scale_reference() {
    return make_blob(5, 0x5CA1Eull);
}

// Case names, as accepted by make_hard_case() and lsnif_make_example_scene --hard-case.
inline std::vector<std::string> hard_case_names() {
    return {"hairball", "cards", "cloth", "lattice", "statue", "flat", "blob", "triangle"};
}

// The named case's main mesh (the one the converter is asked to model), scaled by `scale`;
// `floor` receives the statue's floor (scaled alike) and stays empty for other cases.
// Returns false for an unknown name.
inline bool make_hard_case(std::string_view name, double scale, TriMesh& mesh, TriMesh& floor) {
    floor = {};
    if (name == "hairball")
        mesh = make_hard_hairball();
    else if (name == "cards")
        mesh = make_cards(3000, 0xCA4D5ull);
    else if (name == "cloth")
        mesh = make_cloth(100);
    else if (name == "lattice")
        mesh = make_lattice(12);
    else if (name == "statue") {
        mesh = make_statue();
        floor = make_statue_floor();
        scale_mesh(floor, scale);
    } else if (name == "flat")
        mesh = make_flat();
    else if (name == "blob")
        mesh = make_scale_reference();
    else if (name == "triangle")
        mesh = make_single_triangle();
    else
        return false;
    scale_mesh(mesh, scale);
    return true;
}

}  // namespace lsnif::examples
