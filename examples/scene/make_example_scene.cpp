// lsnif_make_example_scene: writes the bundled example scene as a glTF 2.0 binary (.glb).
//
//   lsnif_make_example_scene --out FILE.glb --cgal-data DIR_OR_OFF [--subdivisions N]
//                            [--tubes N] [--segments N] [--seed N]
//   lsnif_make_example_scene --out FILE.glb --hairball-only [--tubes N] [--segments N] [--seed N]
//   lsnif_make_example_scene --out FILE.glb --hard-case NAME [--scale S]
//   lsnif_make_example_scene --out FILE.glb --composition dragons|statues --cgal-data DIR
//   lsnif_make_example_scene --out FILE.glb --composition hairballs
//
// --hard-case writes one case of the hard-geometry suite (hard_cases.hpp,
// docs/failure-modes.md): a mesh named NAME (plus a "floor" mesh for "statue"), scaled by S.
//
// The scene (meters, +Y up, floor top at y = 0) mixes geometry that should stay in an
// ordinary BVH with geometry complex enough for an LSNIF:
//   - a room (floor, back wall, side wall) and four pieces of furniture, each a 12-triangle
//     box mesh with its own node and material;
//   - CGAL's ChineseDragon-10kv (from Debian's libcgal-demo data), Loop-subdivided once to
//     79,976 triangles, 1 m tall, standing on the floor (one instance);
//   - a procedural hairball of 300 thin closed tubes (74,400 triangles), one mesh instanced
//     by three nodes with different translation / rotation about Y / uniform scale.
// The scene graph has one root; some nodes use TRS, others a 4x4 matrix. Output is
// byte-identical across runs (fixed seeds, splitmix64, sorted processing, no trigonometry).
// The file is written to FILE.glb.tmp and renamed, so no half-written FILE.glb remains.
// Exit status: 0 on success, 1 on any error (with one "error: ..." line on stderr).

#include "hard_cases.hpp"
#include "procedural.hpp"

#include <nlohmann/json.hpp>

#include <algorithm>
#include <array>
#include <charconv>
#include <cmath>
#include <cstdint>
#include <cstdio>
#include <cstring>
#include <exception>
#include <filesystem>
#include <fstream>
#include <optional>
#include <string>
#include <string_view>
#include <system_error>
#include <vector>

namespace {

namespace fs = std::filesystem;
namespace ex = lsnif::examples;
using json = nlohmann::ordered_json;

constexpr const char* kCgalMeshName = "ChineseDragon-10kv.off";

// glTF 2.0 constants.
constexpr int kFloat = 5126;
constexpr int kUnsignedInt = 5125;
constexpr int kArrayBuffer = 34962;
constexpr int kElementArrayBuffer = 34963;
constexpr int kTriangles = 4;
constexpr std::uint32_t kGlbMagic = 0x46546C67;   // "glTF"
constexpr std::uint32_t kChunkJson = 0x4E4F534A;  // "JSON"
constexpr std::uint32_t kChunkBin = 0x004E4942;   // "BIN\0"

// ---- small helpers --------------------------------------------------------------------

void put_u32(std::vector<std::uint8_t>& out, std::uint32_t v) {
    for (int i = 0; i < 4; ++i) out.push_back(static_cast<std::uint8_t>(v >> (8 * i)));
}

void put_f32(std::vector<std::uint8_t>& out, float f) {
    std::uint32_t bits = 0;
    std::memcpy(&bits, &f, 4);
    put_u32(out, bits);
}

// A rotation about +Y given by its exact cosine and sine (|(c, s)| = 1), so quaternions and
// matrices come from sqrt only and are the same on every IEEE platform.
struct Yaw {
    double c = 1, s = 0;
};

const double kSqrt3Half = 0.5 * std::sqrt(3.0);
const Yaw kYaw0{1.0, 0.0};
const Yaw kYaw60{0.5, kSqrt3Half};
const Yaw kYaw90{0.0, 1.0};
const Yaw kYaw30{kSqrt3Half, 0.5};
const Yaw kYaw150{-kSqrt3Half, 0.5};
const Yaw kYawMinus150{-kSqrt3Half, -0.5};
const Yaw kYawMinus30{kSqrt3Half, -0.5};
const Yaw kYawMinus120{-0.5, -kSqrt3Half};

// Unit quaternion (x, y, z, w) of the yaw, by the half-angle formulas.
json yaw_quaternion(Yaw r) {
    const double w = std::sqrt(0.5 * (1.0 + r.c));
    const double y = (r.s < 0 ? -1.0 : 1.0) * std::sqrt(0.5 * (1.0 - r.c));
    return json::array({0.0, y, 0.0, w});
}

// A TRS node: translation t, rotation about Y, uniform scale k (identity parts omitted).
json trs_node(const std::string& name, ex::Vec3 t, Yaw r = kYaw0, double k = 1.0) {
    json node = {{"name", name}};
    if (t.x != 0 || t.y != 0 || t.z != 0) node["translation"] = {t.x, t.y, t.z};
    if (r.c != 1.0) node["rotation"] = yaw_quaternion(r);
    if (k != 1.0) node["scale"] = {k, k, k};
    return node;
}

// A matrix node: T * R_y * S(k), column-major as glTF requires.
json matrix_node(const std::string& name, ex::Vec3 t, Yaw r, double k = 1.0) {
    return {{"name", name},
            {"matrix",
             {k * r.c, 0.0, -k * r.s, 0.0,  //
              0.0, k, 0.0, 0.0,             //
              k * r.s, 0.0, k * r.c, 0.0,   //
              t.x, t.y, t.z, 1.0}}};
}

// ---- glTF document under construction --------------------------------------------------

class GltfBuilder {
public:
    GltfBuilder() {
        doc_["asset"] = {{"version", "2.0"}, {"generator", "lsnif_make_example_scene"}};
        doc_["scene"] = 0;
        for (const char* key : {"scenes", "nodes", "meshes", "materials", "accessors", "bufferViews"}) {
            doc_[key] = json::array();
        }
    }

    // A metal/roughness material without textures; returns its index.
    int add_material(const std::string& name, std::array<double, 3> rgb, double metallic, double roughness) {
        doc_["materials"].push_back({{"name", name},
                                     {"pbrMetallicRoughness",
                                      {{"baseColorFactor", {rgb[0], rgb[1], rgb[2], 1.0}},
                                       {"metallicFactor", metallic},
                                       {"roughnessFactor", roughness}}}});
        return int(doc_["materials"].size()) - 1;
    }

    // A mesh with one indexed triangle primitive (positions as float32 with exact min/max,
    // indices as uint32); returns its index.
    int add_mesh(const std::string& name, const ex::TriMesh& mesh, int material) {
        std::vector<float> xyz;
        xyz.reserve(3 * mesh.positions.size());
        float lo[3] = {INFINITY, INFINITY, INFINITY}, hi[3] = {-INFINITY, -INFINITY, -INFINITY};
        for (const ex::Vec3& p : mesh.positions) {
            const float f[3] = {float(p.x), float(p.y), float(p.z)};
            for (int a = 0; a < 3; ++a) {
                xyz.push_back(f[a]);
                lo[a] = std::min(lo[a], f[a]);
                hi[a] = std::max(hi[a], f[a]);
            }
        }
        const std::size_t position_view = begin_view();
        for (float f : xyz) put_f32(bin_, f);
        end_view(position_view, kArrayBuffer);
        const std::size_t index_view = begin_view();
        for (std::uint32_t i : mesh.indices) put_u32(bin_, i);
        end_view(index_view, kElementArrayBuffer);

        json& accessors = doc_["accessors"];
        accessors.push_back({{"bufferView", position_view},
                             {"componentType", kFloat},
                             {"count", mesh.positions.size()},
                             {"type", "VEC3"},
                             {"min", {double(lo[0]), double(lo[1]), double(lo[2])}},
                             {"max", {double(hi[0]), double(hi[1]), double(hi[2])}}});
        const std::size_t position_accessor = accessors.size() - 1;
        accessors.push_back({{"bufferView", index_view},
                             {"componentType", kUnsignedInt},
                             {"count", mesh.indices.size()},
                             {"type", "SCALAR"}});
        const std::size_t index_accessor = accessors.size() - 1;
        doc_["meshes"].push_back({{"name", name},
                                  {"primitives",
                                   {{{"attributes", {{"POSITION", position_accessor}}},
                                     {"indices", index_accessor},
                                     {"material", material},
                                     {"mode", kTriangles}}}}});
        return int(doc_["meshes"].size()) - 1;
    }

    // Appends a node (children are linked with add_child); returns its index.
    int add_node(json node) {
        doc_["nodes"].push_back(std::move(node));
        return int(doc_["nodes"].size()) - 1;
    }

    void add_child(int parent, int child) { doc_["nodes"][std::size_t(parent)]["children"].push_back(child); }

    int add_mesh_node(int parent, json node, int mesh) {
        node["mesh"] = mesh;
        const int index = add_node(std::move(node));
        add_child(parent, index);
        return index;
    }

    void set_root(int node) {
        doc_["scenes"] = json::array({{{"name", "example_scene"}, {"nodes", {node}}}});
    }

    // The complete GLB: 12-byte header, JSON chunk padded with spaces, BIN chunk padded with
    // zeros, all little-endian.
    std::vector<std::uint8_t> glb() const {
        json doc = doc_;
        doc["buffers"] = json::array({{{"byteLength", bin_.size()}}});
        std::string text = doc.dump();
        while (text.size() % 4 != 0) text.push_back(' ');
        std::vector<std::uint8_t> bin = bin_;
        while (bin.size() % 4 != 0) bin.push_back(0);

        std::vector<std::uint8_t> out;
        out.reserve(12 + 8 + text.size() + 8 + bin.size());
        put_u32(out, kGlbMagic);
        put_u32(out, 2);
        put_u32(out, static_cast<std::uint32_t>(12 + 8 + text.size() + 8 + bin.size()));
        put_u32(out, static_cast<std::uint32_t>(text.size()));
        put_u32(out, kChunkJson);
        out.insert(out.end(), text.begin(), text.end());
        put_u32(out, static_cast<std::uint32_t>(bin.size()));
        put_u32(out, kChunkBin);
        out.insert(out.end(), bin.begin(), bin.end());
        return out;
    }

    const json& document() const { return doc_; }

private:
    // Starts a bufferView at the current end of the BIN data (aligned to 4); returns its index.
    std::size_t begin_view() {
        while (bin_.size() % 4 != 0) bin_.push_back(0);
        doc_["bufferViews"].push_back({{"buffer", 0}, {"byteOffset", bin_.size()}});
        return doc_["bufferViews"].size() - 1;
    }

    void end_view(std::size_t view, int target) {
        json& v = doc_["bufferViews"][view];
        v["byteLength"] = bin_.size() - v["byteOffset"].get<std::size_t>();
        v["target"] = target;
    }

    json doc_;
    std::vector<std::uint8_t> bin_;
};

// ---- scene content ----------------------------------------------------------------------

struct Options {
    std::string out;
    std::string cgal_data;
    bool hairball_only = false;
    std::string hard_case;  // non-empty: write this hard-geometry case only
    double scale = 1.0;
    std::optional<int> subdivisions;  // --subdivisions; each scene has its own default
    std::string composition;          // non-empty: write this evaluation composition only
    ex::HairballParams hairball;
};

// Finds a CGAL mesh: `path` itself if it is a file (and `name` is the dragon), else `name`
// under path/data/meshes, path/meshes or path. Returns false with `error` set if none exists.
bool locate_cgal_mesh(const std::string& path, const std::string& name, fs::path& mesh, std::string& error) {
    std::error_code ec;
    if (fs::is_regular_file(path, ec) && name == kCgalMeshName) {
        mesh = path;
        return true;
    }
    if (fs::is_directory(path, ec)) {
        for (const char* sub : {"data/meshes", "meshes", "."}) {
            const fs::path candidate = fs::path(path) / sub / name;
            if (fs::is_regular_file(candidate, ec)) {
                mesh = candidate.lexically_normal();
                return true;
            }
        }
        error =
            "no " + name + " under '" + path + "' (looked in data/meshes/, meshes/ and the directory itself)";
        return false;
    }
    error = "CGAL data '" + path + "' is not " + (name == kCgalMeshName ? "a file or " : "") +
            "a directory (extract data/meshes/" + name +
            " from /usr/share/doc/libcgal-dev/data.tar.gz, package libcgal-demo)";
    return false;
}

// Reads CGAL mesh `name` (locate_cgal_mesh), Loop-subdivides it `subdivisions` times and
// scales it to `height` with its lowest point on y = 0, centred in x and z. Returns false
// with `error` set when it cannot be found or read, has no triangles or is flat in y.
bool load_cgal_mesh(const std::string& path, const std::string& name, int subdivisions, double height,
                    ex::TriMesh& mesh, std::string& error) {
    fs::path file;
    if (!locate_cgal_mesh(path, name, file, error)) return false;
    if (!ex::read_off(file.string(), mesh, error)) return false;
    if (mesh.triangle_count() == 0) {
        error = "'" + file.string() + "' has no triangles";
        return false;
    }
    for (int i = 0; i < subdivisions; ++i) mesh = ex::loop_subdivide(mesh);
    const ex::Bounds b = ex::mesh_bounds(mesh);
    if (!(b.max.y - b.min.y > 0)) {
        error = "'" + file.string() + "' is flat in y";
        return false;
    }
    ex::fit_on_floor(mesh, height);
    return true;
}

// Builds the complete scene into `gltf`. Returns false with `error` set if the CGAL mesh
// cannot be found or read.
bool build_full_scene(const Options& opt, GltfBuilder& gltf, std::string& error) {
    ex::TriMesh dragon;
    if (!load_cgal_mesh(opt.cgal_data, kCgalMeshName, opt.subdivisions.value_or(1), 1.0, dragon, error))
        return false;

    const int m_floor = gltf.add_material("floor_oak", {0.55, 0.38, 0.22}, 0.0, 0.6);
    const int m_wall = gltf.add_material("wall_plaster", {0.85, 0.83, 0.78}, 0.0, 0.9);
    const int m_wood = gltf.add_material("walnut", {0.36, 0.22, 0.13}, 0.0, 0.5);
    const int m_steel = gltf.add_material("painted_steel", {0.30, 0.35, 0.42}, 0.7, 0.35);
    const int m_fabric = gltf.add_material("sofa_fabric", {0.55, 0.12, 0.10}, 0.0, 0.95);
    const int m_jade = gltf.add_material("dragon_jade", {0.25, 0.60, 0.40}, 0.0, 0.3);
    const int m_hair = gltf.add_material("hair", {0.12, 0.08, 0.05}, 0.0, 0.45);

    const int root = gltf.add_node({{"name", "example_scene"}});
    gltf.set_root(root);

    // Room: 6 m x 6 m, 3 m high walls at z = -3 and x = -3; boxes authored in place.
    const int room = gltf.add_node({{"name", "room"}});
    gltf.add_child(root, room);
    gltf.add_mesh_node(room, {{"name", "floor"}},
                       gltf.add_mesh("floor", ex::make_box({-3, -0.1, -3}, {3, 0, 3}), m_floor));
    gltf.add_mesh_node(room, {{"name", "back_wall"}},
                       gltf.add_mesh("back_wall", ex::make_box({-3, 0, -3.1}, {3, 3, -3}), m_wall));
    gltf.add_mesh_node(room, {{"name", "side_wall"}},
                       gltf.add_mesh("side_wall", ex::make_box({-3.1, 0, -3}, {-3, 3, 3}), m_wall));

    // Furniture: a group node with a matrix (90 degrees about Y, then a translation); each
    // piece is a box resting on its local y = 0, placed by a TRS translation computed from
    // the wanted world position w as R^T (w - t).
    const ex::Vec3 group_t{0.25, 0.0, 0.0};
    const Yaw group_r = kYaw90;
    const int furniture = gltf.add_node(matrix_node("furniture", group_t, group_r));
    gltf.add_child(root, furniture);
    const auto to_group = [&](double wx, double wy, double wz) {
        const double dx = wx - group_t.x, dz = wz - group_t.z;
        return ex::Vec3{group_r.c * dx - group_r.s * dz, wy - group_t.y, group_r.s * dx + group_r.c * dz};
    };
    // Sizes are in the group frame: local x runs along world -z, local z along world +x.
    gltf.add_mesh_node(furniture, trs_node("table", to_group(1.0, 0.0, 0.5)),
                       gltf.add_mesh("table", ex::make_box_on_floor(1.4, 0.75, 0.8), m_wood));
    gltf.add_mesh_node(furniture, trs_node("cabinet", to_group(2.3, 0.0, -2.6)),
                       gltf.add_mesh("cabinet", ex::make_box_on_floor(0.6, 1.8, 0.5), m_steel));
    gltf.add_mesh_node(furniture, trs_node("sofa", to_group(-2.4, 0.0, 0.8)),
                       gltf.add_mesh("sofa", ex::make_box_on_floor(2.0, 0.45, 0.9), m_fabric));
    gltf.add_mesh_node(furniture, trs_node("stool", to_group(1.9, 0.0, 1.7), kYaw60),
                       gltf.add_mesh("stool", ex::make_box_on_floor(0.4, 0.5, 0.4), m_wood));

    // The dragon: one TRS instance on the floor.
    gltf.add_mesh_node(root, trs_node("dragon", {-1.0, 0.0, -1.5}, kYawMinus30),
                       gltf.add_mesh("dragon", dragon, m_jade));

    // The hairball: one mesh (diameter 1), three instances (two TRS, one matrix).
    const int hair = gltf.add_mesh("hairball", ex::make_hairball(opt.hairball), m_hair);
    const int hairballs = gltf.add_node({{"name", "hairballs"}});
    gltf.add_child(root, hairballs);
    gltf.add_mesh_node(hairballs, trs_node("hairball_on_table", {1.0, 0.75 + 0.4, 0.5}, kYaw60, 0.8), hair);
    gltf.add_mesh_node(hairballs, trs_node("hairball_on_cabinet", {2.3, 1.8 + 0.25, -2.6}, kYawMinus120, 0.5),
                       hair);
    gltf.add_mesh_node(hairballs, matrix_node("hairball_on_floor", {0.4, 0.3, -1.9}, kYaw90, 0.6), hair);
    return true;
}

// The compositions `lsnif eval` measures (docs/eval.md "Scenes like the paper's"), built
// from CGAL's meshes with floors that end just beyond the objects, so eval's default camera
// (framing the scene's bounds) is filled by them:
//   dragons: the dragon Loop-subdivided (three times unless --subdivisions says otherwise:
//            1,279,616 triangles), 1 m tall, three instances side by side, the middle one
//            set back, each turned differently;
//   statues: armadillo, bunny, bear and lion, 0.8 m tall, each on a 0.5 m pedestal (one
//            mesh, four instances), in a row;
//   hairballs: four procedural hairballs (no CGAL data), below.
bool build_composition(const Options& opt, GltfBuilder& gltf, std::string& error) {
    const int m_floor = gltf.add_material("floor_stone", {0.55, 0.55, 0.52}, 0.0, 0.7);
    const int root = gltf.add_node({{"name", opt.composition}});
    gltf.set_root(root);
    if (opt.composition == "dragons") {
        ex::TriMesh dragon;
        const int steps = opt.subdivisions.value_or(3);
        if (!load_cgal_mesh(opt.cgal_data, kCgalMeshName, steps, 1.0, dragon, error)) return false;
        const int m_jade = gltf.add_material("dragon_jade", {0.25, 0.60, 0.40}, 0.0, 0.3);
        const int mesh = gltf.add_mesh("dragon", dragon, m_jade);
        gltf.add_mesh_node(root, trs_node("dragon_left", {-0.95, 0.0, 0.0}, kYawMinus30), mesh);
        gltf.add_mesh_node(root, trs_node("dragon_middle", {0.0, 0.0, -0.3}, kYaw0), mesh);
        gltf.add_mesh_node(root, trs_node("dragon_right", {0.95, 0.0, 0.0}, kYaw30), mesh);
        gltf.add_mesh_node(
            root, {{"name", "floor"}},
            gltf.add_mesh("floor", ex::make_box({-1.7, -0.05, -1.0}, {1.7, 0.0, 0.8}), m_floor));
        return true;
    }
    if (opt.composition == "statues") {
        const int steps = opt.subdivisions.value_or(0);
        const int m_stone = gltf.add_material("pedestal_stone", {0.75, 0.73, 0.70}, 0.0, 0.8);
        const int pedestal = gltf.add_mesh("pedestal", ex::make_box_on_floor(0.5, 0.5, 0.5), m_stone);
        // Turned to face the camera (+z) a little from either side: the armadillo and the
        // bear are modelled facing -z.
        const char* statues[] = {"armadillo", "bunny00", "bear", "lion"};
        const Yaw turn[] = {kYawMinus150, kYaw30, kYaw150, kYawMinus30};
        const double x0 = -1.65, dx = 1.1;
        for (int k = 0; k < 4; ++k) {
            ex::TriMesh mesh;
            const std::string file = std::string(statues[k]) + ".off";
            if (!load_cgal_mesh(opt.cgal_data, file, steps, 0.8, mesh, error)) return false;
            const int material = gltf.add_material(std::string(statues[k]) + "_bronze",
                                                   {0.55 + 0.1 * k, 0.42, 0.25 + 0.08 * k}, 0.0, 0.4);
            const double x = x0 + dx * k;
            gltf.add_mesh_node(root, trs_node(std::string("pedestal_") + statues[k], {x, 0.0, 0.0}),
                               pedestal);
            gltf.add_mesh_node(root, trs_node(statues[k], {x, 0.5, 0.0}, turn[k]),
                               gltf.add_mesh(statues[k], mesh, material));
        }
        gltf.add_mesh_node(
            root, {{"name", "floor"}},
            gltf.add_mesh("floor", ex::make_box({-2.4, -0.05, -0.8}, {2.4, 0.0, 0.8}), m_floor));
        return true;
    }
    if (opt.composition == "hairballs") {
        // Four procedural hairballs of different densities and curves, 1,117,600 triangles in
        // all (like the LSNIF paper's HAIRBALLS scene: thin, repeated geometry filling the
        // frame), 0.8 m across, in a row on a floor, alternately set back.
        struct Ball {
            int tubes, segments;
            std::uint64_t seed;
            ex::Vec3 at;
            Yaw turn;
        };
        const Ball balls[] = {{1000, 24, 0x4A11B0A1ull, {-1.35, 0.4, 0.0}, kYaw30},
                              {900, 24, 0x4A11B0A2ull, {-0.45, 0.4, -0.35}, kYaw0},
                              {1100, 22, 0x4A11B0A3ull, {0.45, 0.4, 0.0}, kYawMinus30},
                              {800, 26, 0x4A11B0A4ull, {1.35, 0.4, -0.35}, kYaw60}};
        const std::array<double, 3> hair[] = {
            {0.12, 0.08, 0.05}, {0.55, 0.35, 0.15}, {0.30, 0.12, 0.08}, {0.70, 0.62, 0.45}};
        for (int k = 0; k < 4; ++k) {
            ex::HairballParams p = opt.hairball;
            p.tubes = balls[k].tubes;
            p.segments = balls[k].segments;
            p.seed = balls[k].seed;
            const std::string name = "hairball_" + std::to_string(k + 1);
            const int material = gltf.add_material(name + "_hair", hair[k], 0.0, 0.45);
            gltf.add_mesh_node(root, trs_node(name, balls[k].at, balls[k].turn, 0.8),
                               gltf.add_mesh(name, ex::make_hairball(p), material));
        }
        gltf.add_mesh_node(
            root, {{"name", "floor"}},
            gltf.add_mesh("floor", ex::make_box({-2.0, -0.05, -1.0}, {2.0, 0.0, 0.7}), m_floor));
        return true;
    }
    error = "unknown --composition '" + opt.composition + "'; one of: dragons statues hairballs";
    return false;
}

// Only the hairball mesh, once, under a root node.
void build_hairball_scene(const Options& opt, GltfBuilder& gltf) {
    const int m_hair = gltf.add_material("hair", {0.12, 0.08, 0.05}, 0.0, 0.45);
    const int root = gltf.add_node({{"name", "hairball_scene"}});
    gltf.set_root(root);
    gltf.add_mesh_node(root, {{"name", "hairball"}},
                       gltf.add_mesh("hairball", ex::make_hairball(opt.hairball), m_hair));
}

// One case of the hard-geometry suite under a root node. False for an unknown case.
bool build_hard_case(const Options& opt, GltfBuilder& gltf, std::string& error) {
    ex::TriMesh mesh, floor;
    if (!ex::make_hard_case(opt.hard_case, opt.scale, mesh, floor)) {
        error = "unknown --hard-case '" + opt.hard_case + "'; one of:";
        for (const auto& n : ex::hard_case_names()) error += " " + n;
        return false;
    }
    const int m_obj = gltf.add_material("object", {0.6, 0.5, 0.3}, 0.0, 0.5);
    const int root = gltf.add_node({{"name", opt.hard_case + "_case"}});
    gltf.set_root(root);
    gltf.add_mesh_node(root, {{"name", opt.hard_case}}, gltf.add_mesh(opt.hard_case, mesh, m_obj));
    if (!floor.positions.empty()) {
        const int m_floor = gltf.add_material("floor", {0.5, 0.5, 0.5}, 0.0, 0.8);
        gltf.add_mesh_node(root, {{"name", "floor"}}, gltf.add_mesh("floor", floor, m_floor));
    }
    return true;
}

// Writes `bytes` to `path` through `path`.tmp and a rename. Returns false with `error` set
// (and no file left at either name) on failure.
bool write_atomically(const fs::path& path, const std::vector<std::uint8_t>& bytes, std::string& error) {
    const fs::path tmp = fs::path(path.string() + ".tmp");
    {
        std::ofstream out(tmp, std::ios::binary | std::ios::trunc);
        if (!out) {
            error = "cannot write '" + tmp.string() + "'";
            return false;
        }
        out.write(reinterpret_cast<const char*>(bytes.data()), std::streamsize(bytes.size()));
        out.close();
        if (!out) {
            std::error_code ignored;
            fs::remove(tmp, ignored);
            error = "failed writing '" + tmp.string() + "'";
            return false;
        }
    }
    std::error_code ec;
    fs::rename(tmp, path, ec);
    if (ec) {
        std::error_code ignored;
        fs::remove(tmp, ignored);
        error = "cannot rename '" + tmp.string() + "' to '" + path.string() + "': " + ec.message();
        return false;
    }
    return true;
}

// One line per mesh: vertices, triangles, and how many nodes reference it.
void print_stats(const json& doc, const fs::path& out, std::size_t bytes) {
    std::size_t total_instances = 0, total_triangles = 0;
    for (std::size_t m = 0; m < doc["meshes"].size(); ++m) {
        const json& prim = doc["meshes"][m]["primitives"][0];
        const std::size_t vertices =
            doc["accessors"][prim["attributes"]["POSITION"].get<std::size_t>()]["count"];
        const std::size_t triangles =
            doc["accessors"][prim["indices"].get<std::size_t>()]["count"].get<std::size_t>() / 3;
        std::size_t instances = 0;
        for (const json& node : doc["nodes"]) instances += node.contains("mesh") && node["mesh"] == m;
        total_instances += instances;
        total_triangles += instances * triangles;
        std::printf("mesh %-10s %7zu vertices %7zu triangles  x%zu\n",
                    doc["meshes"][m]["name"].get<std::string>().c_str(), vertices, triangles, instances);
    }
    std::printf("%zu meshes, %zu instances, %zu instanced triangles, %zu nodes\n", doc["meshes"].size(),
                total_instances, total_triangles, doc["nodes"].size());
    std::printf("wrote %s (%zu bytes)\n", out.string().c_str(), bytes);
}

void print_usage(std::FILE* to) {
    std::fprintf(
        to,
        "usage: lsnif_make_example_scene --out FILE.glb --cgal-data DIR_OR_OFF [options]\n"
        "       lsnif_make_example_scene --out FILE.glb --hairball-only [options]\n"
        "       lsnif_make_example_scene --out FILE.glb --hard-case NAME [--scale S]\n"
        "       lsnif_make_example_scene --out FILE.glb --composition dragons|statues --cgal-data DIR\n"
        "       lsnif_make_example_scene --out FILE.glb --composition hairballs\n"
        "  --cgal-data PATH    directory holding data/meshes/%s (from libcgal-demo's\n"
        "                      data.tar.gz), or the .off file itself\n"
        "  --hairball-only     write only the hairball mesh (no CGAL data needed)\n"
        "  --hard-case NAME    write one hard-geometry case (hairball, cards, cloth, lattice,\n"
        "                      statue, flat, blob, triangle; no CGAL data needed)\n"
        "  --scale S           scale of the hard case (default 1; 1e-6..1e7)\n"
        "  --composition NAME  write an evaluation composition: dragons (three Loop x3 CGAL\n"
        "                      dragons on a floor), statues (four CGAL meshes on pedestals)\n"
        "                      or hairballs (four procedural hairballs, 1.1 M triangles;\n"
        "                      no --cgal-data needed)\n"
        "  --subdivisions N    Loop subdivision steps of the CGAL mesh (0..3, default 1;\n"
        "                      dragons 3, statues 0)\n"
        "  --tubes N           hairball tubes (1..100000, default 300)\n"
        "  --segments N        segments per tube (1..1000, default 20)\n"
        "  --seed N            hairball seed (default %llu)\n",
        kCgalMeshName, static_cast<unsigned long long>(ex::HairballParams{}.seed));
}

// Parses an integer in [lo, hi]; nullopt if malformed or out of range.
template <typename T>
std::optional<T> parse_int(std::string_view text, T lo, T hi) {
    T v{};
    const auto [end, ec] = std::from_chars(text.data(), text.data() + text.size(), v);
    if (ec != std::errc{} || end != text.data() + text.size() || v < lo || v > hi) return std::nullopt;
    return v;
}

// Fills `opt` from argv. Returns false with `error` set on a usage error.
bool parse_args(int argc, char** argv, Options& opt, bool& help, std::string& error) {
    for (int i = 1; i < argc; ++i) {
        const std::string_view arg = argv[i];
        const auto value = [&](std::string_view& v) {
            if (i + 1 >= argc) {
                error = std::string(arg) + " needs a value";
                return false;
            }
            v = argv[++i];
            return true;
        };
        std::string_view v;
        if (arg == "--help" || arg == "-h") {
            help = true;
        } else if (arg == "--hairball-only") {
            opt.hairball_only = true;
        } else if (arg == "--composition") {
            if (!value(v)) return false;
            opt.composition = std::string(v);
        } else if (arg == "--hard-case") {
            if (!value(v)) return false;
            opt.hard_case = std::string(v);
        } else if (arg == "--scale") {
            if (!value(v)) return false;
            double x = 0;
            const auto [end, ec] = std::from_chars(v.data(), v.data() + v.size(), x);
            if (ec != std::errc() || end != v.data() + v.size() || !(x >= 1e-6 && x <= 1e7)) {
                error = "bad value '" + std::string(v) + "' for --scale (a number in [1e-6, 1e7])";
                return false;
            }
            opt.scale = x;
        } else if (arg == "--out" || arg == "--cgal-data") {
            if (!value(v)) return false;
            (arg == "--out" ? opt.out : opt.cgal_data) = std::string(v);
        } else if (arg == "--subdivisions" || arg == "--tubes" || arg == "--segments") {
            if (!value(v)) return false;
            const int hi = arg == "--subdivisions" ? 3 : arg == "--tubes" ? 100000 : 1000;
            const auto n = parse_int<int>(v, arg == "--subdivisions" ? 0 : 1, hi);
            if (!n) {
                error = "bad value '" + std::string(v) + "' for " + std::string(arg);
                return false;
            }
            if (arg == "--subdivisions")
                opt.subdivisions = *n;
            else
                (arg == "--tubes" ? opt.hairball.tubes : opt.hairball.segments) = *n;
        } else if (arg == "--seed") {
            if (!value(v)) return false;
            const auto n = parse_int<std::uint64_t>(v, 0, UINT64_MAX);
            if (!n) {
                error = "bad value '" + std::string(v) + "' for --seed";
                return false;
            }
            opt.hairball.seed = *n;
        } else {
            error = "unknown argument '" + std::string(arg) + "' (see --help)";
            return false;
        }
    }
    if (help) return true;
    if (opt.out.empty()) {
        error = "--out FILE.glb is required";
        return false;
    }
    if (!opt.hairball_only && opt.hard_case.empty() && opt.cgal_data.empty() &&
        opt.composition != "hairballs") {
        error = opt.composition.empty() ? "--cgal-data PATH is required (or --hairball-only)"
                                        : "--composition needs --cgal-data DIR (libcgal-demo's data)";
        return false;
    }
    return true;
}

}  // namespace

int main(int argc, char** argv) {
    Options opt;
    bool help = false;
    std::string error;
    if (!parse_args(argc, argv, opt, help, error)) {
        std::fprintf(stderr, "error: %s\n", error.c_str());
        return 1;
    }
    if (help) {
        print_usage(stdout);
        return 0;
    }
    try {
        GltfBuilder gltf;
        if (!opt.composition.empty()) {
            if (!build_composition(opt, gltf, error)) {
                std::fprintf(stderr, "error: %s\n", error.c_str());
                return 1;
            }
        } else if (!opt.hard_case.empty()) {
            if (!build_hard_case(opt, gltf, error)) {
                std::fprintf(stderr, "error: %s\n", error.c_str());
                return 1;
            }
        } else if (opt.hairball_only) {
            build_hairball_scene(opt, gltf);
        } else if (!build_full_scene(opt, gltf, error)) {
            std::fprintf(stderr, "error: %s\n", error.c_str());
            return 1;
        }
        const std::vector<std::uint8_t> bytes = gltf.glb();
        if (bytes.size() > UINT32_MAX) {
            std::fprintf(stderr, "error: scene too large for GLB (%zu bytes)\n", bytes.size());
            return 1;
        }
        if (!write_atomically(opt.out, bytes, error)) {
            std::fprintf(stderr, "error: %s\n", error.c_str());
            return 1;
        }
        print_stats(gltf.document(), opt.out, bytes.size());
    } catch (const std::exception& e) {  // out of memory, JSON misuse: report, never crash
        std::fprintf(stderr, "error: %s\n", e.what());
        return 1;
    }
    return 0;
}
