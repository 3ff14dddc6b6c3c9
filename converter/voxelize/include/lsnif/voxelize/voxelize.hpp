// Conservative triangle voxelizer: the occupancy grid of an LSNIF asset (docs/architecture.md §3,
// schema/FORMAT.md §6.3).
//
// A voxel is marked iff some triangle overlaps its *closed* cell (touching a face, an edge
// or a corner counts). The test is the separating-axis theorem for a triangle against an
// axis-aligned box: the 3 box normals, the triangle normal and the 9 cross products
// edge × box axis (T. Akenine-Möller, "Fast 3D Triangle-Box Overlap Testing", Journal of
// Graphics Tools 6(1), 2001). It is evaluated in double precision with a tiny, proven
// outward slack so that rounding can only ever ADD voxels, never drop one:
//
//   * No miss, ever. If a triangle (vertices as given, real arithmetic) intersects the
//     closed cell of voxel (x, y, z), that voxel is marked. This includes touching
//     contacts, slivers and degenerate triangles (segments, points).
//   * False positives are bounded. A voxel is marked only if the triangle comes within
//     2 * tau_T voxel widths of its cell (L-infinity distance, measured per axis in units
//     of that axis' cell size), where
//         tau_T = kSlackFactor * (max(V, M_T) + 1),   kSlackFactor = 2^-40,
//     and M_T is the largest |grid coordinate| of the triangle's vertices (grid coordinate
//     = (p - box_min) / cell, so M_T <= V for a triangle inside the box). For V = 32 and a
//     triangle inside the box, tau_T < 3.1e-11 voxel.
//   The error analysis behind both statements is at the top of src/voxelize.cpp; the tests
//   check them against CGAL's exact predicates (tests/voxelize).
//
// Cost: a triangle whose grown AABB lies in one voxel, or in two neighbours along one axis,
// takes a branch-light O(1) path (the common case when triangles are small against voxels);
// otherwise every cell of its AABB gets the SAT (3 axes when the triangle stays within one
// voxel slab, else up to 13; rows are pre-clipped by the normal's plane). Triangles are
// processed by the shared thread pool into private grids that are OR-ed at the end, so the
// output does not depend on the thread count.
//
// Library code never throws or exits: every function returns Result/Error (allocation
// failure included).
#pragma once

#include <lsnif/base/result.hpp>
#include <lsnif/mesh/mesh.hpp>

#include <array>
#include <cstddef>
#include <cstdint>
#include <span>
#include <string>
#include <utility>
#include <variant>
#include <vector>

namespace lsnif::voxelize {

inline constexpr std::uint32_t kMinResolution = 1;
inline constexpr std::uint32_t kMaxResolution = 256;

// Relative outward slack of the overlap test (see the header comment for the bound it gives).
inline constexpr double kSlackFactor = 0x1p-40;

struct Error {
    std::string message;  // one line, names the offending vertex/triangle/field
};

template <class T>
using Result = base::Result<T, Error>;

// The converter's one mesh view and box (lsnif/mesh/mesh.hpp). Voxelization reads positions
// and indices only; winding and orientation do not matter; degenerate triangles are
// allowed. A Box, as stored in the descriptor (FORMAT.md §6.1): finite, min[a] < max[a].
using MeshView = mesh::MeshView;
using Box = mesh::Box;

// Options of padded_box(). Both are fractions of L, the largest extent of the mesh's AABB.
struct BoxOptions {
    // Added on each side of every axis. Default 1/64: at V = 32 that is about half a voxel,
    // so no surface lies on the outer face of the grid. Must be finite and in [0, 1].
    double padding = 1.0 / 64;
    // Minimum extent of every axis of the returned box; an axis thinner than this (a flat
    // mesh) is widened symmetrically around its centre. Must be finite and in (0, 1].
    double min_thickness = 1.0 / 16;
};

// docs/architecture.md §3 "Box": the AABB of the vertices referenced by the triangles, padded by
// options.padding * L on each side, every axis at least options.min_thickness * L thick.
// If L = 0 (every triangle collapses to one point p) L is taken as max(|p|_inf, 1) * 2^-10.
// The result is rounded outward to float, so it strictly contains the AABB on every axis
// (min < aabb_min and aabb_max < max). Errors: no triangles, a non-finite position, an
// index out of range, bad options, a box that overflows float.
Result<Box> padded_box(const MeshView& mesh, const BoxOptions& options = {});

// The occupancy grid in the exact layout of the OCCU section (FORMAT.md §6.3): voxel
// (x, y, z), 0 <= x, y, z < V, has index i = x + V * (y + V * z); its bit is bit (i & 7)
// of bits[i >> 3]; bits has ceil(V^3 / 8) bytes and the unused high bits of the last
// byte are 0.
struct Occupancy {
    std::uint32_t resolution = 0;  // V
    std::vector<std::uint8_t> bits;

    static std::size_t byte_count(std::uint32_t v) { return (std::size_t(v) * v * v + 7) / 8; }
    static std::size_t index(std::uint32_t v, std::uint32_t x, std::uint32_t y, std::uint32_t z) {
        return x + std::size_t(v) * (y + std::size_t(v) * z);
    }
    // Precondition: x, y, z < resolution.
    bool occupied(std::uint32_t x, std::uint32_t y, std::uint32_t z) const {
        const std::size_t i = index(resolution, x, y, z);
        return (bits[i >> 3] >> (i & 7)) & 1u;
    }
    std::size_t count() const;  // number of occupied voxels
};

struct Options {
    // Worker threads; 0 = std::thread::hardware_concurrency(). Small meshes use fewer.
    // The result does not depend on the thread count (bits are OR-ed, order-free).
    unsigned threads = 0;
};

// Voxelizes `mesh` into the V×V×V grid spanning `box`, V = resolution in [1, 256].
// Voxel (x, y, z) is the closed cell box.min + [x, x+1] * cell (per axis, likewise y, z),
// cell = (box.max - box.min) / V, all in real arithmetic on the given float values.
// Triangles (partly) outside the box mark only the voxels they overlap; triangles wholly
// outside mark nothing. Guarantees: see the header comment (no misses; false positives
// only within 2 * tau_T).
// Errors (nothing is marked): V out of range; a non-finite or empty box (min >= max on
// some axis); positions or indices not a multiple of 3; a non-finite position (any vertex,
// referenced or not); an index >= vertex count.
Result<Occupancy> voxelize(const MeshView& mesh, const Box& box, std::uint32_t resolution,
                           const Options& options = {});

}  // namespace lsnif::voxelize
