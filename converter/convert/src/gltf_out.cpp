// OUTDIR/scene.gltf (gltf_out.hpp): the input glTF kept whole, or a document built from the
// imported scenes, with the LSNIF_neural_geometry extension on every converted mesh.
#include <lsnif/converter/gltf_out.hpp>
#include <lsnif/converter/manifest.hpp>
#include <lsnif/format/container.hpp>

#include <algorithm>
#include <array>
#include <cctype>
#include <cstdint>
#include <cstring>
#include <fstream>
#include <iterator>
#include <limits>
#include <map>
#include <span>

namespace lsnif::converter {

namespace fs = std::filesystem;
using nlohmann::json;

namespace {

// glTF 2.0 "Binary glTF Layout": the magic "glTF", version 2, and the chunk types.
constexpr std::uint32_t kGlbMagic = 0x46546C67, kChunkJson = 0x4E4F534A, kChunkBin = 0x004E4942;
// glTF 2.0 accessor component types and buffer view targets.
constexpr int kFloat = 5126, kUnsignedInt = 5125, kArrayBuffer = 34962, kElementArrayBuffer = 34963;

std::uint32_t le32(const std::uint8_t* p) {
    return std::uint32_t(p[0]) | std::uint32_t(p[1]) << 8 | std::uint32_t(p[2]) << 16 |
           std::uint32_t(p[3]) << 24;
}

// A glTF file's JSON document and, for a .glb, its binary chunk.
std::string read_gltf(const fs::path& path, json& doc, std::vector<std::uint8_t>& bin) {
    std::ifstream f(path, std::ios::binary);
    const std::vector<std::uint8_t> b{std::istreambuf_iterator<char>(f), std::istreambuf_iterator<char>()};
    if (!f && !f.eof()) return path.string() + ": cannot read";
    std::string text;
    if (b.size() >= 12 && le32(b.data()) == kGlbMagic) {
        for (std::size_t at = 12; at + 8 <= b.size();) {
            const std::uint32_t length = le32(&b[at]), type = le32(&b[at + 4]);
            if (length > b.size() - at - 8)
                return path.string() + ": a GLB chunk runs past the end of the file";
            const auto* data = reinterpret_cast<const char*>(&b[at + 8]);
            if (type == kChunkJson && text.empty()) text.assign(data, length);
            if (type == kChunkBin && bin.empty()) bin.assign(&b[at + 8], &b[at + 8] + length);
            at += 8 + std::size_t(length);
        }
    } else {
        text.assign(b.begin(), b.end());
    }
    doc = json::parse(text, nullptr, false);
    if (!doc.is_object()) return path.string() + ": its glTF JSON cannot be parsed";
    return {};
}

std::string percent_decoded(const std::string& uri) {
    std::string out;
    for (std::size_t i = 0; i < uri.size(); ++i) {
        if (uri[i] == '%' && i + 2 < uri.size() && std::isxdigit(static_cast<unsigned char>(uri[i + 1])) &&
            std::isxdigit(static_cast<unsigned char>(uri[i + 2]))) {
            out += char(std::stoi(uri.substr(i + 1, 2), nullptr, 16));
            i += 2;
        } else {
            out += uri[i];
        }
    }
    return out;
}

std::string percent_encoded(const std::string& path) {
    static const char* hex = "0123456789ABCDEF";
    std::string out;
    for (unsigned char c : path) {
        if (std::isalnum(c) || std::strchr("-._~/", c))
            out += char(c);
        else
            out += {'%', hex[c >> 4], hex[c & 15]};
    }
    return out;
}

// A buffer or image URI of a file in `from_dir`, for a document written into `outdir`. Data
// URIs and URIs with a scheme are absolute already.
std::string rebased_uri(const std::string& uri, const fs::path& from_dir, const fs::path& outdir) {
    const std::size_t colon = uri.find(':'), slash = uri.find('/');
    if (colon != std::string::npos && (slash == std::string::npos || colon < slash)) return uri;
    return percent_encoded(manifest_relative_path(from_dir / percent_decoded(uri), outdir));
}

// Appends `bytes` to `bin` at a 4-byte boundary (glTF 2.0 "Data Alignment") as a buffer view.
int add_view(json& doc, std::vector<std::uint8_t>& bin, std::span<const std::uint8_t> bytes, int target) {
    bin.resize((bin.size() + 3) & ~std::size_t(3), 0);
    doc["bufferViews"].push_back(
        {{"buffer", 0}, {"byteOffset", bin.size()}, {"byteLength", bytes.size()}, {"target", target}});
    bin.insert(bin.end(), bytes.begin(), bytes.end());
    return int(doc["bufferViews"].size()) - 1;
}

template <class T>
std::span<const std::uint8_t> as_bytes(const std::vector<T>& v) {
    return {reinterpret_cast<const std::uint8_t*>(v.data()), v.size() * sizeof(T)};
}

int add_accessor(json& doc, int view, int component, std::size_t count, const char* type) {
    doc["accessors"].push_back(
        {{"bufferView", view}, {"componentType", component}, {"count", count}, {"type", type}});
    return int(doc["accessors"].size()) - 1;
}

// A glTF mesh for `m`: shared POSITION and NORMAL, one primitive per material its
// triangles use (material 0, the default, gets none: glTF's default material).
json mesh_json(json& doc, std::vector<std::uint8_t>& bin, const scene::Mesh& m,
               const std::map<std::uint32_t, int>& materials) {
    std::array<float, 3> lo{}, hi{};
    lo.fill(std::numeric_limits<float>::infinity());
    hi.fill(-std::numeric_limits<float>::infinity());
    for (std::size_t v = 0; v < m.vertex_count(); ++v)
        for (int a = 0; a < 3; ++a) {
            lo[a] = std::min(lo[a], m.positions[3 * v + a]);
            hi[a] = std::max(hi[a], m.positions[3 * v + a]);
        }
    const int position = add_accessor(doc, add_view(doc, bin, as_bytes(m.positions), kArrayBuffer), kFloat,
                                      m.vertex_count(), "VEC3");
    doc["accessors"][position]["min"] = lo;
    doc["accessors"][position]["max"] = hi;
    const int normal = add_accessor(doc, add_view(doc, bin, as_bytes(m.normals), kArrayBuffer), kFloat,
                                    m.vertex_count(), "VEC3");
    std::map<std::uint32_t, std::vector<std::uint32_t>> by_material;
    for (std::size_t t = 0; t < m.triangle_count(); ++t) {
        const std::uint32_t mat = t < m.triangle_materials.size() ? m.triangle_materials[t] : 0;
        auto& idx = by_material[mat];
        idx.insert(idx.end(), &m.indices[3 * t], &m.indices[3 * t] + 3);
    }
    json prims = json::array();
    for (const auto& [mat, idx] : by_material) {
        const int view = add_view(doc, bin, as_bytes(idx), kElementArrayBuffer);
        json prim = {{"attributes", {{"POSITION", position}, {"NORMAL", normal}}},
                     {"indices", add_accessor(doc, view, kUnsignedInt, idx.size(), "SCALAR")},
                     {"mode", 4}};
        if (auto it = materials.find(mat); it != materials.end()) prim["material"] = it->second;
        prims.push_back(std::move(prim));
    }
    return {{"name", m.name}, {"primitives", prims}};
}

// glTF's column-major 4x4 from the 3x4 row-major [A|b] of scene::Transform.
json matrix_json(const scene::Transform& t) {
    return {t[0], t[4], t[8], 0, t[1], t[5], t[9], 0, t[2], t[6], t[10], 0, t[3], t[7], t[11], 1};
}

using MeshIndex = std::map<std::pair<std::size_t, std::size_t>, std::size_t>;  // (input, mesh) -> glTF mesh

// A document built from the imported scenes: one root node per input holding its instances.
json built_document(const std::vector<GltfSource>& sources, std::vector<std::uint8_t>& bin,
                    MeshIndex& index) {
    json doc = {{"asset", {{"version", "2.0"}, {"generator", std::string("lsnif ") + LSNIF_VERSION_STRING}}},
                {"scene", 0},
                {"scenes", {{{"nodes", json::array()}}}},
                {"nodes", json::array()},
                {"meshes", json::array()},
                {"materials", json::array()},
                {"accessors", json::array()},
                {"bufferViews", json::array()}};
    for (std::size_t i = 0; i < sources.size(); ++i) {
        const scene::Scene* sc = sources[i].scene;
        if (!sc) continue;
        std::map<std::uint32_t, int> materials;
        for (std::uint32_t j = 1; j < sc->materials.size(); ++j) {
            materials[j] = int(doc["materials"].size());
            doc["materials"].push_back({{"name", sc->materials[j]}});
        }
        for (std::size_t k = 0; k < sc->meshes.size(); ++k) {
            index[{i, k}] = doc["meshes"].size();
            doc["meshes"].push_back(mesh_json(doc, bin, sc->meshes[k], materials));
        }
        json children = json::array();
        for (const scene::Instance& in : sc->instances) {
            json node = {{"name", in.node_name}, {"mesh", index[{i, in.mesh}]}};
            if (in.transform != scene::kIdentityTransform) node["matrix"] = matrix_json(in.transform);
            children.push_back(doc["nodes"].size());
            doc["nodes"].push_back(std::move(node));
        }
        doc["scenes"][0]["nodes"].push_back(doc["nodes"].size());
        doc["nodes"].push_back(
            {{"name", fs::path(sources[i].path).filename().string()}, {"children", children}});
    }
    if (doc["materials"].empty()) doc.erase("materials");
    if (!bin.empty()) doc["buffers"] = {{{"uri", "scene.bin"}, {"byteLength", bin.size()}}};
    return doc;
}

// The one glTF input, kept whole: URIs rebased to OUTDIR, a .glb's binary chunk as scene.bin.
std::string kept_document(const GltfSource& source, const fs::path& outdir, json& doc,
                          std::vector<std::uint8_t>& bin, MeshIndex& index) {
    if (std::string e = read_gltf(source.path, doc, bin); !e.empty()) return e;
    const fs::path from = fs::path(source.path).parent_path();
    for (const char* list : {"buffers", "images"}) {
        if (!doc.contains(list) || !doc[list].is_array()) continue;
        for (std::size_t b = 0; b < doc[list].size(); ++b) {
            json& item = doc[list][b];
            if (item.contains("uri") && item["uri"].is_string())
                item["uri"] = rebased_uri(item["uri"].get<std::string>(), from, outdir);
            else if (std::string(list) == "buffers" && b == 0 && !bin.empty()) {
                // The GLB-stored buffer (glTF 2.0 "Binary buffer"): the chunk is padded to 4
                // bytes, an external buffer file must be byteLength long.
                item["uri"] = "scene.bin";
                const std::size_t length = item.value("byteLength", bin.size());
                if (length <= bin.size()) bin.resize(length);
            }
        }
    }
    for (std::size_t k = 0; k < source.scene->meshes.size(); ++k)
        if (source.scene->meshes[k].source_index >= 0)
            index[{0, k}] = std::size_t(source.scene->meshes[k].source_index);
    return {};
}

// Every mesh shipped as an LSNIF gets the extension on its glTF mesh.
void tag_meshes(json& doc, const MeshIndex& index, const std::vector<MeshOutcome>& meshes) {
    bool any = false;
    for (const MeshOutcome& m : meshes) {
        if (!m.asset || !m.held_out) continue;
        const auto it = index.find({std::size_t(m.input), std::size_t(m.source_mesh)});
        if (it == index.end() || it->second >= doc["meshes"].size()) continue;
        doc["meshes"][it->second]["extensions"][kGltfExtension] = {
            {"uri", percent_encoded(m.asset->file)},
            {"byteLength", m.asset->bytes},
            {"geometryHash", m.geometry_hash},
            {"manifestMesh", m.id},
            {"heldOutVisibility", m.held_out->metrics.pooled.visibility_accuracy},
            {"escapePoints", m.held_out->escape_points}};
        any = true;
    }
    if (!any) return;
    json& used = doc["extensionsUsed"];
    if (!used.is_array()) used = json::array();
    if (std::find(used.begin(), used.end(), kGltfExtension) == used.end()) used.push_back(kGltfExtension);
}

bool is_gltf_path(const std::string& path) {
    std::string ext = fs::path(path).extension().string();
    std::transform(ext.begin(), ext.end(), ext.begin(),
                   [](unsigned char c) { return char(std::tolower(c)); });
    return ext == ".gltf" || ext == ".glb";
}

}  // namespace

std::string write_scene_gltf(const fs::path& outdir, const std::vector<GltfSource>& sources,
                             const std::vector<MeshOutcome>& meshes) {
    json doc;
    std::vector<std::uint8_t> bin;
    MeshIndex index;
    if (sources.size() == 1 && sources[0].scene && is_gltf_path(sources[0].path)) {
        if (std::string e = kept_document(sources[0], outdir, doc, bin, index); !e.empty()) return e;
    } else {
        doc = built_document(sources, bin, index);
    }
    tag_meshes(doc, index, meshes);
    if (!bin.empty())
        if (const format::Error e = format::write_bytes_atomically((outdir / "scene.bin").string(), bin))
            return e.message;
    const format::Error e =
        format::write_text_atomically((outdir / "scene.gltf").string(), doc.dump(1) + "\n");
    return e ? e.message : std::string();
}

}  // namespace lsnif::converter
