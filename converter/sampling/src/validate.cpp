// The one check of EmbreeSource::create()'s input. Everything the later construction
// stages assume about the caller's mesh, box and configuration (sizes, finiteness, ranges,
// a positive area) is decided here, in one function (the mesh rules themselves are
// mesh::check's, shared with voxelize), so that no stage re-checks or
// half-checks its input and the error a caller gets does not depend on which stage first
// noticed the problem. The messages are the library's public error texts (tests match
// words of them), so their wording and order are part of the contract.
#include "sampling_internal.hpp"

namespace lsnif::sampling {

namespace {

// Sum of the triangle areas in double, in triangle order (the same sum, bit for bit, as
// compute_face_geometry() forms for the alias table). Indices must be in range.
double total_area(const MeshView& mesh) {
    auto vertex = [&](std::uint32_t v) {
        const float* p = &mesh.positions[3 * std::size_t(v)];
        return V3{p[0], p[1], p[2]};
    };
    double total = 0;
    for (std::size_t t = 0; t < mesh.indices.size() / 3; ++t) {
        const std::uint32_t* v = &mesh.indices[3 * t];
        total += 0.5 * length(cross(vertex(v[1]) - vertex(v[0]), vertex(v[2]) - vertex(v[0])));
    }
    return total;
}

std::string validate_config(const SamplingConfig& cfg) {
    if (!(cfg.shadow_fraction >= 0.0f && cfg.shadow_fraction <= 1.0f))
        return "shadow_fraction outside [0, 1]";
    if (!(cfg.offset_diagonal >= 0.0f) || !(cfg.offset_relative >= 0.0f) ||
        !std::isfinite(cfg.offset_diagonal) || !std::isfinite(cfg.offset_relative))
        return "offsets must be finite and >= 0";
    if (cfg.classify_resolution > 1024) return "classify_resolution above 1024";
    if (!(cfg.max_hole_size >= 0.0f) || !std::isfinite(cfg.max_hole_size))
        return "max_hole_size must be finite and >= 0";
    return {};
}

}  // namespace

std::string validate_input(const MeshView& mesh, const Box& box, const SamplingConfig& cfg) {
    if (mesh.positions.empty() || mesh.indices.empty()) return "empty mesh (no vertices or no triangles)";
    if (std::string why = mesh::check(mesh, mesh::Normals::required); !why.empty()) return why;
    const std::size_t nv = mesh.positions.size() / 3, nt = mesh.indices.size() / 3;
    if (nv >= 0x80000000u || nt >= 0x80000000u) return "mesh too large (2^31 vertices or triangles)";
    if (std::string why = validate_config(cfg); !why.empty()) return why;
    for (int a = 0; a < 3; ++a) {
        if (!std::isfinite(box.min[std::size_t(a)]) || !std::isfinite(box.max[std::size_t(a)]))
            return "box is not finite";
        if (!(box.min[std::size_t(a)] < box.max[std::size_t(a)]))
            return "box min must be below max on every axis";
    }
    for (std::size_t i = 0; i < mesh.positions.size(); ++i) {
        const float p = mesh.positions[i];
        if (p < box.min[i % 3] || p > box.max[i % 3])
            return "vertex " + std::to_string(i / 3) + " lies outside the box";
    }
    const double area = total_area(mesh);
    if (!(area > 0) || !std::isfinite(area)) return "mesh has zero total area";
    return {};
}

}  // namespace lsnif::sampling
