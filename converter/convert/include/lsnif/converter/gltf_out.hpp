// OUTDIR/scene.gltf: the converted scene as glTF 2.0, every complex mesh tagged with the
// LSNIF_neural_geometry extension (schema/LSNIF_neural_geometry.md) that names its .lsnif.
// The geometry stays: a renderer rasterizes (or traces) primary visibility against the
// triangles and traces secondary rays through the asset.
//
// Library code: never prints or exits.
#pragma once

#include <lsnif/converter/outcome.hpp>

#include <lsnif/scene/scene.hpp>

#include <nlohmann/json.hpp>

#include <filesystem>
#include <string>
#include <vector>

namespace lsnif::converter {

// The extension's name, as `extensionsUsed` and meshes[].extensions spell it.
inline constexpr const char* kGltfExtension = "LSNIF_neural_geometry";

// One input of a conversion: its path as given and its imported scene (null when the input
// failed to import; none of the manifest's meshes refers to it then).
struct GltfSource {
    std::string path;
    const scene::Scene* scene = nullptr;
};

// Writes OUTDIR/scene.gltf and OUTDIR/scene.bin for the manifest convert() wrote into
// `outdir` (its meshes' outcomes `meshes`, whose inputs are `sources` in order). Returns "" or "PATH:
// problem"; on failure nothing partial is left (each file is written to a temporary and renamed).
//
// One glTF input that imported: that document, kept whole (nodes, materials, textures,
// extras), its meshes tagged; buffer and image URIs made relative to OUTDIR again; a .glb's
// binary chunk written as scene.bin. Any other case (mesh files, several inputs): a document
// built from the imported scenes, one root node per input holding its instances, one
// primitive per material used, positions, normals and 32-bit indices in scene.bin.
std::string write_scene_gltf(const std::filesystem::path& outdir, const std::vector<GltfSource>& sources,
                             const std::vector<MeshOutcome>& meshes);

}  // namespace lsnif::converter
