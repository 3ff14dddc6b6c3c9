// Shared helpers of the lsnif::scene tests: paths, a glTF writer for generated cases, and
// an independent reference for node world transforms (JSON walked with nlohmann-json,
// 4x4 column-major matrices in double, quaternions applied as q v q*), written without
// looking at the importer's code paths.
#pragma once

#include <lsnif/scene/scene.hpp>

#include <doctest/doctest.h>
#include <nlohmann/json.hpp>
#include "../test_data.hpp"

#include <array>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <iterator>
#include <stdexcept>
#include <string>
#include <vector>

namespace scene_test {

namespace fs = std::filesystem;
using json = nlohmann::json;
namespace sc = lsnif::scene;

inline const fs::path kGltf2Dir = LSNIF_ASSIMP_MODELS_DIR "/glTF2";
inline const fs::path kAssimpDir = LSNIF_ASSIMP_MODELS_DIR;
inline const fs::path kCgalMeshDir = LSNIF_SCENE_MESH_DIR;
inline const fs::path kWorkDir = LSNIF_SCENE_WORK_DIR;

// A fresh empty directory under the test work dir.
inline fs::path fresh_dir(const std::string& name) {
    return lsnif::test::fresh_dir(kWorkDir, name);
}

inline std::vector<std::uint8_t> read_bytes(const fs::path& path) {
    std::ifstream in(path, std::ios::binary);
    return {std::istreambuf_iterator<char>(in), std::istreambuf_iterator<char>()};
}

inline void write_bytes(const fs::path& path, const void* data, std::size_t size) {
    std::ofstream out(path, std::ios::binary);
    out.write(static_cast<const char*>(data), std::streamsize(size));
    REQUIRE(out.good());
}

inline void write_text(const fs::path& path, const std::string& text) {
    write_bytes(path, text.data(), text.size());
}

// The JSON of a .gltf, or the JSON chunk of a .glb (glTF 2.0 "Binary glTF Layout").
inline json load_gltf_json(const fs::path& path) {
    const std::vector<std::uint8_t> bytes = read_bytes(path);
    if (bytes.size() >= 20 && std::memcmp(bytes.data(), "glTF", 4) == 0) {
        std::uint32_t length = 0;
        std::memcpy(&length, bytes.data() + 12, 4);
        REQUIRE(20 + std::size_t(length) <= bytes.size());
        return json::parse(bytes.begin() + 20, bytes.begin() + 20 + length);
    }
    return json::parse(bytes.begin(), bytes.end());
}

// ---- independent reference transforms --------------------------------------------------

using Mat4 = std::array<double, 16>;  // column-major, element (r, c) at [4 * c + r]

inline Mat4 mat_identity() {
    return {1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1};
}

inline Mat4 mat_mul(const Mat4& a, const Mat4& b) {
    Mat4 r{};
    for (int c = 0; c < 4; ++c) {
        for (int row = 0; row < 4; ++row) {
            double s = 0;
            for (int k = 0; k < 4; ++k) s += a[4 * k + row] * b[4 * c + k];
            r[4 * c + row] = s;
        }
    }
    return r;
}

// Rotates v by unit quaternion q = (x, y, z, w) as q * (v, 0) * conj(q) (Hamilton products).
inline std::array<double, 3> quat_rotate(const std::array<double, 4>& q, const std::array<double, 3>& v) {
    auto mul = [](const std::array<double, 4>& a, const std::array<double, 4>& b) {
        // (x, y, z, w) layout
        return std::array<double, 4>{a[3] * b[0] + a[0] * b[3] + a[1] * b[2] - a[2] * b[1],
                                     a[3] * b[1] - a[0] * b[2] + a[1] * b[3] + a[2] * b[0],
                                     a[3] * b[2] + a[0] * b[1] - a[1] * b[0] + a[2] * b[3],
                                     a[3] * b[3] - a[0] * b[0] - a[1] * b[1] - a[2] * b[2]};
    };
    const std::array<double, 4> conj = {-q[0], -q[1], -q[2], q[3]};
    const auto r = mul(mul(q, {v[0], v[1], v[2], 0.0}), conj);
    return {r[0], r[1], r[2]};
}

inline Mat4 node_local(const json& node) {
    if (node.contains("matrix")) {
        Mat4 m{};
        for (int i = 0; i < 16; ++i) m[std::size_t(i)] = node["matrix"][std::size_t(i)].get<double>();
        return m;
    }
    std::array<double, 3> t = {0, 0, 0}, s = {1, 1, 1};
    std::array<double, 4> q = {0, 0, 0, 1};
    if (node.contains("translation"))
        for (int i = 0; i < 3; ++i) t[std::size_t(i)] = node["translation"][std::size_t(i)].get<double>();
    if (node.contains("scale"))
        for (int i = 0; i < 3; ++i) s[std::size_t(i)] = node["scale"][std::size_t(i)].get<double>();
    if (node.contains("rotation")) {
        double n = 0;
        for (int i = 0; i < 4; ++i) {
            q[std::size_t(i)] = node["rotation"][std::size_t(i)].get<double>();
            n += q[std::size_t(i)] * q[std::size_t(i)];
        }
        for (auto& x : q) x /= std::sqrt(n);
    }
    // Column c of T*R*S is R applied to the scaled basis vector e_c; column 3 is t.
    Mat4 m{};
    for (int c = 0; c < 3; ++c) {
        std::array<double, 3> e = {0, 0, 0};
        e[std::size_t(c)] = s[std::size_t(c)];
        const auto col = quat_rotate(q, e);
        for (int r = 0; r < 3; ++r) m[std::size_t(4 * c + r)] = col[std::size_t(r)];
    }
    for (int r = 0; r < 3; ++r) m[std::size_t(12 + r)] = t[std::size_t(r)];
    m[15] = 1;
    return m;
}

struct RefInstance {
    int node;
    int mesh;  // glTF mesh index
    Mat4 world;
};

// Every node with a mesh under the selected scene, depth-first, children in order
// (recursive; only used on well-formed files).
inline std::vector<RefInstance> reference_instances(const json& gltf) {
    std::vector<RefInstance> out;
    const json& nodes = gltf["nodes"];
    std::vector<int> roots;
    const int scene = gltf.contains("scene") ? gltf["scene"].get<int>() : 0;
    for (const auto& n : gltf["scenes"][std::size_t(scene)]["nodes"]) roots.push_back(n.get<int>());
    auto visit = [&](auto&& self, int index, const Mat4& parent) -> void {
        const json& node = nodes[std::size_t(index)];
        const Mat4 world = mat_mul(parent, node_local(node));
        if (node.contains("mesh")) out.push_back({index, node["mesh"].get<int>(), world});
        if (node.contains("children")) {
            for (const auto& c : node["children"]) self(self, c.get<int>(), world);
        }
    };
    for (const int r : roots) visit(visit, r, mat_identity());
    return out;
}

// |importer - reference| <= 1e-5 relative to the magnitude of the reference matrix.
inline void check_transform(const sc::Transform& got, const Mat4& ref, const std::string& what) {
    double scale = 1.0;
    for (int r = 0; r < 3; ++r) {
        for (int c = 0; c < 4; ++c) scale = std::max(scale, std::fabs(ref[std::size_t(4 * c + r)]));
    }
    for (int r = 0; r < 3; ++r) {
        for (int c = 0; c < 4; ++c) {
            const double want = ref[std::size_t(4 * c + r)];
            const double have = got[std::size_t(4 * r + c)];
            INFO(what << " element (" << r << ", " << c << "): importer " << have << ", reference " << want);
            CHECK(std::fabs(have - want) <= 1e-5 * scale);
        }
    }
}

// ---- writing glTF files -------------------------------------------------------------------

// A glTF document under construction: JSON plus one binary buffer (buffer 0).
struct GltfDoc {
    json j;
    std::vector<std::uint8_t> bin;

    GltfDoc() {
        j["asset"] = {{"version", "2.0"}, {"generator", "lsnif test_scene"}};
        j["buffers"] = json::array();
        j["bufferViews"] = json::array();
        j["accessors"] = json::array();
        j["meshes"] = json::array();
        j["nodes"] = json::array();
        j["scenes"] = json::array({json{{"nodes", json::array()}}});
        j["scene"] = 0;
    }

    // Appends raw bytes (4-byte aligned) as a new bufferView; returns its index.
    int add_view(const void* data, std::size_t size, std::size_t stride = 0) {
        while (bin.size() % 4) bin.push_back(0);
        const std::size_t offset = bin.size();
        const auto* p = static_cast<const std::uint8_t*>(data);
        bin.insert(bin.end(), p, p + size);
        json view = {{"buffer", 0}, {"byteOffset", offset}, {"byteLength", size}};
        if (stride) view["byteStride"] = stride;
        j["bufferViews"].push_back(view);
        return int(j["bufferViews"].size() - 1);
    }

    int add_accessor(int view, int component_type, std::size_t count, const char* type) {
        j["accessors"].push_back(
            {{"bufferView", view}, {"componentType", component_type}, {"count", count}, {"type", type}});
        return int(j["accessors"].size() - 1);
    }

    int add_positions(const std::vector<float>& xyz) {
        return add_accessor(add_view(xyz.data(), xyz.size() * 4), 5126, xyz.size() / 3, "VEC3");
    }
    int add_indices_u32(const std::vector<std::uint32_t>& idx) {
        return add_accessor(add_view(idx.data(), idx.size() * 4), 5125, idx.size(), "SCALAR");
    }
    int add_indices_u16(const std::vector<std::uint16_t>& idx) {
        return add_accessor(add_view(idx.data(), idx.size() * 2), 5123, idx.size(), "SCALAR");
    }
    int add_indices_u8(const std::vector<std::uint8_t>& idx) {
        return add_accessor(add_view(idx.data(), idx.size()), 5121, idx.size(), "SCALAR");
    }

    // A mesh with the given primitives (JSON objects); returns its index.
    int add_mesh(const json& primitives, const std::string& name = "") {
        json mesh = {{"primitives", primitives}};
        if (!name.empty()) mesh["name"] = name;
        j["meshes"].push_back(mesh);
        return int(j["meshes"].size() - 1);
    }

    int add_node(const json& node, bool root = true) {
        j["nodes"].push_back(node);
        const int index = int(j["nodes"].size() - 1);
        if (root) j["scenes"][0]["nodes"].push_back(index);
        return index;
    }

    // Writes NAME.gltf and NAME.bin into dir; returns the .gltf path.
    fs::path write_gltf(const fs::path& dir, const std::string& name) {
        json doc = j;
        if (doc["buffers"].empty())
            doc["buffers"].push_back({{"byteLength", bin.size()}, {"uri", name + ".bin"}});
        write_bytes(dir / (name + ".bin"), bin.data(), bin.size());
        write_text(dir / (name + ".gltf"), doc.dump(1));
        return dir / (name + ".gltf");
    }

    // The whole document as .glb bytes (glTF 2.0 "Binary glTF Layout").
    std::vector<std::uint8_t> glb_bytes() const {
        json doc = j;
        if (doc["buffers"].empty()) doc["buffers"].push_back({{"byteLength", bin.size()}});
        std::string text = doc.dump();
        while (text.size() % 4) text.push_back(' ');
        std::vector<std::uint8_t> payload = bin;
        while (payload.size() % 4) payload.push_back(0);
        std::vector<std::uint8_t> out;
        auto u32 = [&out](std::uint32_t v) {
            for (int i = 0; i < 4; ++i) out.push_back(std::uint8_t(v >> (8 * i)));
        };
        for (const char c : {'g', 'l', 'T', 'F'}) out.push_back(std::uint8_t(c));
        u32(2);
        u32(std::uint32_t(12 + 8 + text.size() + 8 + payload.size()));
        u32(std::uint32_t(text.size()));
        u32(0x4E4F534Au);  // "JSON"
        out.insert(out.end(), text.begin(), text.end());
        u32(std::uint32_t(payload.size()));
        u32(0x004E4942u);  // "BIN\0"
        out.insert(out.end(), payload.begin(), payload.end());
        return out;
    }

    fs::path write_glb(const fs::path& dir, const std::string& name) {
        const auto bytes = glb_bytes();
        write_bytes(dir / (name + ".glb"), bytes.data(), bytes.size());
        return dir / (name + ".glb");
    }
};

// A regular octahedron centred at the origin (6 vertices, 8 outward CCW triangles).
inline std::vector<float> octahedron_positions() {
    return {1, 0, 0, -1, 0, 0, 0, 1, 0, 0, -1, 0, 0, 0, 1, 0, 0, -1};
}
inline std::vector<std::uint32_t> octahedron_indices() {
    return {0, 2, 4, 2, 1, 4, 1, 3, 4, 3, 0, 4, 2, 0, 5, 1, 2, 5, 3, 1, 5, 0, 3, 5};
}

// Checks what every import must give, and prints the error on failure.
inline void require_ok(const sc::ImportResult& r) {
    INFO("import error: " << r.error);
    REQUIRE(r.ok());
    const std::string problem = sc::check_scene(r.scene);
    INFO("check_scene: " << problem);
    REQUIRE(problem.empty());
}

// Checks a failed import: the message starts with the file name and contains `needle`.
inline void require_error(const sc::ImportResult& r, const std::string& file, const std::string& needle) {
    INFO("error: " << r.error);
    REQUIRE_FALSE(r.ok());
    CHECK(r.error.rfind(file + ": ", 0) == 0);
    CHECK(r.error.find(needle) != std::string::npos);
    CHECK(r.scene.meshes.empty());
    CHECK(r.scene.instances.empty());
}

inline bool has_warning(const sc::Scene& s, const std::string& needle) {
    for (const auto& w : s.warnings) {
        if (w.find(needle) != std::string::npos) return true;
    }
    return false;
}

}  // namespace scene_test
