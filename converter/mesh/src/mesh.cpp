#include <lsnif/mesh/mesh.hpp>

#include <algorithm>
#include <bit>
#include <cmath>

namespace lsnif::mesh {

namespace {

std::string non_finite(const char* what, std::size_t i, float value) {
    return std::string(what) + " " + std::to_string(i / 3) + ": coordinate " + "xyz"[i % 3] + " is " +
           (std::isnan(value) ? "NaN" : "infinite");
}

}  // namespace

bool all_finite(std::span<const float> v) {
    std::uint32_t nonfinite = 0;
    for (float f : v) nonfinite |= (std::bit_cast<std::uint32_t>(f) & 0x7F800000u) == 0x7F800000u;
    return nonfinite == 0;
}

std::string check(const MeshView& mesh, Normals normals) {
    if (mesh.positions.size() % 3 != 0)
        return "positions: " + std::to_string(mesh.positions.size()) + " floats is not a multiple of 3";
    if (mesh.indices.size() % 3 != 0)
        return "indices: " + std::to_string(mesh.indices.size()) + " indices is not a multiple of 3";
    if (!all_finite(mesh.positions))
        for (std::size_t i = 0; i < mesh.positions.size(); ++i)
            if (!std::isfinite(mesh.positions[i])) return non_finite("vertex", i, mesh.positions[i]);
    const std::size_t nv = mesh.vertex_count();
    const auto largest = std::max_element(mesh.indices.begin(), mesh.indices.end());
    if (largest != mesh.indices.end() && std::uint64_t(*largest) >= nv)
        for (std::size_t i = 0; i < mesh.indices.size(); ++i)
            if (mesh.indices[i] >= nv)
                return "triangle " + std::to_string(i / 3) + ": index " + std::to_string(mesh.indices[i]) +
                       " is out of range (" + std::to_string(nv) + " vertices)";
    if (!mesh.normals.empty() || normals == Normals::required) {
        if (mesh.normals.size() != mesh.positions.size())
            return "normals: " + std::to_string(mesh.normals.size()) +
                   " floats, expected one xyz per vertex (" + std::to_string(mesh.positions.size()) + ")";
        if (!all_finite(mesh.normals))
            for (std::size_t i = 0; i < mesh.normals.size(); ++i)
                if (!std::isfinite(mesh.normals[i])) return non_finite("normal", i, mesh.normals[i]);
    }
    if (!mesh.materials.empty() && mesh.materials.size() != mesh.triangle_count())
        return "materials: " + std::to_string(mesh.materials.size()) +
               " entries, expected none or one per triangle (" + std::to_string(mesh.triangle_count()) + ")";
    return {};
}

}  // namespace lsnif::mesh
