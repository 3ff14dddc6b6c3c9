// Tests of the example scene generator (examples/scene): the procedural generators as
// functions (splitmix64, boxes, tubes, Loop subdivision, OFF reading), and the program as a
// process: the .glb it writes is parsed here independently (GLB container by hand, JSON
// with nlohmann-json) and checked for structure, bounds, content, placement, determinism
// and error handling.
#include "procedural.hpp"

#include <doctest/doctest.h>
#include <nlohmann/json.hpp>
#include "../test_data.hpp"

#include <sys/wait.h>

#include <array>
#include <cmath>
#include <cstdint>
#include <cstdlib>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <iterator>
#include <map>
#include <set>
#include <string>
#include <utility>
#include <vector>

namespace {

namespace fs = std::filesystem;
namespace ex = lsnif::examples;
using json = nlohmann::json;

const fs::path kGenerator = LSNIF_EXAMPLE_GENERATOR;
const fs::path kCgalDir = LSNIF_EXAMPLE_CGAL_DIR;
const fs::path kBuiltScene = LSNIF_EXAMPLE_SCENE_GLB;
const fs::path kWorkDir = LSNIF_EXAMPLE_WORK_DIR;

fs::path fresh_dir(const std::string& name) {
    return lsnif::test::fresh_dir(kWorkDir, name);
}

std::vector<std::uint8_t> read_bytes(const fs::path& path) {
    std::ifstream in(path, std::ios::binary);
    REQUIRE_MESSAGE(in.good(), "cannot read ", path.string());
    return {std::istreambuf_iterator<char>(in), std::istreambuf_iterator<char>()};
}

std::string read_text(const fs::path& path) {
    const std::vector<std::uint8_t> b = read_bytes(path);
    return {b.begin(), b.end()};
}

void write_text(const fs::path& path, const std::string& text) {
    std::ofstream out(path, std::ios::binary);
    out << text;
    REQUIRE(out.good());
}

// `p` in single quotes for /bin/sh (test paths contain no quotes).
std::string quoted(const fs::path& p) {
    std::string s(1, '\'');
    s += p.string();
    s += '\'';
    return s;
}

std::string q(const fs::path& p) {
    return quoted(p);
}

struct RunResult {
    int exit_code = -1;
    std::string out, err;
};

// Runs the generator with `args` (already shell-quoted where needed), capturing output.
RunResult run_generator(const std::string& args, const fs::path& dir) {
    const fs::path out = dir / "stdout.txt", err = dir / "stderr.txt";
    std::string cmd = quoted(kGenerator);  // appended piecewise (GCC 12 -Wrestrict false positive)
    cmd += ' ';
    cmd += args;
    cmd += " >";
    cmd += quoted(out);
    cmd += " 2>";
    cmd += quoted(err);
    const int status = std::system(cmd.c_str());
    RunResult r;
    r.exit_code = (status != -1 && WIFEXITED(status)) ? WEXITSTATUS(status) : -1;
    r.out = read_text(out);
    r.err = read_text(err);
    return r;
}

// ---- independent GLB parsing -----------------------------------------------------------

std::uint32_t le32(const std::vector<std::uint8_t>& b, std::size_t at) {
    return std::uint32_t(b[at]) | std::uint32_t(b[at + 1]) << 8 | std::uint32_t(b[at + 2]) << 16 |
           std::uint32_t(b[at + 3]) << 24;
}

float le_f32(const std::vector<std::uint8_t>& b, std::size_t at) {
    const std::uint32_t bits = le32(b, at);
    float f;
    std::memcpy(&f, &bits, 4);
    return f;
}

struct Glb {
    json doc;
    std::vector<std::uint8_t> bin;
};

// Checks the binary glTF container ("Binary glTF Layout" of the glTF 2.0 spec) and returns
// its JSON and BIN chunk.
Glb parse_glb(const std::vector<std::uint8_t>& b) {
    REQUIRE(b.size() >= 12 + 8);
    REQUIRE(std::memcmp(b.data(), "glTF", 4) == 0);
    CHECK(le32(b, 4) == 2);
    REQUIRE(le32(b, 8) == b.size());
    REQUIRE(b.size() % 4 == 0);
    const std::size_t json_length = le32(b, 12);
    CHECK(le32(b, 16) == 0x4E4F534Au);  // "JSON"
    CHECK(json_length % 4 == 0);
    REQUIRE(20 + json_length + 8 <= b.size());
    const std::size_t bin_at = 20 + json_length;
    const std::size_t bin_length = le32(b, bin_at);
    CHECK(le32(b, bin_at + 4) == 0x004E4942u);  // "BIN\0"
    CHECK(bin_length % 4 == 0);
    REQUIRE(bin_at + 8 + bin_length == b.size());  // exactly two chunks
    // JSON padding is spaces (trailing whitespace is valid JSON).
    const std::string text(b.begin() + 20, b.begin() + std::ptrdiff_t(bin_at));
    const auto last = text.find_last_not_of(' ');
    REQUIRE(last != std::string::npos);
    CHECK(text.size() - last - 1 < 4);
    Glb glb;
    glb.doc = json::parse(text);
    glb.bin.assign(b.begin() + std::ptrdiff_t(bin_at + 8), b.end());
    return glb;
}

std::size_t component_size(int type) {
    switch (type) {
        case 5120:
        case 5121: return 1;
        case 5122:
        case 5123: return 2;
        case 5125:
        case 5126: return 4;
        default: return 0;
    }
}

std::size_t component_count(const std::string& type) {
    static const std::map<std::string, std::size_t> counts{
        {"SCALAR", 1}, {"VEC2", 2}, {"VEC3", 3}, {"VEC4", 4}, {"MAT2", 4}, {"MAT3", 9}, {"MAT4", 16}};
    const auto it = counts.find(type);
    return it == counts.end() ? 0 : it->second;
}

// Checks buffers, bufferViews and accessors lie inside the BIN chunk, properly aligned.
void check_binary_layout(const Glb& glb) {
    const json& doc = glb.doc;
    REQUIRE(doc.at("buffers").size() == 1);
    const json& buffer = doc["buffers"][0];
    CHECK_FALSE(buffer.contains("uri"));
    const std::size_t buffer_length = buffer.at("byteLength");
    REQUIRE(buffer_length <= glb.bin.size());
    CHECK(glb.bin.size() - buffer_length < 4);
    for (const json& view : doc.at("bufferViews")) {
        CHECK(view.at("buffer") == 0);
        const std::size_t offset = view.value("byteOffset", std::size_t(0));
        CHECK(offset % 4 == 0);
        CHECK(view.at("byteLength").get<std::size_t>() > 0);
        CHECK(offset + view["byteLength"].get<std::size_t>() <= buffer_length);
        CHECK_FALSE(view.contains("byteStride"));
    }
    for (const json& a : doc.at("accessors")) {
        const std::size_t v = a.at("bufferView");
        REQUIRE(v < doc["bufferViews"].size());
        const std::size_t elem = component_size(a.at("componentType")) * component_count(a.at("type"));
        REQUIRE(elem > 0);
        const std::size_t count = a.at("count");
        REQUIRE(count > 0);
        const std::size_t offset = a.value("byteOffset", std::size_t(0));
        CHECK(offset % component_size(a["componentType"]) == 0);
        CHECK(offset + count * elem <= doc["bufferViews"][v]["byteLength"].get<std::size_t>());
    }
}

// Float positions of a VEC3 float accessor.
std::vector<std::array<float, 3>> positions_of(const Glb& glb, std::size_t accessor) {
    const json& a = glb.doc["accessors"][accessor];
    REQUIRE(a["componentType"] == 5126);
    REQUIRE(a["type"] == "VEC3");
    const json& view = glb.doc["bufferViews"][a["bufferView"].get<std::size_t>()];
    const std::size_t at = view.value("byteOffset", std::size_t(0)) + a.value("byteOffset", std::size_t(0));
    std::vector<std::array<float, 3>> out(a["count"].get<std::size_t>());
    for (std::size_t i = 0; i < out.size(); ++i) {
        for (std::size_t k = 0; k < 3; ++k) out[i][k] = le_f32(glb.bin, at + 12 * i + 4 * k);
    }
    return out;
}

std::vector<std::uint32_t> indices_of(const Glb& glb, std::size_t accessor) {
    const json& a = glb.doc["accessors"][accessor];
    REQUIRE(a["componentType"] == 5125);
    REQUIRE(a["type"] == "SCALAR");
    const json& view = glb.doc["bufferViews"][a["bufferView"].get<std::size_t>()];
    const std::size_t at = view.value("byteOffset", std::size_t(0)) + a.value("byteOffset", std::size_t(0));
    std::vector<std::uint32_t> out(a["count"].get<std::size_t>());
    for (std::size_t i = 0; i < out.size(); ++i) out[i] = le32(glb.bin, at + 4 * i);
    return out;
}

// Per mesh name: vertex and triangle counts, after checking every primitive (triangles,
// uint32 indices in range, a material, finite positions inside tight accessor min/max).
struct MeshInfo {
    std::size_t vertices = 0, triangles = 0;
    std::array<double, 3> min{}, max{};
};

std::map<std::string, MeshInfo> check_meshes(const Glb& glb) {
    const json& doc = glb.doc;
    std::map<std::string, MeshInfo> info;
    for (const json& mesh : doc.at("meshes")) {
        const std::string name = mesh.at("name");
        CAPTURE(name);
        REQUIRE(mesh.at("primitives").size() == 1);
        const json& prim = mesh["primitives"][0];
        CHECK(prim.value("mode", 4) == 4);
        REQUIRE(prim.contains("material"));
        CHECK(prim["material"].get<std::size_t>() < doc.at("materials").size());
        const std::size_t pa = prim.at("attributes").at("POSITION");
        const json& acc = doc["accessors"][pa];
        REQUIRE(acc.contains("min"));
        REQUIRE(acc.contains("max"));
        const auto positions = positions_of(glb, pa);
        std::array<float, 3> lo{INFINITY, INFINITY, INFINITY}, hi{-INFINITY, -INFINITY, -INFINITY};
        bool finite = true, inside = true;
        for (const auto& p : positions) {
            for (std::size_t k = 0; k < 3; ++k) {
                finite = finite && std::isfinite(p[k]);
                inside = inside && p[k] >= acc["min"][k].get<double>() && p[k] <= acc["max"][k].get<double>();
                lo[k] = std::min(lo[k], p[k]);
                hi[k] = std::max(hi[k], p[k]);
            }
        }
        CHECK(finite);
        CHECK(inside);
        for (std::size_t k = 0; k < 3; ++k) {  // min/max are the exact bounds of the data
            CHECK(double(lo[k]) == acc["min"][k].get<double>());
            CHECK(double(hi[k]) == acc["max"][k].get<double>());
        }
        const auto indices = indices_of(glb, prim.at("indices"));
        REQUIRE(indices.size() % 3 == 0);
        bool in_range = true;
        for (std::uint32_t i : indices) in_range = in_range && i < positions.size();
        CHECK(in_range);
        CHECK(info.count(name) == 0);
        info[name] = {positions.size(), indices.size() / 3, {lo[0], lo[1], lo[2]}, {hi[0], hi[1], hi[2]}};
    }
    return info;
}

// ---- independent node transforms (column-major 4x4, double) ---------------------------

using Mat4 = std::array<double, 16>;

Mat4 mat_mul(const Mat4& a, const Mat4& b) {
    Mat4 r{};
    for (int c = 0; c < 4; ++c)
        for (int row = 0; row < 4; ++row)
            for (int k = 0; k < 4; ++k) r[4 * c + row] += a[4 * k + row] * b[4 * c + k];
    return r;
}

Mat4 local_matrix(const json& node) {
    if (node.contains("matrix")) {
        Mat4 m{};
        for (int i = 0; i < 16; ++i) m[i] = node["matrix"][i].get<double>();
        return m;
    }
    const json t = node.value("translation", json::array({0.0, 0.0, 0.0}));
    const json r = node.value("rotation", json::array({0.0, 0.0, 0.0, 1.0}));
    const json s = node.value("scale", json::array({1.0, 1.0, 1.0}));
    const double x = r[0], y = r[1], z = r[2], w = r[3];
    // Rotation matrix of the unit quaternion, columns scaled by s.
    const double rot[3][3] = {{1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)},
                              {2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)},
                              {2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)}};
    Mat4 m{};
    for (int c = 0; c < 3; ++c)
        for (int row = 0; row < 3; ++row) m[4 * c + row] = rot[row][c] * s[c].get<double>();
    for (int row = 0; row < 3; ++row) m[12 + row] = t[row].get<double>();
    m[15] = 1;
    return m;
}

struct Instance {
    std::string node, mesh;
    Mat4 world;
};

// Walks the scene graph from the default scene's roots, checking it is a tree over all nodes.
std::vector<Instance> instances_of(const json& doc) {
    std::vector<Instance> out;
    std::vector<int> visits(doc.at("nodes").size(), 0);
    const auto walk = [&](auto&& self, std::size_t i, const Mat4& parent) -> void {
        REQUIRE(i < visits.size());
        REQUIRE(++visits[i] == 1);  // no node reached twice: a tree, no cycles
        const json& node = doc["nodes"][i];
        const Mat4 world = mat_mul(parent, local_matrix(node));
        if (node.contains("mesh")) {
            out.push_back({node.at("name"), doc["meshes"][node["mesh"].get<std::size_t>()]["name"], world});
        }
        for (const json& c : node.value("children", json::array())) self(self, c.get<std::size_t>(), world);
    };
    const json& scene = doc.at("scenes").at(doc.value("scene", 0));
    for (const json& r : scene.at("nodes"))
        walk(walk, r.get<std::size_t>(), Mat4{1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1});
    for (std::size_t i = 0; i < visits.size(); ++i)
        CHECK_MESSAGE(visits[i] == 1, "node ", i, " is not in the scene");
    return out;
}

// World-space bounds of an instance: the 8 transformed corners of the mesh's local box.
std::pair<std::array<double, 3>, std::array<double, 3>> world_bounds(const MeshInfo& mesh, const Mat4& m) {
    std::array<double, 3> lo{INFINITY, INFINITY, INFINITY}, hi{-INFINITY, -INFINITY, -INFINITY};
    for (int corner = 0; corner < 8; ++corner) {
        const double p[3] = {(corner & 1) ? mesh.max[0] : mesh.min[0],
                             (corner & 2) ? mesh.max[1] : mesh.min[1],
                             (corner & 4) ? mesh.max[2] : mesh.min[2]};
        for (int r = 0; r < 3; ++r) {
            const double v = m[r] * p[0] + m[4 + r] * p[1] + m[8 + r] * p[2] + m[12 + r];
            lo[r] = std::min(lo[r], v);
            hi[r] = std::max(hi[r], v);
        }
    }
    return {lo, hi};
}

// ---- mesh topology helpers for the generator unit tests --------------------------------

// True if every directed edge occurs once and its reverse once: closed, 2-manifold along
// edges, consistently oriented.
bool closed_and_oriented(const ex::TriMesh& m) {
    std::map<std::pair<std::uint32_t, std::uint32_t>, int> directed;
    for (std::size_t t = 0; t < m.triangle_count(); ++t) {
        for (int k = 0; k < 3; ++k) {
            ++directed[{m.indices[3 * t + k], m.indices[3 * t + (k + 1) % 3]}];
        }
    }
    for (const auto& [e, n] : directed) {
        if (n != 1) return false;
        const auto rev = directed.find({e.second, e.first});
        if (rev == directed.end() || rev->second != 1) return false;
    }
    return true;
}

double signed_volume(const ex::TriMesh& m) {
    double v = 0;
    for (std::size_t t = 0; t < m.triangle_count(); ++t) {
        const ex::Vec3 a = m.positions[m.indices[3 * t]], b = m.positions[m.indices[3 * t + 1]],
                       c = m.positions[m.indices[3 * t + 2]];
        v += lsnif::base::dot(a, lsnif::base::cross(b, c)) / 6.0;
    }
    return v;
}

bool near(ex::Vec3 a, ex::Vec3 b, double eps = 1e-12) {
    return lsnif::base::length(a - b) <= eps;
}

}  // namespace

// ==== the generators as functions ========================================================

TEST_CASE("splitmix64 matches the reference sequence for seed 0") {
    ex::SplitMix64 rng(0);
    CHECK(rng.next() == 0xE220A8397B1DCDAFull);
    CHECK(rng.next() == 0x6E789E6AA1B965F4ull);
    CHECK(rng.next() == 0x06C45D188009454Full);
    ex::SplitMix64 r2(42);
    for (int i = 0; i < 1000; ++i) {
        const double u = r2.uniform();
        REQUIRE(u >= 0.0);
        REQUIRE(u < 1.0);
    }
}

TEST_CASE("a box is 8 corners, 12 outward triangles, closed") {
    const ex::TriMesh box = ex::make_box({-1, 0, 2}, {1, 0.5, 5});
    CHECK(box.positions.size() == 8);
    CHECK(box.triangle_count() == 12);
    CHECK(closed_and_oriented(box));
    CHECK(signed_volume(box) == doctest::Approx(2.0 * 0.5 * 3.0));
    const ex::Bounds b = ex::mesh_bounds(ex::make_box_on_floor(1.4, 0.75, 0.8));
    CHECK(near(b.min, {-0.7, 0, -0.4}));
    CHECK(near(b.max, {0.7, 0.75, 0.4}));
}

TEST_CASE("hairball tubes are closed, outward, counted and inside the ball") {
    ex::HairballParams p;
    p.tubes = 12;
    p.segments = 9;
    const ex::TriMesh hair = ex::make_hairball(p);
    CHECK(hair.triangle_count() == ex::hairball_triangle_count(p));
    CHECK(hair.triangle_count() == 12u * (9 * 12 + 8));
    CHECK(hair.positions.size() == 12u * 10 * 6);
    CHECK(closed_and_oriented(hair));
    // Every tube encloses positive volume (outward normals), roughly pi r^2 L.
    for (int t = 0; t < p.tubes; ++t) {
        ex::TriMesh tube;
        tube.positions.assign(hair.positions.begin() + 60 * t, hair.positions.begin() + 60 * (t + 1));
        for (std::size_t i = std::size_t(t) * 116 * 3; i < std::size_t(t + 1) * 116 * 3; ++i) {
            tube.indices.push_back(hair.indices[i] - 60 * t);
        }
        CHECK(closed_and_oriented(tube));
        const double hexagon_area = 1.5 * std::sqrt(3.0) * p.tube_radius * p.tube_radius;
        CHECK(signed_volume(tube) > 0.5 * hexagon_area * 9 * p.step * p.ball_radius * p.shell_inner);
    }
    for (const ex::Vec3& v : hair.positions) {
        REQUIRE(lsnif::base::length(v) <= p.ball_radius + p.tube_radius + 1e-12);
        REQUIRE(lsnif::base::length(v) >= p.ball_radius * p.shell_inner - p.tube_radius - 1e-12);
    }
    // Same parameters, same mesh; another seed, another mesh.
    const ex::TriMesh again = ex::make_hairball(p);
    CHECK(std::memcmp(again.positions.data(), hair.positions.data(),
                      hair.positions.size() * sizeof(ex::Vec3)) == 0);
    p.seed += 1;
    CHECK_FALSE(near(ex::make_hairball(p).positions[0], hair.positions[0]));
}

TEST_CASE("Loop subdivision of a regular tetrahedron follows the stencils") {
    ex::TriMesh tet;
    tet.positions = {{1, 1, 1}, {1, -1, -1}, {-1, 1, -1}, {-1, -1, 1}};  // centroid at 0
    tet.indices = {0, 1, 2, 0, 3, 1, 0, 2, 3, 1, 3, 2};
    REQUIRE(closed_and_oriented(tet));
    REQUIRE(signed_volume(tet) > 0);
    const ex::TriMesh s = ex::loop_subdivide(tet);
    CHECK(s.positions.size() == 4 + 6);
    CHECK(s.triangle_count() == 16);
    CHECK(closed_and_oriented(s));
    CHECK(signed_volume(s) > 0);
    // Valence 3, beta = 3/16, neighbours sum to -v: v' = 7/16 v - 3/16 v = v / 4.
    for (int i = 0; i < 4; ++i) CHECK(near(s.positions[i], 0.25 * tet.positions[i]));
    // Edge (a, b): 3/8 (a + b) + 1/8 (c + d) with c + d = -(a + b): (a + b) / 4. Edges are
    // numbered in ascending (min, max) order: (0,1) (0,2) (0,3) (1,2) (1,3) (2,3).
    const int pairs[6][2] = {{0, 1}, {0, 2}, {0, 3}, {1, 2}, {1, 3}, {2, 3}};
    for (int e = 0; e < 6; ++e) {
        CHECK(near(s.positions[4 + e], 0.25 * (tet.positions[pairs[e][0]] + tet.positions[pairs[e][1]])));
    }
    // Twice more: still closed, Euler characteristic 2, 4x triangles per step.
    const ex::TriMesh s3 = ex::loop_subdivide(ex::loop_subdivide(s));
    CHECK(s3.triangle_count() == 256);
    CHECK(s3.positions.size() == 130);  // V - E + F = 130 - 384 + 256 = 2
    CHECK(closed_and_oriented(s3));
}

TEST_CASE("Loop subdivision uses the boundary rules on open meshes") {
    ex::TriMesh tri;
    tri.positions = {{0, 0, 0}, {4, 0, 0}, {0, 8, 0}};
    tri.indices = {0, 1, 2};
    const ex::TriMesh s = ex::loop_subdivide(tri);
    REQUIRE(s.positions.size() == 6);
    CHECK(s.triangle_count() == 4);
    // Corners: two boundary edges each -> 3/4 v + 1/8 (b0 + b1).
    CHECK(near(s.positions[0], {0.5, 1, 0}));
    CHECK(near(s.positions[1], {3, 1, 0}));
    CHECK(near(s.positions[2], {0.5, 6, 0}));
    // Boundary edges: midpoints, in (0,1) (0,2) (1,2) order.
    CHECK(near(s.positions[3], {2, 0, 0}));
    CHECK(near(s.positions[4], {0, 4, 0}));
    CHECK(near(s.positions[5], {2, 4, 0}));
    // Orientation kept: all four children face +z like the parent.
    for (std::size_t t = 0; t < 4; ++t) {
        const ex::Vec3 a = s.positions[s.indices[3 * t]], b = s.positions[s.indices[3 * t + 1]],
                       c = s.positions[s.indices[3 * t + 2]];
        CHECK(lsnif::base::cross(b - a, c - a).z > 0);
    }
}

TEST_CASE("read_off reads polygons and rejects broken files") {
    const fs::path dir = fresh_dir("off");
    ex::TriMesh m;
    std::string error;

    write_text(dir / "quad.off",
               "OFF # a comment\n# full-line comment\n5 2 0\n0 0 0\n1 0 0\n1 1 0\n0 1 0\n"
               "0 0 1\n4 0 1 2 3 255 0 0\n3 0 1 4\n");
    REQUIRE(ex::read_off((dir / "quad.off").string(), m, error));
    CHECK(m.positions.size() == 5);
    CHECK(m.indices == std::vector<std::uint32_t>{0, 1, 2, 0, 2, 3, 0, 1, 4});

    write_text(dir / "inline.off", "OFF 3 1 0\n0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n");
    REQUIRE(ex::read_off((dir / "inline.off").string(), m, error));
    CHECK(m.triangle_count() == 1);

    const std::pair<const char*, const char*> broken[] = {
        {"ply.off", "ply\nformat ascii 1.0\n"},
        {"empty.off", ""},
        {"truncated.off", "OFF\n3 1 0\n0 0 0\n1 0 0\n"},
        {"index.off", "OFF\n3 1 0\n0 0 0\n1 0 0\n0 1 0\n3 0 1 3\n"},
        {"negative.off", "OFF\n3 1 0\n0 0 0\n1 0 0\n0 1 0\n3 0 -1 2\n"},
        {"nan.off", "OFF\n3 1 0\n0 0 0\n1 nan 0\n0 1 0\n3 0 1 2\n"},
        {"counts.off", "OFF\n-3 1 0\n"},
    };
    for (const auto& file : broken) {  // no structured binding: clang 14 cannot capture one
        const std::string name = file.first;
        CAPTURE(name);
        write_text(dir / name, file.second);
        error.clear();
        CHECK_FALSE(ex::read_off((dir / name).string(), m, error));
        CHECK_FALSE(error.empty());
    }
    error.clear();
    CHECK_FALSE(ex::read_off((dir / "missing.off").string(), m, error));
    CHECK(error.find("cannot open") != std::string::npos);
}

// ==== the program and its output =========================================================

TEST_CASE("the built example scene is a valid GLB with the promised content") {
    const Glb glb = parse_glb(read_bytes(kBuiltScene));
    const json& doc = glb.doc;
    CHECK(doc.at("asset").at("version") == "2.0");
    CHECK_FALSE(doc.contains("extensionsUsed"));
    CHECK_FALSE(doc.contains("textures"));
    CHECK_FALSE(doc.contains("images"));
    check_binary_layout(glb);
    const std::map<std::string, MeshInfo> meshes = check_meshes(glb);

    // Materials: named, unique, no textures.
    std::set<std::string> material_names;
    for (const json& m : doc.at("materials")) {
        const std::string name = m.at("name");
        CHECK_FALSE(name.empty());
        CHECK(material_names.insert(name).second);
        CHECK(m.dump().find("Texture") == std::string::npos);
    }
    CHECK(material_names.size() >= 4);

    // Nodes: each uses a matrix or TRS (never both); both kinds occur.
    int matrix_nodes = 0, trs_nodes = 0;
    for (const json& n : doc.at("nodes")) {
        const bool trs = n.contains("translation") || n.contains("rotation") || n.contains("scale");
        CHECK_FALSE((trs && n.contains("matrix")));
        if (n.contains("matrix")) {
            REQUIRE(n["matrix"].size() == 16);
            ++matrix_nodes;
        }
        if (n.contains("rotation")) {
            const json& r = n["rotation"];
            double norm2 = 0;
            for (const json& c : r) norm2 += c.get<double>() * c.get<double>();
            CHECK(norm2 == doctest::Approx(1.0));
        }
        trs_nodes += trs;
    }
    CHECK(matrix_nodes >= 1);
    CHECK(trs_nodes >= 1);
    REQUIRE(doc.at("scenes").at(doc.value("scene", 0)).at("nodes").size() == 1);  // a single root

    // Content: >= 4 simple boxes, one subdivided mesh > 60k triangles, a hairball x3.
    const std::vector<Instance> instances = instances_of(doc);
    std::map<std::string, int> uses;
    for (const Instance& i : instances) ++uses[i.mesh];
    int boxes = 0;
    for (const auto& [name, m] : meshes) boxes += m.triangles == 12 && m.vertices == 8;
    CHECK(boxes >= 4);
    REQUIRE(meshes.count("dragon") == 1);
    CHECK(meshes.at("dragon").triangles == 4u * 19994);  // ChineseDragon-10kv, one Loop step
    CHECK(meshes.at("dragon").triangles > 60000);
    CHECK(uses["dragon"] == 1);
    REQUIRE(meshes.count("hairball") == 1);
    CHECK(meshes.at("hairball").triangles == 300u * (20 * 12 + 8));
    CHECK(uses["hairball"] == 3);
    for (const auto& mesh : meshes) CHECK_MESSAGE(uses[mesh.first] >= 1, mesh.first, " is not instanced");

    // Placement: everything inside the room, the dragon 1 m tall standing on the floor, and
    // the three hairballs at three different places with three different sizes.
    std::set<std::pair<long, long>> hair_places;
    std::set<long> hair_sizes;
    for (const Instance& i : instances) {
        CAPTURE(i.node);
        const auto [lo, hi] = world_bounds(meshes.at(i.mesh), i.world);
        CHECK(lo[0] >= -3.1 - 1e-6);
        CHECK(lo[1] >= -0.1 - 1e-6);
        CHECK(lo[2] >= -3.1 - 1e-6);
        CHECK(hi[0] <= 3.0 + 1e-6);
        CHECK(hi[1] <= 3.0 + 1e-6);
        CHECK(hi[2] <= 3.0 + 1e-6);
        if (i.mesh == "dragon") {
            CHECK(lo[1] == doctest::Approx(0.0));
            CHECK(hi[1] - lo[1] == doctest::Approx(1.0));
        }
        if (i.mesh == "hairball") {
            hair_places.insert({std::lround(i.world[12] * 100), std::lround(i.world[14] * 100)});
            hair_sizes.insert(std::lround(std::hypot(i.world[0], i.world[1], i.world[2]) * 100));
            CHECK(i.world[1] == doctest::Approx(0.0));  // rotation about Y only
            CHECK(i.world[9] == doctest::Approx(0.0));
        }
    }
    CHECK(hair_places.size() == 3);
    CHECK(hair_sizes.size() == 3);
}

TEST_CASE("the generator is deterministic") {
    const fs::path dir = fresh_dir("determinism");
    const RunResult a = run_generator("--out " + q(dir / "a.glb") + " --cgal-data " + q(kCgalDir), dir);
    REQUIRE_MESSAGE(a.exit_code == 0, a.err);
    CHECK(a.err.empty());
    CHECK(a.out.find("mesh hairball") != std::string::npos);
    const RunResult b = run_generator("--out " + q(dir / "b.glb") + " --cgal-data " + q(kCgalDir), dir);
    REQUIRE(b.exit_code == 0);
    const auto bytes_a = read_bytes(dir / "a.glb");
    CHECK(bytes_a == read_bytes(dir / "b.glb"));
    CHECK(bytes_a == read_bytes(kBuiltScene));  // the build-time scene is the same file
    CHECK_FALSE(fs::exists(dir / "a.glb.tmp"));
    // The .off file itself is accepted too and gives the same scene.
    const RunResult c = run_generator(
        "--out " + q(dir / "c.glb") + " --cgal-data " + q(kCgalDir / "data/meshes/ChineseDragon-10kv.off"),
        dir);
    REQUIRE(c.exit_code == 0);
    CHECK(bytes_a == read_bytes(dir / "c.glb"));
}

TEST_CASE("--hairball-only writes a single small hairball") {
    const fs::path dir = fresh_dir("hairball_only");
    const RunResult r =
        run_generator("--out " + q(dir / "h.glb") + " --hairball-only --tubes 7 --segments 5", dir);
    REQUIRE_MESSAGE(r.exit_code == 0, r.err);
    const Glb glb = parse_glb(read_bytes(dir / "h.glb"));
    check_binary_layout(glb);
    const auto meshes = check_meshes(glb);
    REQUIRE(meshes.size() == 1);
    CHECK(meshes.at("hairball").triangles == 7u * (5 * 12 + 8));
    CHECK(meshes.at("hairball").vertices == 7u * 6 * 6);
    CHECK(instances_of(glb.doc).size() == 1);
    // A different seed gives different bytes, the same seed the same bytes.
    REQUIRE(
        run_generator("--out " + q(dir / "s.glb") + " --hairball-only --tubes 7 --segments 5 --seed 7", dir)
            .exit_code == 0);
    REQUIRE(run_generator("--out " + q(dir / "h2.glb") + " --hairball-only --tubes 7 --segments 5", dir)
                .exit_code == 0);
    CHECK(read_bytes(dir / "s.glb") != read_bytes(dir / "h.glb"));
    CHECK(read_bytes(dir / "h2.glb") == read_bytes(dir / "h.glb"));
}

TEST_CASE("errors exit 1 with an error line and leave no files behind") {
    const fs::path dir = fresh_dir("errors");

    SUBCASE("missing CGAL data") {
        const RunResult r =
            run_generator("--out " + q(dir / "x.glb") + " --cgal-data " + q(dir / "nowhere"), dir);
        CHECK(r.exit_code == 1);
        CHECK(r.err.rfind("error: ", 0) == 0);
        CHECK_FALSE(fs::exists(dir / "x.glb"));
        CHECK_FALSE(fs::exists(dir / "x.glb.tmp"));
    }
    SUBCASE("a directory without the mesh") {
        fs::create_directories(dir / "empty");
        const RunResult r =
            run_generator("--out " + q(dir / "x.glb") + " --cgal-data " + q(dir / "empty"), dir);
        CHECK(r.exit_code == 1);
        CHECK(r.err.find("ChineseDragon-10kv.off") != std::string::npos);
    }
    SUBCASE("a broken mesh keeps the previous output") {
        write_text(dir / "broken.off", "OFF\n3 1 0\n0 0 0\n");
        write_text(dir / "x.glb", "previous");
        const RunResult r =
            run_generator("--out " + q(dir / "x.glb") + " --cgal-data " + q(dir / "broken.off"), dir);
        CHECK(r.exit_code == 1);
        CHECK(r.err.rfind("error: ", 0) == 0);
        CHECK(read_text(dir / "x.glb") == "previous");
        CHECK_FALSE(fs::exists(dir / "x.glb.tmp"));
    }
    SUBCASE("unwritable output") {
        const RunResult r = run_generator("--out " + q(dir / "no/such/dir/x.glb") + " --hairball-only", dir);
        CHECK(r.exit_code == 1);
        CHECK(r.err.rfind("error: ", 0) == 0);
        fs::create_directories(dir / "isdir.glb");  // renaming onto a directory fails
        const RunResult d =
            run_generator("--out " + q(dir / "isdir.glb") + " --hairball-only --tubes 2", dir);
        CHECK(d.exit_code == 1);
        CHECK(fs::is_directory(dir / "isdir.glb"));
        CHECK_FALSE(fs::exists(dir / "isdir.glb.tmp"));
    }
    SUBCASE("usage errors") {
        for (const char* args :
             {"", "--hairball-only", "--out x.glb", "--out x.glb --hairball-only --tubes 0",
              "--out x.glb --hairball-only --segments abc", "--out x.glb --bogus", "--out"}) {
            CAPTURE(args);
            const RunResult r = run_generator(args, dir);
            CHECK(r.exit_code == 1);
            CHECK(r.err.rfind("error: ", 0) == 0);
        }
        CHECK_FALSE(fs::exists("x.glb"));
    }
}
