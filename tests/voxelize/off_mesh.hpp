// Minimal OFF reader and 1-to-4 midpoint subdivision for the voxelizer's tests and
// benchmark. OFF: optional "OFF" keyword line, then "nv nf ne", nv lines "x y z [...]",
// nf lines "n i0 ... i(n-1) [colour]"; '#' starts a comment. Polygons are triangulated
// as fans around their first vertex.
#pragma once

#include <cstdint>
#include <fstream>
#include <optional>
#include <sstream>
#include <stdexcept>
#include <string>
#include <unordered_map>
#include <utility>
#include <vector>

namespace lsnif::voxelize::testing {

struct TriMesh {
    std::vector<float> positions;        // xyz per vertex
    std::vector<std::uint32_t> indices;  // 3 per triangle
    std::size_t vertex_count() const { return positions.size() / 3; }
    std::size_t triangle_count() const { return indices.size() / 3; }
};

// Returns std::nullopt (and sets `error`) on a malformed file.
inline std::optional<TriMesh> read_off(const std::string& path, std::string& error) {
    std::ifstream in(path);
    if (!in) {
        error = path + ": cannot open";
        return std::nullopt;
    }
    // Non-empty lines, comments stripped, split into tokens.
    std::vector<std::vector<std::string>> lines;
    std::string text;
    while (std::getline(in, text)) {
        if (auto hash = text.find('#'); hash != std::string::npos) text.resize(hash);
        std::istringstream ls(text);
        std::vector<std::string> tokens;
        for (std::string tok; ls >> tok;) tokens.push_back(tok);
        if (!tokens.empty()) lines.push_back(std::move(tokens));
    }
    std::size_t line_no = 0;
    // "OFF" alone on its line, or followed by the counts on the same line.
    if (!lines.empty() && lines[0][0] == "OFF") {
        lines[0].erase(lines[0].begin());
        if (lines[0].empty()) ++line_no;
    }
    auto line_tokens = [&](std::size_t l) { return lines[l]; };
    try {
        if (line_no >= lines.size()) throw std::runtime_error("no counts line");
        auto counts = line_tokens(line_no++);
        if (counts.size() < 2) throw std::runtime_error("bad counts line");
        const std::size_t nv = std::stoul(counts[0]), nf = std::stoul(counts[1]);
        TriMesh mesh;
        mesh.positions.reserve(3 * nv);
        for (std::size_t i = 0; i < nv; ++i) {
            if (line_no >= lines.size()) throw std::runtime_error("truncated vertices");
            auto t = line_tokens(line_no++);
            if (t.size() < 3) throw std::runtime_error("vertex with fewer than 3 coordinates");
            for (int a = 0; a < 3; ++a) mesh.positions.push_back(std::stof(t[std::size_t(a)]));
        }
        for (std::size_t f = 0; f < nf; ++f) {
            if (line_no >= lines.size()) throw std::runtime_error("truncated faces");
            auto t = line_tokens(line_no++);
            const std::size_t n = std::stoul(t.at(0));
            if (n < 3 || t.size() < n + 1) throw std::runtime_error("bad face");
            std::vector<std::uint32_t> poly(n);
            for (std::size_t k = 0; k < n; ++k) {
                const unsigned long idx = std::stoul(t[k + 1]);
                if (idx >= nv) throw std::runtime_error("face index out of range");
                poly[k] = std::uint32_t(idx);
            }
            for (std::size_t k = 1; k + 1 < n; ++k) {
                mesh.indices.insert(mesh.indices.end(), {poly[0], poly[k], poly[k + 1]});
            }
        }
        return mesh;
    } catch (const std::exception& e) {
        error = path + ": " + e.what();
        return std::nullopt;
    }
}

// 1-to-4 midpoint subdivision: every triangle (a, b, c) becomes (a, ab, ca), (ab, b, bc),
// (ca, bc, c), (ab, bc, ca); each edge midpoint is created once and shared, so a closed
// mesh stays closed. Midpoints are computed in float as 0.5f * (p + q).
inline TriMesh subdivide(const TriMesh& in) {
    TriMesh out;
    out.positions = in.positions;
    out.indices.reserve(in.indices.size() * 4);
    std::unordered_map<std::uint64_t, std::uint32_t> midpoints;
    midpoints.reserve(in.indices.size());
    auto midpoint = [&](std::uint32_t i, std::uint32_t j) {
        const std::uint64_t key = i < j ? (std::uint64_t(i) << 32 | j) : (std::uint64_t(j) << 32 | i);
        auto [it, inserted] = midpoints.try_emplace(key, std::uint32_t(out.positions.size() / 3));
        if (inserted) {
            for (int a = 0; a < 3; ++a)
                out.positions.push_back(0.5f * (in.positions[3 * std::size_t(i) + std::size_t(a)] +
                                                in.positions[3 * std::size_t(j) + std::size_t(a)]));
        }
        return it->second;
    };
    for (std::size_t t = 0; t < in.triangle_count(); ++t) {
        const std::uint32_t a = in.indices[3 * t], b = in.indices[3 * t + 1], c = in.indices[3 * t + 2];
        const std::uint32_t ab = midpoint(a, b), bc = midpoint(b, c), ca = midpoint(c, a);
        out.indices.insert(out.indices.end(), {a, ab, ca, ab, b, bc, ca, bc, c, ab, bc, ca});
    }
    return out;
}

}  // namespace lsnif::voxelize::testing
