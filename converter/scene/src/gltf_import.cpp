// glTF 2.0 import (.gltf / .glb) on top of tinygltf's parser. tinygltf turns the JSON and
// the buffers into a tinygltf::Model; it checks little of what the model says, so every
// index, accessor range and value is validated here before it is used. Quotes in error
// messages ("Accessors", "Nodes and Hierarchy", ...) are section names of the glTF 2.0
// specification.
#include "scene_internal.hpp"

#include <tiny_gltf.h>
#include <nlohmann/json.hpp>

#include <algorithm>
#include <bit>
#include <climits>
#include <cmath>
#include <cstring>
#include <exception>
#include <fstream>
#include <limits>
#include <map>
#include <new>
#include <span>
#include <string>
#include <utility>
#include <vector>

namespace lsnif::scene {
namespace {

using detail::quote_name;

static_assert(std::endian::native == std::endian::little,
              "glTF buffers are little-endian and are read with memcpy");

// An accessor without bufferView is all zeros (plus sparse values); nothing in the file
// bounds its count, so we do.
constexpr std::size_t kMaxZeroFilledElements = std::size_t(1) << 24;

constexpr std::int64_t kUnvisited = -2;
constexpr std::int64_t kSkipped = -1;

// Row-major 3x4 affine matrix [A | b] in double.
struct Affine {
    double m[3][4] = {{1, 0, 0, 0}, {0, 1, 0, 0}, {0, 0, 1, 0}};
};

Affine multiply(const Affine& a, const Affine& b) {
    Affine r;
    for (int i = 0; i < 3; ++i) {
        for (int j = 0; j < 4; ++j) {
            double s = a.m[i][0] * b.m[0][j] + a.m[i][1] * b.m[1][j] + a.m[i][2] * b.m[2][j];
            if (j == 3) s += a.m[i][3];
            r.m[i][j] = s;
        }
    }
    return r;
}

bool finite(const Affine& a) {
    for (const auto& row : a.m) {
        for (const double x : row) {
            if (!std::isfinite(x)) return false;
        }
    }
    return true;
}

int component_size(int type) {
    switch (type) {
        case TINYGLTF_COMPONENT_TYPE_BYTE:
        case TINYGLTF_COMPONENT_TYPE_UNSIGNED_BYTE: return 1;
        case TINYGLTF_COMPONENT_TYPE_SHORT:
        case TINYGLTF_COMPONENT_TYPE_UNSIGNED_SHORT: return 2;
        case TINYGLTF_COMPONENT_TYPE_UNSIGNED_INT:
        case TINYGLTF_COMPONENT_TYPE_FLOAT: return 4;
        default: return 0;  // includes 5124 (INT) and 5130 (DOUBLE): not glTF 2.0 accessor types
    }
}

std::string component_name(int type) {
    switch (type) {
        case TINYGLTF_COMPONENT_TYPE_BYTE: return "BYTE";
        case TINYGLTF_COMPONENT_TYPE_UNSIGNED_BYTE: return "UNSIGNED_BYTE";
        case TINYGLTF_COMPONENT_TYPE_SHORT: return "SHORT";
        case TINYGLTF_COMPONENT_TYPE_UNSIGNED_SHORT: return "UNSIGNED_SHORT";
        case TINYGLTF_COMPONENT_TYPE_UNSIGNED_INT: return "UNSIGNED_INT";
        case TINYGLTF_COMPONENT_TYPE_FLOAT: return "FLOAT";
        default: return "componentType " + std::to_string(type);
    }
}

std::string type_name(int type) {
    switch (type) {
        case TINYGLTF_TYPE_SCALAR: return "SCALAR";
        case TINYGLTF_TYPE_VEC2: return "VEC2";
        case TINYGLTF_TYPE_VEC3: return "VEC3";
        case TINYGLTF_TYPE_VEC4: return "VEC4";
        case TINYGLTF_TYPE_MAT2: return "MAT2";
        case TINYGLTF_TYPE_MAT3: return "MAT3";
        case TINYGLTF_TYPE_MAT4: return "MAT4";
        default: return "type " + std::to_string(type);
    }
}

std::string mode_name(int mode) {
    switch (mode) {
        case TINYGLTF_MODE_POINTS: return "POINTS";
        case TINYGLTF_MODE_LINE: return "LINES";
        case TINYGLTF_MODE_LINE_LOOP: return "LINE_LOOP";
        case TINYGLTF_MODE_LINE_STRIP: return "LINE_STRIP";
        case TINYGLTF_MODE_TRIANGLES: return "TRIANGLES";
        case TINYGLTF_MODE_TRIANGLE_STRIP: return "TRIANGLE_STRIP";
        case TINYGLTF_MODE_TRIANGLE_FAN: return "TRIANGLE_FAN";
        default: return "mode " + std::to_string(mode);
    }
}

bool is_unsigned_index_type(int type) {
    return type == TINYGLTF_COMPONENT_TYPE_UNSIGNED_BYTE || type == TINYGLTF_COMPONENT_TYPE_UNSIGNED_SHORT ||
           type == TINYGLTF_COMPONENT_TYPE_UNSIGNED_INT;
}

// One component as float. Normalized integers follow glTF 2.0 "Accessor Data Types":
// f = max(c / 127, -1), c / 255, max(c / 32767, -1), c / 65535.
float decode_float(const unsigned char* p, int type, bool normalized) {
    switch (type) {
        case TINYGLTF_COMPONENT_TYPE_FLOAT: {
            float f;
            std::memcpy(&f, p, 4);
            return f;
        }
        case TINYGLTF_COMPONENT_TYPE_BYTE: {
            std::int8_t c;
            std::memcpy(&c, p, 1);
            return normalized ? std::max(float(c) / 127.0f, -1.0f) : float(c);
        }
        case TINYGLTF_COMPONENT_TYPE_UNSIGNED_BYTE: {
            const std::uint8_t c = p[0];
            return normalized ? float(c) / 255.0f : float(c);
        }
        case TINYGLTF_COMPONENT_TYPE_SHORT: {
            std::int16_t c;
            std::memcpy(&c, p, 2);
            return normalized ? std::max(float(c) / 32767.0f, -1.0f) : float(c);
        }
        case TINYGLTF_COMPONENT_TYPE_UNSIGNED_SHORT: {
            std::uint16_t c;
            std::memcpy(&c, p, 2);
            return normalized ? float(c) / 65535.0f : float(c);
        }
        default: return 0.0f;  // not reached: component types are checked before decoding
    }
}

std::uint32_t decode_uint(const unsigned char* p, int type) {
    switch (type) {
        case TINYGLTF_COMPONENT_TYPE_UNSIGNED_BYTE: return p[0];
        case TINYGLTF_COMPONENT_TYPE_UNSIGNED_SHORT: {
            std::uint16_t c;
            std::memcpy(&c, p, 2);
            return c;
        }
        case TINYGLTF_COMPONENT_TYPE_UNSIGNED_INT: {
            std::uint32_t c;
            std::memcpy(&c, p, 4);
            return c;
        }
        default: return 0;  // not reached: checked before decoding
    }
}

// The image loader tinygltf calls for embedded / bufferView images: we never decode images.
bool ignore_image(tinygltf::Image*, const int, std::string*, std::string*, int, int, const unsigned char*,
                  int, void*) {
    return true;
}

// Extensions a file may *require* that we honour: either implemented here
// (KHR_mesh_quantization) or without any effect on geometry (materials, textures, lights).
bool extension_supported(const std::string& name) {
    return name == "KHR_mesh_quantization" || name.rfind("KHR_materials_", 0) == 0 ||
           name == "KHR_texture_transform" || name == "KHR_texture_basisu" || name == "EXT_texture_webp" ||
           name == "EXT_texture_avif" || name == "KHR_lights_punctual";
}

std::string unsupported_extension_message(const std::string& ext) {
    return "the file requires extension " + ext +
           ", which this importer does not support (glTF 2.0 \"Specifying Extensions\"); "
           "re-export the scene without it" +
           (ext == "KHR_draco_mesh_compression" || ext == "EXT_meshopt_compression"
                ? std::string(" (e.g. with uncompressed geometry)")
                : std::string());
}

std::string one_line(std::string text) {
    for (char& c : text) {
        if (c == '\n' || c == '\r') c = ' ';
    }
    while (!text.empty() && text.back() == ' ') text.pop_back();
    return text;
}

// tinygltf converts JSON values (e.g. `extras`) recursively: a deeply nested document would
// overflow the call stack, so the nesting depth is bounded before anything parses it.
constexpr std::size_t kMaxJsonDepth = 256;

// Deepest nesting of arrays / objects in JSON text (brackets inside strings ignored).
std::size_t json_depth(const char* text, std::size_t length) {
    std::size_t depth = 0, deepest = 0;
    bool in_string = false;
    for (std::size_t i = 0; i < length; ++i) {
        const char c = text[i];
        if (in_string) {
            if (c == '\\') {
                ++i;
            } else if (c == '"') {
                in_string = false;
            }
        } else if (c == '"') {
            in_string = true;
        } else if (c == '[' || c == '{') {
            deepest = std::max(deepest, ++depth);
        } else if ((c == ']' || c == '}') && depth > 0) {
            --depth;
        }
    }
    return deepest;
}

// A .glb whose buffer 0 (the one without a uri) declares more bytes than its BIN chunk holds,
// or that has no BIN chunk for it: tinygltf reads past the end of the file for it (glTF 2.0
// "Binary buffer": the chunk is the buffer, padded to 4 bytes). The problem, or "".
std::string glb_buffer_problem(std::span<const std::uint8_t> bytes, std::string_view json_text) {
    const nlohmann::json j = nlohmann::json::parse(json_text, nullptr, false);
    if (!j.is_object() || !j.contains("buffers") || !j["buffers"].is_array() || j["buffers"].empty())
        return {};
    const nlohmann::json& b0 = j["buffers"][0];
    if (!b0.is_object() || b0.contains("uri") || !b0.contains("byteLength") ||
        !b0["byteLength"].is_number_unsigned())
        return {};
    const std::uint64_t declared = b0["byteLength"].get<std::uint64_t>();
    std::uint32_t json_chunk = 0;
    std::memcpy(&json_chunk, bytes.data() + 12, 4);
    const std::uint64_t bin_header = 20 + std::uint64_t(json_chunk);
    std::uint32_t bin_length = 0, bin_type = 0;
    if (bin_header + 8 <= bytes.size()) {
        std::memcpy(&bin_length, bytes.data() + bin_header, 4);
        std::memcpy(&bin_type, bytes.data() + bin_header + 4, 4);
    }
    const std::uint64_t available = bin_type == 0x004E4942u
                                        ? std::min<std::uint64_t>(bin_length, bytes.size() - bin_header - 8)
                                        : 0;  // "BIN\0"
    if (declared <= available) return {};
    return "invalid binary glTF (.glb): buffer 0 declares " + std::to_string(declared) +
           " bytes, the BIN chunk holds " + std::to_string(available) +
           " (truncated or inconsistent; glTF 2.0 \"Binary buffer\")";
}

// Looks at the version fields and extensionsRequired before tinygltf parses the file, so
// that a file we cannot read gets the real reason rather than one of its consequences
// (tinygltf rejects KHR_draco_mesh_compression files with "accessor[0] invalid bufferView",
// and glTF 1.0 .glb files with "Invalid glTF binary"). Returns "" when nothing is found or
// the JSON is unreadable (tinygltf then reports the parse error).
std::string precheck(std::span<const std::uint8_t> bytes, bool binary) {
    const char* text = reinterpret_cast<const char*>(bytes.data());
    std::size_t length = bytes.size();
    if (binary) {
        if (bytes.size() < 20) return {};
        std::uint32_t version = 0, chunk = 0;
        std::memcpy(&version, bytes.data() + 4, 4);
        std::memcpy(&chunk, bytes.data() + 12, 4);
        if (version != 2) {
            return "binary glTF container version " + std::to_string(version) +
                   "; only version 2 is supported (glTF 2.0 \"Binary glTF Layout\")";
        }
        if (std::size_t(chunk) > bytes.size() - 20) return {};
        text += 20;
        length = chunk;
    }
    if (binary)
        if (std::string why = glb_buffer_problem(bytes, std::string_view(text, length)); !why.empty())
            return why;
    if (const std::size_t depth = json_depth(text, length); depth > kMaxJsonDepth) {
        return "the JSON nests " + std::to_string(depth) + " levels deep (at most " +
               std::to_string(kMaxJsonDepth) + " accepted)";
    }
    const nlohmann::json j = nlohmann::json::parse(text, text + length, nullptr, false);
    if (j.is_discarded() || !j.is_object()) return {};
    if (const auto asset = j.find("asset"); asset != j.end() && asset->is_object()) {
        const auto version = asset->find("version");
        if (version != asset->end() && version->is_string()) {
            const std::string v = version->get<std::string>();
            if (v.rfind("2.", 0) != 0) {
                return "asset.version is \"" + v + "\"; only glTF 2.x is supported (glTF 2.0 \"Asset\")";
            }
        }
    }
    if (const auto req = j.find("extensionsRequired"); req != j.end() && req->is_array()) {
        for (const auto& e : *req) {
            if (e.is_string() && !extension_supported(e.get<std::string>())) {
                return unsupported_extension_message(e.get<std::string>());
            }
        }
    }
    return {};
}

class GltfImporter {
public:
    GltfImporter(const tinygltf::Model& model, std::string file) : model_(model), file_(std::move(file)) {}

    void add_parser_messages(const std::string& text) {
        std::size_t start = 0;
        while (start < text.size()) {
            std::size_t end = text.find('\n', start);
            if (end == std::string::npos) end = text.size();
            if (end > start) warnings_.add("tinygltf: " + text.substr(start, end - start));
            start = end + 1;
        }
    }

    ImportResult run() {
        if (!check_asset() || !check_extensions() || !import_hierarchy()) {
            ImportResult failed;
            failed.error = file_ + ": " + error_;
            warnings_.finish(failed.scene.warnings);  // what was skipped before the error
            return failed;
        }
        warnings_.finish(scene_.warnings);
        return {std::move(scene_), {}};
    }

private:
    bool fail(std::string message) {
        if (error_.empty()) error_ = std::move(message);
        return false;
    }

    // glTF 2.0 "Asset": we read 2.x files whose minVersion is at most 2.0.
    bool check_asset() {
        const std::string& v = model_.asset.version;
        if (v.rfind("2.", 0) != 0) {
            return fail("asset.version is \"" + v + "\"; only glTF 2.x is supported (glTF 2.0 \"Asset\")");
        }
        const std::string& mv = model_.asset.minVersion;
        if (!mv.empty() && mv != "2.0") {
            return fail("asset.minVersion is \"" + mv +
                        "\"; this importer implements glTF 2.0 (glTF 2.0 \"Asset\")");
        }
        return true;
    }

    // glTF 2.0 "Specifying Extensions": a loader MUST refuse a file that requires an
    // extension it does not support.
    bool check_extensions() {
        for (const std::string& ext : model_.extensionsRequired) {
            if (!extension_supported(ext)) return fail(unsupported_extension_message(ext));
        }
        for (const std::string& ext : model_.extensionsUsed) {
            if (ext == "KHR_mesh_quantization") quantization_ = true;
            if (ext == "EXT_mesh_gpu_instancing") {
                warnings_.add(
                    "extension EXT_mesh_gpu_instancing is ignored: only the nodes "
                    "themselves are instanced");
            }
        }
        return true;
    }

    bool import_hierarchy() {
        scene_.materials.reserve(model_.materials.size() + 1);
        scene_.materials.push_back("default");
        for (std::size_t i = 0; i < model_.materials.size(); ++i) {
            const std::string& name = model_.materials[i].name;
            scene_.materials.push_back(name.empty() ? "material_" + std::to_string(i) : name);
        }
        mesh_slot_.assign(model_.meshes.size(), kUnvisited);

        // glTF 2.0 "Scenes": `scene` selects the scene to display; without it any may be
        // chosen (we take scene 0); a file without scenes is a library of nodes, of which we
        // take every root.
        std::vector<int> roots;
        std::string origin;
        if (!model_.scenes.empty()) {
            const int s = model_.defaultScene < 0 ? 0 : model_.defaultScene;
            if (std::size_t(s) >= model_.scenes.size()) {
                return fail("scene " + std::to_string(s) + " does not exist (the file has " +
                            std::to_string(model_.scenes.size()) + " scenes; glTF 2.0 \"Scenes\")");
            }
            roots = model_.scenes[std::size_t(s)].nodes;
            origin = "scene " + std::to_string(s);
        } else {
            if (model_.defaultScene >= 0) {
                return fail("scene " + std::to_string(model_.defaultScene) +
                            " does not exist (the file has no scenes; glTF 2.0 \"Scenes\")");
            }
            std::vector<std::uint8_t> is_child(model_.nodes.size(), 0);
            for (const auto& node : model_.nodes) {
                for (const int c : node.children) {
                    if (c >= 0 && std::size_t(c) < is_child.size()) is_child[std::size_t(c)] = 1;
                }
            }
            for (std::size_t i = 0; i < model_.nodes.size(); ++i) {
                if (!is_child[i]) roots.push_back(int(i));
            }
            if (!roots.empty()) {
                warnings_.add("the file has no scenes; importing all " + std::to_string(roots.size()) +
                              " root nodes");
            }
            origin = "the root node list";
        }
        if (!traverse(roots, origin)) return false;
        if (scene_.instances.empty()) {
            std::size_t skipped = 0;
            for (const std::int64_t slot : mesh_slot_) skipped += slot == kSkipped ? 1 : 0;
            return fail(skipped == 0 ? "no triangles to import: " + origin + " instances no mesh"
                                     : "no triangles to import: the " + std::to_string(skipped) +
                                           " mesh(es) instanced by " + origin +
                                           " have no triangle primitives (see warnings)");
        }
        return true;
    }

    // Depth-first over the node trees with an explicit stack (no recursion, so a deep
    // hierarchy cannot overflow the call stack). glTF 2.0 "Nodes and Hierarchy": the
    // hierarchy MUST be a set of disjoint strict trees, so every node is reached at most
    // once; a second visit means a cycle or a shared child and is an error.
    bool traverse(const std::vector<int>& roots, const std::string& origin) {
        struct Item {
            int node;
            int parent;  // -1: listed by `origin`
            Affine parent_world;
        };
        std::vector<Item> stack;
        for (auto it = roots.rbegin(); it != roots.rend(); ++it) stack.push_back({*it, -1, {}});
        std::vector<std::uint8_t> visited(model_.nodes.size(), 0);
        while (!stack.empty()) {
            const Item item = stack.back();
            stack.pop_back();
            const std::string lister = item.parent < 0 ? origin : "node " + std::to_string(item.parent);
            if (item.node < 0 || std::size_t(item.node) >= model_.nodes.size()) {
                return fail(lister + " refers to node " + std::to_string(item.node) +
                            ", which does not exist (the file has " + std::to_string(model_.nodes.size()) +
                            " nodes)");
            }
            const tinygltf::Node& node = model_.nodes[std::size_t(item.node)];
            const std::string what = "node " + std::to_string(item.node) + quote_name(node.name);
            if (visited[std::size_t(item.node)]) {
                return fail(what + " is reached a second time, from " + lister +
                            ": the node hierarchy has a cycle or a node with two parents "
                            "(glTF 2.0 \"Nodes and Hierarchy\" requires disjoint strict trees)");
            }
            visited[std::size_t(item.node)] = 1;

            Affine local;
            if (!local_transform(node, what, local)) return false;
            const Affine world = multiply(item.parent_world, local);
            if (!finite(world)) {
                return fail(what + ": the world transform overflows (not finite)");
            }
            if (node.mesh >= 0 || node.mesh < -1) {
                std::int64_t slot = kSkipped;
                if (!mesh_slot(node.mesh, what, slot)) return false;
                if (node.skin >= 0) {
                    warnings_.add(what +
                                  " is skinned: skinning is not applied, the mesh is "
                                  "instanced with the node's transform");
                }
                if (slot >= 0) {
                    Instance inst;
                    inst.mesh = std::uint32_t(slot);
                    inst.node_name = node.name.empty() ? "node_" + std::to_string(item.node) : node.name;
                    for (int r = 0; r < 3; ++r) {
                        for (int c = 0; c < 4; ++c) {
                            const float x = float(world.m[r][c]);
                            if (!std::isfinite(x)) {
                                return fail(what + ": the world transform exceeds the float range");
                            }
                            inst.transform[std::size_t(4 * r + c)] = x;
                        }
                    }
                    scene_.instances.push_back(std::move(inst));
                }
            }
            for (auto it = node.children.rbegin(); it != node.children.rend(); ++it) {
                stack.push_back({*it, item.node, world});
            }
        }
        return true;
    }

    // glTF 2.0 "Transformations": `matrix` (column-major) or T * R * S.
    bool local_transform(const tinygltf::Node& node, const std::string& what, Affine& out) {
        if (!node.matrix.empty()) {
            const std::vector<double>& c = node.matrix;
            if (c.size() != 16) {
                return fail(what + ": matrix has " + std::to_string(c.size()) +
                            " elements, not 16 (glTF 2.0 \"Transformations\")");
            }
            for (const double x : c) {
                if (!std::isfinite(x)) return fail(what + ": matrix has a non-finite element");
            }
            if (!node.translation.empty() || !node.rotation.empty() || !node.scale.empty()) {
                warnings_.add(what +
                              " has both matrix and translation/rotation/scale; the "
                              "matrix is used (glTF 2.0 \"Transformations\" forbids both)");
            }
            // Column-major: element (row r, column k) is c[4 * k + r]. The bottom row must be
            // (0, 0, 0, 1): the spec requires matrices decomposable to TRS.
            if (std::fabs(c[3]) > 1e-6 || std::fabs(c[7]) > 1e-6 || std::fabs(c[11]) > 1e-6 ||
                std::fabs(c[15] - 1.0) > 1e-6) {
                return fail(what +
                            ": matrix is not affine (its bottom row is not 0 0 0 1; "
                            "glTF 2.0 \"Transformations\")");
            }
            for (int r = 0; r < 3; ++r) {
                for (int k = 0; k < 4; ++k) out.m[r][k] = c[std::size_t(4 * k + r)];
            }
            return true;
        }
        double t[3] = {0, 0, 0}, q[4] = {0, 0, 0, 1}, s[3] = {1, 1, 1};
        auto take = [&](const std::vector<double>& v, std::size_t n, double* dst, const char* name) {
            if (v.empty()) return true;
            if (v.size() != n) {
                return fail(what + ": " + name + " has " + std::to_string(v.size()) + " elements, not " +
                            std::to_string(n) + " (glTF 2.0 \"Transformations\")");
            }
            for (std::size_t i = 0; i < n; ++i) {
                if (!std::isfinite(v[i])) {
                    return fail(what + ": " + name + " has a non-finite element");
                }
                dst[i] = v[i];
            }
            return true;
        };
        if (!take(node.translation, 3, t, "translation") || !take(node.rotation, 4, q, "rotation") ||
            !take(node.scale, 3, s, "scale")) {
            return false;
        }
        const double len = std::sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]);
        if (!(len > 0.0) || !std::isfinite(len)) {
            return fail(what + ": rotation is not a unit quaternion (it is zero)");
        }
        if (std::fabs(len - 1.0) > 1e-3) {
            warnings_.add(what + ": rotation quaternion has length " + std::to_string(len) +
                          "; normalized (glTF 2.0 \"Transformations\" requires unit quaternions)");
        }
        const double x = q[0] / len, y = q[1] / len, z = q[2] / len, w = q[3] / len;
        // Rotation matrix of the unit quaternion (x, y, z, w).
        const double rot[3][3] = {{1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)},
                                  {2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)},
                                  {2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)}};
        for (int r = 0; r < 3; ++r) {
            for (int k = 0; k < 3; ++k) out.m[r][k] = rot[r][k] * s[k];  // R * S
            out.m[r][3] = t[r];                                          // T * (R * S)
        }
        return true;
    }

    bool mesh_slot(int index, const std::string& node_what, std::int64_t& slot) {
        if (index < 0 || std::size_t(index) >= model_.meshes.size()) {
            return fail(node_what + " refers to mesh " + std::to_string(index) +
                        ", which does not exist (the file has " + std::to_string(model_.meshes.size()) +
                        " meshes)");
        }
        std::int64_t& cached = mesh_slot_[std::size_t(index)];
        if (cached == kUnvisited) {
            Mesh mesh;
            const std::string what =
                "mesh " + std::to_string(index) + quote_name(model_.meshes[std::size_t(index)].name);
            if (!import_mesh(index, what, mesh)) return false;
            if (mesh.indices.empty()) {
                warnings_.add(what + " has no triangles; its instances are skipped");
                cached = kSkipped;
            } else {
                cached = std::int64_t(scene_.meshes.size());
                scene_.meshes.push_back(std::move(mesh));
            }
        }
        slot = cached;
        return true;
    }

    // Bytes of a bufferView, checked against its buffer (glTF 2.0 "Buffers and Buffer
    // Views"). `stride` is its byteStride (0 = tightly packed).
    bool view_bytes(int index, const std::string& what, const unsigned char*& data, std::size_t& length,
                    std::size_t& stride) {
        if (index < 0 || std::size_t(index) >= model_.bufferViews.size()) {
            return fail(what + ": bufferView " + std::to_string(index) + " does not exist (the file has " +
                        std::to_string(model_.bufferViews.size()) + " bufferViews)");
        }
        const tinygltf::BufferView& view = model_.bufferViews[std::size_t(index)];
        const std::string vwhat = what + ": bufferView " + std::to_string(index);
        if (view.buffer < 0 || std::size_t(view.buffer) >= model_.buffers.size()) {
            return fail(vwhat + " refers to buffer " + std::to_string(view.buffer) +
                        ", which does not exist (the file has " + std::to_string(model_.buffers.size()) +
                        " buffers)");
        }
        const tinygltf::Buffer& buffer = model_.buffers[std::size_t(view.buffer)];
        const std::size_t size = buffer.data.size();
        if (view.byteLength == 0) return fail(vwhat + " has byteLength 0");
        if (view.byteOffset > size || view.byteLength > size - view.byteOffset) {
            return fail(vwhat + " (byteOffset " + std::to_string(view.byteOffset) + ", byteLength " +
                        std::to_string(view.byteLength) + ") extends past the end of buffer " +
                        std::to_string(view.buffer) +
                        quote_name(buffer.uri.size() < 200 ? buffer.uri : std::string()) + " (" +
                        std::to_string(size) +
                        " bytes loaded; glTF 2.0 \"Buffers and Buffer "
                        "Views\")");
        }
        data = buffer.data.data() + view.byteOffset;
        length = view.byteLength;
        stride = view.byteStride;
        return true;
    }

    // Where the `elem`-byte elements of accessor `acc` start (`base`) and their `stride`,
    // checked to lie inside its bufferView (glTF 2.0 "Accessors", "Data Alignment"). For an
    // accessor without bufferView `base` stays null and its count is bounded instead.
    bool accessor_elements(const tinygltf::Accessor& acc, const std::string& awhat, std::size_t elem,
                           const unsigned char*& base, std::size_t& stride) {
        if (acc.bufferView < 0) {
            if (acc.count > kMaxZeroFilledElements) {
                return fail(awhat + " has no bufferView and count " + std::to_string(acc.count) +
                            " (more than the " + std::to_string(kMaxZeroFilledElements) +
                            " zero-initialized elements accepted)");
            }
            return true;
        }
        const unsigned char* vdata = nullptr;
        std::size_t vlen = 0, vstride = 0;
        if (!view_bytes(acc.bufferView, awhat, vdata, vlen, vstride)) return false;
        if (vstride != 0) {
            if (vstride < elem) {
                return fail(awhat + ": bufferView byteStride " + std::to_string(vstride) +
                            " is smaller than the element size " + std::to_string(elem) +
                            " (glTF 2.0 \"Buffers and Buffer Views\")");
            }
            stride = vstride;
        }
        // Last byte read: byteOffset + (count - 1) * stride + elem, overflow-checked.
        std::size_t end = 0;
        if (__builtin_mul_overflow(acc.count - 1, stride, &end) || __builtin_add_overflow(end, elem, &end) ||
            __builtin_add_overflow(end, acc.byteOffset, &end) || end > vlen) {
            return fail(awhat + " (byteOffset " + std::to_string(acc.byteOffset) + ", count " +
                        std::to_string(acc.count) + ", stride " + std::to_string(stride) +
                        ") reads past the end of its bufferView " + std::to_string(acc.bufferView) +
                        " (byteLength " + std::to_string(vlen) + "; glTF 2.0 \"Accessors\")");
        }
        base = vdata + acc.byteOffset;
        return true;
    }

    // The bytes of a sparse accessor's substitution: `n` indices of `isize` bytes at `idata`
    // and n values of the accessor's element size at `vdata`, both tightly packed.
    struct SparseBytes {
        std::size_t n = 0, isize = 0;
        const unsigned char* idata = nullptr;
        const unsigned char* vdata = nullptr;
    };

    // Locates the sparse substitution of accessor `acc` (elements of `elem` bytes) into
    // `out`, checking its count, index type and byte ranges (glTF 2.0 "Sparse Accessors").
    // The index values themselves are checked by the caller as it applies them.
    bool sparse_bytes(const tinygltf::Accessor& acc, const std::string& swhat, std::size_t elem,
                      SparseBytes& out) {
        const auto& sp = acc.sparse;
        if (sp.count < 1 || std::size_t(sp.count) > acc.count) {
            return fail(swhat + ".count " + std::to_string(sp.count) + " is not in [1, " +
                        std::to_string(acc.count) + "] (glTF 2.0 \"Sparse Accessors\")");
        }
        if (!is_unsigned_index_type(sp.indices.componentType)) {
            return fail(swhat + ".indices has " + component_name(sp.indices.componentType) +
                        "; UNSIGNED_BYTE, UNSIGNED_SHORT or UNSIGNED_INT required (glTF 2.0 "
                        "\"Sparse Accessors\")");
        }
        if (sp.indices.byteOffset < 0 || sp.values.byteOffset < 0) {
            return fail(swhat + " has a negative byteOffset");
        }
        const std::size_t n = std::size_t(sp.count);
        const std::size_t isize = std::size_t(component_size(sp.indices.componentType));
        const unsigned char* idata = nullptr;
        const unsigned char* vdata = nullptr;
        std::size_t ilen = 0, vlen = 0, unused = 0;
        if (!view_bytes(sp.indices.bufferView, swhat + ".indices", idata, ilen, unused) ||
            !view_bytes(sp.values.bufferView, swhat + ".values", vdata, vlen, unused)) {
            return false;
        }
        // Both are tightly packed: n * size bytes from byteOffset.
        const std::size_t ioff = std::size_t(sp.indices.byteOffset);
        const std::size_t voff = std::size_t(sp.values.byteOffset);
        if (ioff > ilen || n * isize > ilen - ioff) {
            return fail(swhat + ".indices read past the end of their bufferView");
        }
        if (voff > vlen || (vlen - voff) / elem < n) {
            return fail(swhat + ".values read past the end of their bufferView");
        }
        out = {n, isize, idata + ioff, vdata + voff};
        return true;
    }

    // Reads accessor `index` as `components` values per element, each decoded by
    // `decode(pointer to component)`, into out (count * components values). Checks that
    // every element lies inside its bufferView (glTF 2.0 "Accessors", "Data Alignment")
    // and applies sparse substitution ("Sparse Accessors").
    template <class T, class Decode>
    bool read_accessor(int index, const std::string& what, std::size_t components, Decode decode,
                       std::vector<T>& out) {
        const tinygltf::Accessor& acc = model_.accessors[std::size_t(index)];
        const std::string awhat = what + " accessor " + std::to_string(index);
        const std::size_t csize = std::size_t(component_size(acc.componentType));
        const std::size_t elem = csize * components;
        if (acc.count == 0) {
            return fail(awhat + " has count 0 (glTF 2.0 \"Accessors\": count >= 1)");
        }
        const unsigned char* base = nullptr;
        std::size_t stride = elem;
        if (!accessor_elements(acc, awhat, elem, base, stride)) return false;
        std::size_t total = 0;
        if (__builtin_mul_overflow(acc.count, components, &total)) {
            return fail(awhat + ": count " + std::to_string(acc.count) + " is too large");
        }
        out.assign(total, T{});
        if (base != nullptr) {
            for (std::size_t i = 0; i < acc.count; ++i) {
                const unsigned char* e = base + i * stride;
                for (std::size_t c = 0; c < components; ++c) {
                    out[i * components + c] = decode(e + c * csize);
                }
            }
        }
        if (!acc.sparse.isSparse) return true;

        const std::string swhat = awhat + " sparse";
        SparseBytes sp;
        if (!sparse_bytes(acc, swhat, elem, sp)) return false;
        std::uint32_t previous = 0;
        for (std::size_t k = 0; k < sp.n; ++k) {
            const std::uint32_t target =
                decode_uint(sp.idata + k * sp.isize, acc.sparse.indices.componentType);
            if (target >= acc.count) {
                return fail(swhat + ": index " + std::to_string(target) + " at position " +
                            std::to_string(k) + " is not below count " + std::to_string(acc.count) +
                            " (glTF 2.0 \"Sparse Accessors\")");
            }
            if (k > 0 && target <= previous) {
                return fail(swhat + ": indices are not strictly increasing at position " + std::to_string(k) +
                            " (glTF 2.0 \"Sparse Accessors\")");
            }
            previous = target;
            for (std::size_t c = 0; c < components; ++c) {
                out[std::size_t(target) * components + c] = decode(sp.vdata + k * elem + c * csize);
            }
        }
        return true;
    }

    bool accessor_exists(int index, const std::string& what) {
        if (index < 0 || std::size_t(index) >= model_.accessors.size()) {
            return fail(what + " refers to accessor " + std::to_string(index) +
                        ", which does not exist (the file has " + std::to_string(model_.accessors.size()) +
                        " accessors)");
        }
        return true;
    }

    // POSITION (role "POSITION") or NORMAL: VEC3 of FLOAT; with KHR_mesh_quantization also
    // the integer types that extension allows.
    bool read_vec3(int index, const std::string& what, bool is_position, std::vector<float>& out) {
        const char* role = is_position ? "POSITION" : "NORMAL";
        const std::string rwhat = what + " " + role;
        if (!accessor_exists(index, rwhat)) return false;
        const tinygltf::Accessor& acc = model_.accessors[std::size_t(index)];
        if (acc.type != TINYGLTF_TYPE_VEC3) {
            return fail(rwhat + " accessor " + std::to_string(index) + " is " + type_name(acc.type) +
                        ", not VEC3 (glTF 2.0 \"Meshes\")");
        }
        const int ct = acc.componentType;
        bool ok = ct == TINYGLTF_COMPONENT_TYPE_FLOAT;
        if (quantization_ && !ok) {
            ok = is_position
                     ? (ct == TINYGLTF_COMPONENT_TYPE_BYTE || ct == TINYGLTF_COMPONENT_TYPE_UNSIGNED_BYTE ||
                        ct == TINYGLTF_COMPONENT_TYPE_SHORT || ct == TINYGLTF_COMPONENT_TYPE_UNSIGNED_SHORT)
                     : ((ct == TINYGLTF_COMPONENT_TYPE_BYTE || ct == TINYGLTF_COMPONENT_TYPE_SHORT) &&
                        acc.normalized);
        }
        if (!ok) {
            return fail(rwhat + " accessor " + std::to_string(index) + " has component type " +
                        component_name(ct) + "; FLOAT is required (glTF 2.0 \"Meshes\"), or " +
                        "an integer type with KHR_mesh_quantization");
        }
        const bool normalized = acc.normalized;
        return read_accessor<float>(
            index, rwhat, 3,
            [ct, normalized](const unsigned char* p) { return decode_float(p, ct, normalized); }, out);
    }

    bool read_indices(int index, const std::string& what, std::vector<std::uint32_t>& out) {
        const std::string iwhat = what + " indices";
        if (!accessor_exists(index, iwhat)) return false;
        const tinygltf::Accessor& acc = model_.accessors[std::size_t(index)];
        if (acc.type != TINYGLTF_TYPE_SCALAR || !is_unsigned_index_type(acc.componentType)) {
            return fail(iwhat + " accessor " + std::to_string(index) + " is " + type_name(acc.type) + " of " +
                        component_name(acc.componentType) +
                        "; SCALAR of UNSIGNED_BYTE, UNSIGNED_SHORT or UNSIGNED_INT is required "
                        "(glTF 2.0 \"Meshes\")");
        }
        const int ct = acc.componentType;
        return read_accessor<std::uint32_t>(
            index, iwhat, 1, [ct](const unsigned char* p) { return decode_uint(p, ct); }, out);
    }

    // What import_mesh carries from one primitive of a mesh to the next.
    struct MeshBuild {
        std::vector<std::uint8_t> has_normal;  // per vertex of the mesh: its normal came from the file
        // Primitives that use the same POSITION and NORMAL accessors share their vertices:
        // (POSITION, NORMAL or -1) -> (first vertex, vertex count).
        std::map<std::pair<int, int>, std::pair<std::uint32_t, std::uint32_t>> ranges;
        bool morph_warned = false;
        std::vector<float> positions, normals;  // one primitive's attributes
        std::vector<std::uint32_t> indices;     // one primitive's indices
    };

    // Merges the triangle primitives of glTF mesh `index` into `mesh` (left without
    // triangles when it has none, which the caller reports).
    bool import_mesh(int index, const std::string& what, Mesh& mesh) {
        const tinygltf::Mesh& source = model_.meshes[std::size_t(index)];
        mesh.name = source.name.empty() ? "mesh_" + std::to_string(index) : source.name;
        mesh.source_index = index;
        if (source.primitives.empty()) {
            warnings_.add(what + " has no primitives (glTF 2.0 \"Meshes\" requires at least one)");
            return true;
        }
        MeshBuild build;
        for (std::size_t k = 0; k < source.primitives.size(); ++k) {
            const std::string pwhat = what + " primitive " + std::to_string(k);
            if (!import_primitive(source.primitives[k], what, pwhat, build, mesh)) return false;
        }
        if (mesh.indices.empty()) return true;
        detail::finalize_normals(mesh, build.has_normal, what, warnings_);
        return true;
    }

    // Appends the triangles of primitive `prim` (`pwhat`) of mesh `what` to `mesh`, and the
    // vertices they use unless an earlier primitive added them. A primitive that is not
    // made of triangles or has no POSITION is skipped with a warning.
    bool import_primitive(const tinygltf::Primitive& prim, const std::string& what, const std::string& pwhat,
                          MeshBuild& build, Mesh& mesh) {
        const int mode = prim.mode < 0 ? TINYGLTF_MODE_TRIANGLES : prim.mode;
        if (mode == TINYGLTF_MODE_POINTS || mode == TINYGLTF_MODE_LINE || mode == TINYGLTF_MODE_LINE_LOOP ||
            mode == TINYGLTF_MODE_LINE_STRIP) {
            warnings_.add(pwhat + ": " + mode_name(mode) + " is not a triangle topology; skipped");
            return true;
        }
        if (mode != TINYGLTF_MODE_TRIANGLES && mode != TINYGLTF_MODE_TRIANGLE_STRIP &&
            mode != TINYGLTF_MODE_TRIANGLE_FAN) {
            return fail(pwhat + ": invalid mode " + std::to_string(mode) + " (glTF 2.0 \"Meshes\": 0 to 6)");
        }
        const auto pos_it = prim.attributes.find("POSITION");
        if (pos_it == prim.attributes.end()) {
            warnings_.add(pwhat + " has no POSITION attribute; skipped (glTF 2.0 \"Meshes\")");
            return true;
        }
        const auto nrm_it = prim.attributes.find("NORMAL");
        const int pos_acc = pos_it->second;
        const int nrm_acc = nrm_it == prim.attributes.end() ? -1 : nrm_it->second;
        if (prim.material < -1 || prim.material >= int(model_.materials.size())) {
            return fail(pwhat + " refers to material " + std::to_string(prim.material) +
                        ", which does not exist (the file has " + std::to_string(model_.materials.size()) +
                        " materials)");
        }
        const std::uint32_t material = std::uint32_t(prim.material + 1);
        if (!prim.targets.empty() && !build.morph_warned) {
            warnings_.add(what +
                          " has morph targets; they are ignored and the base "
                          "geometry is imported");
            build.morph_warned = true;
        }
        std::uint32_t first = 0, count = 0;
        if (!primitive_vertices(pos_acc, nrm_acc, what, pwhat, build, mesh, first, count)) return false;
        if (!primitive_indices(prim.indices, pwhat, count, build.indices)) return false;
        const std::size_t before = mesh.indices.size();
        if (!emit_triangles(mode, build.indices, first, material, pwhat, mesh)) return false;
        if (mesh.indices.size() == before) {
            warnings_.add(pwhat + " (" + mode_name(mode) + ") has no triangles");
        }
        return true;
    }

    // The vertices of POSITION accessor `pos_acc` with NORMAL accessor `nrm_acc` (-1: none)
    // as the range [first, first + count) of `mesh`: the range an earlier primitive made for
    // the same pair, or a new one, read and checked (finite positions, as many normals as
    // positions, at most 2^32 - 1 vertices in the mesh) and appended with build.has_normal.
    bool primitive_vertices(int pos_acc, int nrm_acc, const std::string& what, const std::string& pwhat,
                            MeshBuild& build, Mesh& mesh, std::uint32_t& first, std::uint32_t& count) {
        const auto key = std::make_pair(pos_acc, nrm_acc);
        if (const auto it = build.ranges.find(key); it != build.ranges.end()) {
            first = it->second.first;
            count = it->second.second;
            return true;
        }
        std::vector<float>& positions = build.positions;
        std::vector<float>& normals = build.normals;
        if (!read_vec3(pos_acc, pwhat, true, positions)) return false;
        const std::size_t n = positions.size() / 3;
        for (std::size_t v = 0; v < n; ++v) {
            const float* p = &positions[3 * v];
            if (!std::isfinite(p[0]) || !std::isfinite(p[1]) || !std::isfinite(p[2])) {
                return fail(pwhat + " POSITION accessor " + std::to_string(pos_acc) + ": vertex " +
                            std::to_string(v) + " is (" + std::to_string(p[0]) + ", " + std::to_string(p[1]) +
                            ", " + std::to_string(p[2]) + "), not finite");
            }
        }
        if (nrm_acc >= 0) {
            if (!read_vec3(nrm_acc, pwhat, false, normals)) return false;
            if (normals.size() != positions.size()) {
                return fail(pwhat + ": NORMAL has " + std::to_string(normals.size() / 3) +
                            " elements but POSITION has " + std::to_string(n) +
                            " (glTF 2.0 \"Meshes\": all attributes have the same count)");
            }
        }
        if (mesh.vertex_count() + n > 0xffffffffull) {
            return fail(what + " has more than 2^32 - 1 vertices");
        }
        first = std::uint32_t(mesh.vertex_count());
        count = std::uint32_t(n);
        build.ranges.emplace(key, std::make_pair(first, count));
        mesh.positions.insert(mesh.positions.end(), positions.begin(), positions.end());
        if (nrm_acc >= 0) {
            mesh.normals.insert(mesh.normals.end(), normals.begin(), normals.end());
        } else {
            mesh.normals.resize(mesh.positions.size(), 0.0f);
        }
        build.has_normal.resize(mesh.vertex_count(), nrm_acc >= 0 ? 1 : 0);
        return true;
    }

    // A primitive's indices into `out`, from accessor `accessor` with each checked to be
    // below `count`, or 0 .. count - 1 when it has none (-1).
    bool primitive_indices(int accessor, const std::string& pwhat, std::uint32_t count,
                           std::vector<std::uint32_t>& out) {
        if (accessor >= 0 || accessor < -1) {
            if (!read_indices(accessor, pwhat, out)) return false;
            for (std::size_t i = 0; i < out.size(); ++i) {
                if (out[i] >= count) {
                    return fail(pwhat + ": index " + std::to_string(out[i]) + " at position " +
                                std::to_string(i) + " is out of range (POSITION has " +
                                std::to_string(count) + " vertices; glTF 2.0 \"Meshes\")");
                }
            }
        } else {
            out.resize(count);
            for (std::uint32_t i = 0; i < count; ++i) out[i] = i;
        }
        return true;
    }

    // Appends to `mesh` the triangles that `indices` (relative to vertex `first`) make in
    // topology `mode` (TRIANGLES, TRIANGLE_STRIP or TRIANGLE_FAN), each of `material`.
    bool emit_triangles(int mode, const std::vector<std::uint32_t>& indices, std::uint32_t first,
                        std::uint32_t material, const std::string& pwhat, Mesh& mesh) {
        auto emit = [&](std::uint32_t a, std::uint32_t b, std::uint32_t c) {
            mesh.indices.push_back(first + a);
            mesh.indices.push_back(first + b);
            mesh.indices.push_back(first + c);
            mesh.triangle_materials.push_back(material);
        };
        const std::size_t m = indices.size();
        if (mode == TINYGLTF_MODE_TRIANGLES) {
            if (m % 3 != 0) {
                return fail(pwhat + ": TRIANGLES with " + std::to_string(m) +
                            " vertices, not a multiple of 3 (glTF 2.0 \"Meshes\")");
            }
            for (std::size_t i = 0; i < m; i += 3) {
                emit(indices[i], indices[i + 1], indices[i + 2]);
            }
            return true;
        }
        // glTF 2.0 "Meshes", topology types: strip p_i = {v_i, v_{i+(1+i%2)},
        // v_{i+(2-i%2)}}, fan p_i = {v_{i+1}, v_{i+2}, v_0}. Triangles repeating an
        // index (strip stitching) are dropped.
        for (std::size_t i = 0; i + 2 < m; ++i) {
            std::uint32_t a, b, c;
            if (mode == TINYGLTF_MODE_TRIANGLE_STRIP) {
                a = indices[i];
                b = indices[i + 1 + i % 2];
                c = indices[i + 2 - i % 2];
            } else {
                a = indices[i + 1];
                b = indices[i + 2];
                c = indices[0];
            }
            if (a != b && b != c && a != c) emit(a, b, c);
        }
        return true;
    }

    const tinygltf::Model& model_;
    std::string file_;
    std::string error_;
    detail::WarningSink warnings_;
    Scene scene_;
    std::vector<std::int64_t> mesh_slot_;  // per glTF mesh: kUnvisited, kSkipped or a Scene index
    bool quantization_ = false;
};

ImportResult failure(std::string_view file, const std::string& what) {
    return {{}, std::string(file) + ": " + what};
}

}  // namespace

ImportResult import_gltf_from_memory(std::span<const std::uint8_t> bytes,
                                     const std::filesystem::path& base_dir, std::string_view display_name) {
    try {
        if (bytes.empty()) return failure(display_name, "file is empty");
        if (bytes.size() > UINT_MAX) {
            return failure(display_name, "file is larger than 4 GiB (not supported)");
        }
        const bool binary = bytes.size() >= 4 && std::memcmp(bytes.data(), "glTF", 4) == 0;
        if (const std::string problem = precheck(bytes, binary); !problem.empty()) {
            return failure(display_name, problem);
        }
        tinygltf::TinyGLTF loader;
        loader.SetImageLoader(&ignore_image, nullptr);
        tinygltf::Model model;
        std::string err, warn;
        const std::string dir = base_dir.empty() ? std::string(".") : base_dir.string();
        const bool ok =
            binary
                ? loader.LoadBinaryFromMemory(&model, &err, &warn, bytes.data(), unsigned(bytes.size()), dir)
                : loader.LoadASCIIFromString(&model, &err, &warn, reinterpret_cast<const char*>(bytes.data()),
                                             unsigned(bytes.size()), dir);
        if (!ok) {
            std::string why = one_line(err);
            if (why.empty()) why = "unknown parse error";
            return failure(display_name,
                           std::string(binary ? "invalid binary glTF (.glb): " : "invalid glTF: ") + why);
        }
        GltfImporter importer(model, std::string(display_name));
        importer.add_parser_messages(err);  // non-fatal complaints land in err too
        importer.add_parser_messages(warn);
        return importer.run();
    } catch (const std::bad_alloc&) {
        return failure(display_name, "out of memory while importing");
    } catch (const std::exception& e) {
        return failure(display_name, std::string("import failed: ") + e.what());
    } catch (...) {
        return failure(display_name, "import failed (unknown exception)");
    }
}

ImportResult import_gltf(const std::filesystem::path& path) {
    std::string name;
    try {
        name = path.string();
        std::uintmax_t size = 0;
        if (const std::string problem = detail::regular_file_size(path, size); !problem.empty())
            return failure(name, problem);
        if (size > UINT_MAX) return failure(name, "file is larger than 4 GiB (not supported)");
        std::vector<std::uint8_t> bytes(static_cast<std::size_t>(size));
        std::ifstream in(path, std::ios::binary);
        if (!in) return failure(name, "cannot open for reading");
        in.read(reinterpret_cast<char*>(bytes.data()), std::streamsize(bytes.size()));
        if (std::size_t(in.gcount()) != bytes.size()) return failure(name, "read error");
        return import_gltf_from_memory(bytes, path.parent_path(), name);
    } catch (const std::bad_alloc&) {
        return failure(name, "out of memory while reading");
    } catch (const std::exception& e) {
        return failure(name, std::string("cannot read: ") + e.what());
    }
}

}  // namespace lsnif::scene
