// lsnif::mesh — the one borrowed view of a triangle mesh that the converter's libraries take
// (voxelize, sampling), the one box type, and the one check of a view. The importer
// (converter/scene) owns the arrays; convert builds a MeshView of each scene::Mesh once and
// hands the same view to every stage (docs/architecture.md §2).
#pragma once

#include <array>
#include <cstddef>
#include <cstdint>
#include <span>
#include <string>

namespace lsnif::mesh {

// A triangle mesh, borrowed (not owned; the arrays must outlive every call given the view).
//   positions: x, y, z of each vertex, object space.
//   indices:   3 vertex indices per triangle. Winding does not matter; degenerate
//              triangles are allowed.
//   normals:   x, y, z per vertex, unit shading normals, or empty where a caller does not
//              need them (voxelize); sampling requires them.
//   materials: one material index per triangle, or empty (every triangle material 0).
struct MeshView {
    std::span<const float> positions;
    std::span<const std::uint32_t> indices;
    std::span<const float> normals{};
    std::span<const std::uint32_t> materials{};
    std::size_t vertex_count() const { return positions.size() / 3; }
    std::size_t triangle_count() const { return indices.size() / 3; }
};

// An axis-aligned box in object space, as stored in the model descriptor (FORMAT.md §6.2):
// finite, min[a] < max[a] on every axis (the functions that take one say what they check).
struct Box {
    std::array<float, 3> min{};
    std::array<float, 3> max{};
};

// True iff every float of `v` is finite. Branch-free, so it vectorizes: the scan callers
// run over whole position arrays (or chunks of them, as voxelize's workers do) before
// looking for the first offender.
bool all_finite(std::span<const float> v);

enum class Normals : std::uint8_t { optional, required };

// The first problem of a view, as one line naming the offending vertex, triangle or array,
// or "" when it has none. Checked in this order: positions and indices are multiples of 3;
// every position is finite (referenced or not); every index < vertex count; normals are
// one finite xyz per vertex (or empty, when `normals` is optional); materials are empty or
// one per triangle. An empty mesh passes (callers that need triangles say so). O(size).
std::string check(const MeshView& mesh, Normals normals = Normals::optional);

}  // namespace lsnif::mesh
