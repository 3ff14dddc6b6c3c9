// Test helpers for lsnif::sampling: an OFF reader, an icosphere generator, area-weighted
// vertex normals (MeshView requires normals), the padded model box, and brute-force references
// (Möller–Trumbore 1997 ray/triangle test over all triangles, in double; ray-parity inside test on top of
// it).
#pragma once

#include <lsnif/sampling/sampling.hpp>

#include <algorithm>
#include <array>
#include <cmath>
#include <cstdint>
#include <fstream>
#include <map>
#include <optional>
#include <sstream>
#include <string>
#include <utility>
#include <vector>

namespace lsnif::sampling::testing {

struct TriMesh {
    std::vector<float> positions;        // xyz per vertex
    std::vector<std::uint32_t> indices;  // 3 per triangle
    std::vector<float> normals;          // xyz per vertex (MeshView requires them)
    std::size_t vertex_count() const { return positions.size() / 3; }
    std::size_t triangle_count() const { return indices.size() / 3; }
    MeshView view() const { return MeshView{positions, indices, normals, {}}; }
};

// Area-weighted vertex normals, as the converter's importer computes them for meshes
// without normals (scene::compute_vertex_normals: the normalized sum of the incident
// faces' (p1 - p0) x (p2 - p0), in double), except that a vertex with no direction gets
// zero rather than +z (sampling then uses the faceted normal). For meshes that have none.
inline void compute_normals(TriMesh& m) {
    std::vector<double> sum(m.positions.size(), 0.0);
    for (std::size_t t = 0; t < m.triangle_count(); ++t) {
        const std::uint32_t* v = &m.indices[3 * t];
        double p[3][3];
        for (int j = 0; j < 3; ++j)
            for (int a = 0; a < 3; ++a) p[j][a] = m.positions[3 * std::size_t(v[j]) + std::size_t(a)];
        const double e1[3] = {p[1][0] - p[0][0], p[1][1] - p[0][1], p[1][2] - p[0][2]};
        const double e2[3] = {p[2][0] - p[0][0], p[2][1] - p[0][1], p[2][2] - p[0][2]};
        const double c[3] = {e1[1] * e2[2] - e1[2] * e2[1], e1[2] * e2[0] - e1[0] * e2[2],
                             e1[0] * e2[1] - e1[1] * e2[0]};  // |c| = 2 x area: area weighting
        for (int j = 0; j < 3; ++j)
            for (int a = 0; a < 3; ++a) sum[3 * std::size_t(v[j]) + std::size_t(a)] += c[a];
    }
    m.normals.assign(m.positions.size(), 0.0f);
    for (std::size_t i = 0; i < m.vertex_count(); ++i) {
        const double* s = &sum[3 * i];
        const double len = std::sqrt(s[0] * s[0] + s[1] * s[1] + s[2] * s[2]);
        if (len > 0)
            for (std::size_t a = 0; a < 3; ++a) m.normals[3 * i + a] = float(s[a] / len);
    }
}

// OFF: optional "OFF" keyword (alone or followed by the counts), "nv nf ne", nv lines
// "x y z ...", nf lines "n i0 .. i(n-1) [colour]"; '#' starts a comment. Polygons become
// triangle fans around their first vertex; vertex normals are computed (compute_normals).
// Returns nullopt and sets `error` if malformed.
inline std::optional<TriMesh> read_off(const std::string& path, std::string& error) {
    std::ifstream in(path);
    if (!in) {
        error = path + ": cannot open";
        return std::nullopt;
    }
    std::vector<std::string> tokens;      // all tokens, comments removed
    std::vector<std::size_t> line_start;  // token index where each non-empty line starts
    for (std::string line; std::getline(in, line);) {
        if (auto h = line.find('#'); h != std::string::npos) line.resize(h);
        std::istringstream ls(line);
        const std::size_t before = tokens.size();
        for (std::string t; ls >> t;) tokens.push_back(t);
        if (tokens.size() > before) line_start.push_back(before);
    }
    line_start.push_back(tokens.size());
    std::size_t line = 0, tok = 0;
    auto fail = [&](const std::string& why) {
        error = path + ": " + why;
        return std::nullopt;
    };
    if (tokens.empty()) return fail("empty file");
    if (tokens[0] == "OFF") {
        tok = 1;
        if (line_start[1] == 1) ++line;  // keyword alone on its line
    }
    try {
        // Counts: the rest of the current line.
        if (line + 1 >= line_start.size()) return fail("no counts");
        const std::size_t end = line_start[line + 1];
        if (end - tok < 2) return fail("bad counts line");
        const std::size_t nv = std::stoul(tokens[tok]), nf = std::stoul(tokens[tok + 1]);
        ++line;
        TriMesh mesh;
        mesh.positions.reserve(3 * nv);
        for (std::size_t i = 0; i < nv; ++i, ++line) {
            if (line + 1 >= line_start.size()) return fail("truncated vertex list");
            const std::size_t b = line_start[line], e = line_start[line + 1];
            if (e - b < 3) return fail("vertex with fewer than 3 coordinates");
            for (std::size_t a = 0; a < 3; ++a) mesh.positions.push_back(std::stof(tokens[b + a]));
        }
        for (std::size_t f = 0; f < nf; ++f, ++line) {
            if (line + 1 >= line_start.size()) return fail("truncated face list");
            const std::size_t b = line_start[line], e = line_start[line + 1];
            const std::size_t n = std::stoul(tokens[b]);
            if (n < 3 || e - b < n + 1) return fail("bad face line");
            std::vector<std::uint32_t> poly(n);
            for (std::size_t k = 0; k < n; ++k) {
                const unsigned long idx = std::stoul(tokens[b + 1 + k]);
                if (idx >= nv) return fail("face index out of range");
                poly[k] = std::uint32_t(idx);
            }
            for (std::size_t k = 1; k + 1 < n; ++k)
                mesh.indices.insert(mesh.indices.end(), {poly[0], poly[k], poly[k + 1]});
        }
        compute_normals(mesh);
        return mesh;
    } catch (const std::exception& e) {
        return fail(std::string("parse error: ") + e.what());
    }
}

// Icosahedron subdivided `levels` times (1-to-4, shared midpoints) and projected onto the
// sphere (center, radius); closed and edge-manifold; analytic unit normals per vertex.
// Faces are counter-clockwise seen from outside (geometric normals point outward).
inline TriMesh icosphere(int levels, std::array<double, 3> c, double r) {
    const double t = (1.0 + std::sqrt(5.0)) / 2.0;
    std::vector<std::array<double, 3>> v = {{-1, t, 0}, {1, t, 0}, {-1, -t, 0}, {1, -t, 0},
                                            {0, -1, t}, {0, 1, t}, {0, -1, -t}, {0, 1, -t},
                                            {t, 0, -1}, {t, 0, 1}, {-t, 0, -1}, {-t, 0, 1}};
    std::vector<std::array<std::uint32_t, 3>> f = {
        {0, 11, 5},  {0, 5, 1},  {0, 1, 7},  {0, 7, 10}, {0, 10, 11}, {1, 5, 9}, {5, 11, 4},
        {11, 10, 2}, {10, 7, 6}, {7, 1, 8},  {3, 9, 4},  {3, 4, 2},   {3, 2, 6}, {3, 6, 8},
        {3, 8, 9},   {4, 9, 5},  {2, 4, 11}, {6, 2, 10}, {8, 6, 7},   {9, 8, 1}};
    auto unit = [](std::array<double, 3> p) {
        const double l = std::sqrt(p[0] * p[0] + p[1] * p[1] + p[2] * p[2]);
        return std::array<double, 3>{p[0] / l, p[1] / l, p[2] / l};
    };
    for (auto& p : v) p = unit(p);
    for (int l = 0; l < levels; ++l) {
        std::map<std::pair<std::uint32_t, std::uint32_t>, std::uint32_t> mid;
        auto m = [&](std::uint32_t a, std::uint32_t b) {
            const auto key = std::minmax(a, b);
            auto it = mid.find(key);
            if (it != mid.end()) return it->second;
            v.push_back(unit({v[a][0] + v[b][0], v[a][1] + v[b][1], v[a][2] + v[b][2]}));
            return mid[key] = std::uint32_t(v.size() - 1);
        };
        std::vector<std::array<std::uint32_t, 3>> nf;
        for (auto [a, b, cc] : f) {
            const std::uint32_t ab = m(a, b), bc = m(b, cc), ca = m(cc, a);
            nf.push_back({a, ab, ca});
            nf.push_back({ab, b, bc});
            nf.push_back({ca, bc, cc});
            nf.push_back({ab, bc, ca});
        }
        f = std::move(nf);
    }
    TriMesh mesh;
    for (auto& p : v)
        for (int a = 0; a < 3; ++a) {
            mesh.positions.push_back(float(c[std::size_t(a)] + r * p[std::size_t(a)]));
            mesh.normals.push_back(float(p[std::size_t(a)]));
        }
    for (auto& tri : f) mesh.indices.insert(mesh.indices.end(), tri.begin(), tri.end());
    return mesh;
}

// 1-to-4 midpoint subdivision (shared midpoints, so a closed mesh stays closed; the
// surface is unchanged, only finer). Normals are recomputed (compute_normals).
inline TriMesh subdivide(const TriMesh& in) {
    TriMesh out;
    out.positions = in.positions;
    std::map<std::pair<std::uint32_t, std::uint32_t>, std::uint32_t> mid;
    auto m = [&](std::uint32_t a, std::uint32_t b) {
        const auto key = std::minmax(a, b);
        if (auto it = mid.find(key); it != mid.end()) return it->second;
        for (int k = 0; k < 3; ++k)
            out.positions.push_back(0.5f * (in.positions[3 * std::size_t(a) + std::size_t(k)] +
                                            in.positions[3 * std::size_t(b) + std::size_t(k)]));
        return mid[key] = std::uint32_t(out.positions.size() / 3 - 1);
    };
    for (std::size_t t = 0; t < in.triangle_count(); ++t) {
        const std::uint32_t a = in.indices[3 * t], b = in.indices[3 * t + 1], c = in.indices[3 * t + 2];
        const std::uint32_t ab = m(a, b), bc = m(b, c), ca = m(c, a);
        out.indices.insert(out.indices.end(), {a, ab, ca, ab, b, bc, ca, bc, c, ab, bc, ca});
    }
    compute_normals(out);
    return out;
}

// The model box of docs/architecture.md §3: the AABB padded by 1 % of the largest extent per side.
inline Box padded_box(const TriMesh& m) {
    Box b;
    b.min = {INFINITY, INFINITY, INFINITY};
    b.max = {-INFINITY, -INFINITY, -INFINITY};
    for (std::size_t i = 0; i < m.positions.size(); ++i) {
        b.min[i % 3] = std::min(b.min[i % 3], m.positions[i]);
        b.max[i % 3] = std::max(b.max[i % 3], m.positions[i]);
    }
    float ext = 0;
    for (int a = 0; a < 3; ++a) ext = std::max(ext, b.max[std::size_t(a)] - b.min[std::size_t(a)]);
    for (int a = 0; a < 3; ++a) {
        b.min[std::size_t(a)] -= 0.01f * ext;
        b.max[std::size_t(a)] += 0.01f * ext;
    }
    return b;
}

struct RefHit {
    bool hit = false;
    double t = 0, u = 0, v = 0;
    std::uint32_t prim = kNoPrimitive;
};

// Möller & Trumbore 1997, in double, closest hit over all triangles with t in
// [tmin, tmax * tmax_scale]. `bary_eps` grows (> 0) or shrinks (< 0) every triangle in
// barycentric space, to tell grazing rays from real disagreements.
inline RefHit brute_force(const TriMesh& m, const format::Ray& r, double bary_eps = 0,
                          double tmax_scale = 1) {
    RefHit best;
    const double o[3] = {r.org[0], r.org[1], r.org[2]}, d[3] = {r.dir[0], r.dir[1], r.dir[2]};
    const double tmax = std::isinf(r.tmax) ? INFINITY : double(r.tmax) * tmax_scale;
    double best_t = tmax;
    for (std::size_t k = 0; k < m.triangle_count(); ++k) {
        const float* p0 = &m.positions[3 * std::size_t(m.indices[3 * k])];
        const float* p1 = &m.positions[3 * std::size_t(m.indices[3 * k + 1])];
        const float* p2 = &m.positions[3 * std::size_t(m.indices[3 * k + 2])];
        const double e1[3] = {double(p1[0]) - p0[0], double(p1[1]) - p0[1], double(p1[2]) - p0[2]};
        const double e2[3] = {double(p2[0]) - p0[0], double(p2[1]) - p0[1], double(p2[2]) - p0[2]};
        const double pv[3] = {d[1] * e2[2] - d[2] * e2[1], d[2] * e2[0] - d[0] * e2[2],
                              d[0] * e2[1] - d[1] * e2[0]};
        const double det = e1[0] * pv[0] + e1[1] * pv[1] + e1[2] * pv[2];
        if (det == 0) continue;
        const double inv = 1.0 / det;
        const double tv[3] = {o[0] - p0[0], o[1] - p0[1], o[2] - p0[2]};
        const double u = (tv[0] * pv[0] + tv[1] * pv[1] + tv[2] * pv[2]) * inv;
        if (u < -bary_eps || u > 1 + bary_eps) continue;
        const double qv[3] = {tv[1] * e1[2] - tv[2] * e1[1], tv[2] * e1[0] - tv[0] * e1[2],
                              tv[0] * e1[1] - tv[1] * e1[0]};
        const double v = (d[0] * qv[0] + d[1] * qv[1] + d[2] * qv[2]) * inv;
        if (v < -bary_eps || u + v > 1 + bary_eps) continue;
        const double t = (e2[0] * qv[0] + e2[1] * qv[1] + e2[2] * qv[2]) * inv;
        if (t < r.tmin || t > best_t) continue;
        best_t = t;
        best = {true, t, u, v, std::uint32_t(k)};
    }
    return best;
}

// Crossings of the ray o + t d (t > 0) with the mesh, in double (Möller–Trumbore).
inline std::size_t crossings(const TriMesh& m, const std::array<double, 3>& o,
                             const std::array<double, 3>& d) {
    std::size_t n = 0;
    for (std::size_t k = 0; k < m.triangle_count(); ++k) {
        const float* p0 = &m.positions[3 * std::size_t(m.indices[3 * k])];
        const float* p1 = &m.positions[3 * std::size_t(m.indices[3 * k + 1])];
        const float* p2 = &m.positions[3 * std::size_t(m.indices[3 * k + 2])];
        const double e1[3] = {double(p1[0]) - p0[0], double(p1[1]) - p0[1], double(p1[2]) - p0[2]};
        const double e2[3] = {double(p2[0]) - p0[0], double(p2[1]) - p0[1], double(p2[2]) - p0[2]};
        const double pv[3] = {d[1] * e2[2] - d[2] * e2[1], d[2] * e2[0] - d[0] * e2[2],
                              d[0] * e2[1] - d[1] * e2[0]};
        const double det = e1[0] * pv[0] + e1[1] * pv[1] + e1[2] * pv[2];
        if (det == 0) continue;
        const double inv = 1.0 / det;
        const double tv[3] = {o[0] - p0[0], o[1] - p0[1], o[2] - p0[2]};
        const double u = (tv[0] * pv[0] + tv[1] * pv[1] + tv[2] * pv[2]) * inv;
        if (u < 0 || u > 1) continue;
        const double qv[3] = {tv[1] * e1[2] - tv[2] * e1[1], tv[2] * e1[0] - tv[0] * e1[2],
                              tv[0] * e1[1] - tv[1] * e1[0]};
        const double v = (d[0] * qv[0] + d[1] * qv[1] + d[2] * qv[2]) * inv;
        if (v < 0 || u + v > 1) continue;
        const double t = (e2[0] * qv[0] + e2[1] * qv[1] + e2[2] * qv[2]) * inv;
        if (t > 0) ++n;
    }
    return n;
}

// Reference inside test: majority of parity over three fixed, generic directions.
inline bool brute_inside(const TriMesh& m, const std::array<double, 3>& o) {
    static const std::array<std::array<double, 3>, 3> dirs = {
        std::array<double, 3>{0.5773502691896258, 0.6123724356957945, 0.5400617248673217},
        std::array<double, 3>{-0.7071067811865476, 0.3162277660168379, 0.6324555320336759},
        std::array<double, 3>{0.2672612419124244, -0.8017837257372732, 0.5345224838248488}};
    int votes = 0;
    for (const auto& d : dirs) votes += int(crossings(m, o, d) & 1);
    return votes >= 2;
}

}  // namespace lsnif::sampling::testing
