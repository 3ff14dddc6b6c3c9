// Scene import for `lsnif convert` (docs/architecture.md §1, first stage): glTF 2.0 (.gltf, .glb)
// through tinygltf, OBJ / PLY / STL through OpenMesh and OFF through a reader of our own,
// into one in-memory model of unique meshes, their instances and material names.
//
// Contract of the whole module:
//   * Library code never throws, aborts or exits. Every import returns an ImportResult;
//     on failure `error` is one line "<file>: <what is wrong>" naming the offending
//     element (node, mesh, primitive, accessor, face, vertex) and, for glTF, the section
//     of the glTF 2.0 specification that the file violates. Allocation failure and
//     exceptions thrown inside tinygltf/OpenMesh are caught and reported the same way.
//   * A successful import satisfies check_scene() (below): sizes consistent, every index
//     in range, all positions and transforms finite, every normal unit length, at least
//     one instance and one triangle.
//   * Nothing is silently dropped: whatever is skipped (points, lines, faces with fewer
//     than three corners, primitives without positions, unsupported features that do not
//     change geometry) is reported in Scene::warnings, one line each, without the file name.
//   * Units are those of the source: glTF 2.0 uses metres, a right-handed frame with +Y up
//     (glTF 2.0 "Coordinate System and Units"); OBJ/PLY/OFF/STL carry no units.
//     Nothing is rescaled or re-oriented.
//   * Everything is owned by value (std::vector / std::string); a Scene has no pointers
//     into the source file or library state and may be moved freely.
#pragma once

#include <array>
#include <cstddef>
#include <cstdint>
#include <filesystem>
#include <span>
#include <string>
#include <string_view>
#include <vector>

namespace lsnif::scene {

// Affine transform as a 3x4 row-major matrix [A | b]: element (r, c) is m[4 * r + c], and
// a point maps as x_world = A * x_object + b (b = m[3], m[7], m[11]). All 12 values are
// finite. A may have a negative determinant (a mirroring instance); triangles keep their
// object-space order, and by glTF 2.0 "Instantiation" a negative determinant makes the
// world-space winding clockwise, so front faces stay front faces.
using Transform = std::array<float, 12>;

inline constexpr Transform kIdentityTransform = {1.0f, 0.0f, 0.0f, 0.0f,  //
                                                 0.0f, 1.0f, 0.0f, 0.0f,  //
                                                 0.0f, 0.0f, 1.0f, 0.0f};

// Where a mesh's shading normals came from.
enum class NormalOrigin : std::uint8_t {
    source,    // every vertex normal was read from the file (and normalized)
    computed,  // every vertex normal was computed (compute_vertex_normals)
    mixed,     // some primitives/vertices had usable normals in the file, others did not
};

// One unique piece of triangle geometry in object space. A glTF mesh is one Mesh however
// many nodes instance it, and all its triangle primitives are merged into it (their
// vertex arrays appended; primitives that share the same POSITION/NORMAL accessors share
// their vertices). A mesh file (OBJ/PLY/OFF/STL) is one Mesh.
struct Mesh {
    std::string name;  // glTF mesh name, "mesh_<index>" if it has none; file stem for mesh files
    // glTF: the mesh's index in the file's `meshes` (meshes without triangles or instances
    // are dropped, so it can differ from the index in Scene::meshes); -1 for mesh files.
    std::int32_t source_index = -1;

    // x, y, z per vertex (3 floats per vertex), object space, source units, all finite.
    std::vector<float> positions;

    // 3 vertex indices per triangle, each < vertex_count(). Counter-clockwise is the front
    // face (glTF 2.0 "Meshes"; the usual convention of the other formats). Triangle
    // strips and fans are already converted to lists. Degenerate triangles of the source
    // are kept, except those of strips/fans that repeat an index (stitching artefacts).
    std::vector<std::uint32_t> indices;

    // Shading normal per vertex (3 floats per vertex), unit length (|n| = 1 within 1e-5),
    // object space. From the file where it has them; otherwise computed as documented at
    // compute_vertex_normals(). (The glTF 2.0 spec, "Meshes", asks for flat normals when
    // a primitive has none; we compute smooth ones on purpose: the network learns shading
    // normals, and smooth ones are what a renderer would interpolate — docs/architecture.md §3.)
    std::vector<float> normals;
    NormalOrigin normal_origin = NormalOrigin::computed;

    // Material of each triangle (1 per triangle): an index into Scene::materials. 0 is the
    // default material (glTF 2.0 "Default Material"; the only one for mesh files).
    std::vector<std::uint32_t> triangle_materials;

    std::size_t vertex_count() const noexcept { return positions.size() / 3; }
    std::size_t triangle_count() const noexcept { return indices.size() / 3; }
};

// One placement of a Mesh in the world.
struct Instance {
    std::uint32_t mesh = 0;  // index into Scene::meshes
    std::string node_name;   // glTF node name, "node_<index>" if it has none; file stem for mesh files
    Transform transform = kIdentityTransform;  // object -> world, see Transform
};

struct Scene {
    std::vector<Mesh> meshes;            // unique geometry, each instanced at least once
    std::vector<Instance> instances;     // glTF: depth-first node order, children in file order
    std::vector<std::string> materials;  // [0] = "default"; glTF material i is [i + 1] (its
                                         // name, "material_<i>" if it has none)
    std::vector<std::string> warnings;   // one line each, no file name prefix
};

struct ImportResult {
    Scene scene;        // meaningful only when ok(); on failure only scene.warnings may be
                        // non-empty (what was skipped before the error, e.g. the points
                        // primitives of a file that then has no triangles)
    std::string error;  // empty on success, else "<file>: <what is wrong>"
    bool ok() const noexcept { return error.empty(); }
};

// Imports any supported file, chosen by its extension (case-insensitive):
// .gltf/.glb -> import_gltf, .obj/.ply/.off/.stl -> import_mesh_file; anything else is an
// error.
ImportResult import_scene(const std::filesystem::path& path);

// Whether import_scene() reads `path` by its extension (.gltf .glb .obj .ply .off .stl, any
// case). Looks at the name only.
bool is_scene_file(const std::filesystem::path& path);

// glTF 2.0, JSON (.gltf, buffers embedded as data URIs or external files relative to the
// file's folder) or binary (.glb). The container is recognized by content (the "glTF" magic
// of glTF 2.0 "Binary glTF Layout"), not by the extension. Textures are never loaded.
//
// Which nodes: the scene `scene` names (glTF 2.0 "Scenes"); scene 0 when `scene` is
// absent; every root node (a node that is no one's child) when the file has no scenes.
// World transform of a node = parent's world transform * local, local = the node's
// `matrix` (column-major, must be affine) or T * R * S from translation, rotation
// (unit quaternion x, y, z, w) and scale (glTF 2.0 "Transformations").
//
// Supported: triangles, triangle strips and fans (mode 4, 5, 6; converted to lists by the
// rules of "Meshes": strip triangle i = (v_i, v_{i+1+i%2}, v_{i+2-i%2}), fan
// triangle i = (v_{i+1}, v_{i+2}, v_0)), indexed (unsigned byte / short / int) or not,
// several primitives per mesh, sparse accessors ("Sparse Accessors"), accessors without bufferView
// (zeros), KHR_mesh_quantization (integer and normalized positions / normals).
// Skipped with a warning: points and lines (mode 0-3), primitives without POSITION,
// morph targets and skins (the base / bind-pose geometry is imported as is), meshes
// that end up with no triangles (with all their instances).
// Errors (with the spec section): unreadable or malformed file, version other than 2.x,
// a required extension we cannot honour (e.g. KHR_draco_mesh_compression), any index out of
// range (node, mesh, accessor, bufferView, buffer, material), accessor data outside its
// bufferView or buffer, wrong accessor type or component type, vertex index >= vertex
// count, NaN/Inf positions or transforms, a node reachable twice (cycles; "Nodes and
// Hierarchy" requires disjoint strict trees), a missing or short buffer, and a scene with no triangles at
// all.
ImportResult import_gltf(const std::filesystem::path& path);

// The same from memory (a .gltf's JSON text or a whole .glb). External buffers are read
// relative to `base_dir`; `display_name` is what error messages call the file.
ImportResult import_gltf_from_memory(std::span<const std::uint8_t> bytes,
                                     const std::filesystem::path& base_dir, std::string_view display_name);

// OBJ, PLY (ASCII / binary) and STL (ASCII / binary), read by OpenMesh's format readers
// into a polygon soup (so non-manifold input is kept, not dropped as OpenMesh's half-edge
// meshes would); ASCII OFF ([ST][C][N]OFF with '#' comments, as in CGAL's data set) by a
// reader of our own, because OpenMesh 9 reads an OFF file with a comment line as empty;
// binary OFF is an error (OpenMesh 9 misreads the format's big-endian counts).
//   * One Mesh named after the file stem, one Instance with the identity transform, the
//     single default material (OBJ materials are not read).
//   * Polygons are triangulated by ear clipping in their best-fit (Newell) plane, which is
//     correct for concave planar polygons; faces with fewer than 3 corners are skipped
//     with a warning.
//   * Vertex normals from the file are used where it gives them, normalized (OBJ `vn`
//     through `f v//vn`, the last one given for a vertex wins; PLY nx/ny/nz; NOFF); the
//     other vertices' normals are computed (NormalOrigin says which case). STL facet
//     normals are per face and not used.
//   * Errors: unreadable file, declared element counts larger than the file can hold, face
//     index out of range, NaN/Inf coordinate, no triangles.
// What OpenMesh reports becomes Scene::warnings: for the duration of a read (serialized by
// a mutex of this module) std::cerr and std::clog are redirected into a buffer and
// std::cout output of OpenMesh is muted, so avoid writing to those from other threads
// meanwhile.
ImportResult import_mesh_file(const std::filesystem::path& path);

// Recomputes every vertex normal of `mesh` (sizes `normals` to 3 * vertex_count()) as the
// normalized sum over the incident triangles of (p1 - p0) x (p2 - p0): each face normal
// weighted by twice its area (area weighting; computed in double). A vertex whose sum is
// zero or not finite (unreferenced, or only degenerate/cancelling triangles) gets
// (0, 0, 1). Sets normal_origin = computed. Indices must be in range (not checked).
void compute_vertex_normals(Mesh& mesh);

// Content hash of the geometry, for naming assets: "fnv1a64:" + 16 lowercase hex digits of
// FNV-1a 64 over, in order, the vertex count and the triangle count (uint64 little-endian),
// the position floats' IEEE-754 bits (uint32 little-endian each) and the indices (uint32
// little-endian each). Normals, names and materials are not hashed; -0.0 and 0.0 differ.
std::string geometry_hash(const Mesh& mesh);

// Checks every invariant documented above; returns "" when all hold, else a description of
// the first violation. Every successful import satisfies it.
std::string check_scene(const Scene& scene);

}  // namespace lsnif::scene
