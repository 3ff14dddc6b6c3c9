// lsnif::scene glTF 2.0 import: real files from assimp-testmodels (the glTF-Asset-Generator
// cases, sample models and malformed files) and cases the test writes itself.
#include "scene_test_util.hpp"

#include <algorithm>
#include <map>
#include <set>
#include <tuple>

using namespace scene_test;

namespace {

// Triangles as sorted triples of positions (order- and rotation-independent comparison).
using Vec3 = std::array<float, 3>;
using Tri = std::array<Vec3, 3>;

Vec3 vertex(const sc::Mesh& m, std::uint32_t i) {
    return {m.positions[3 * i], m.positions[3 * i + 1], m.positions[3 * i + 2]};
}

std::multiset<Tri> triangle_set(const sc::Mesh& m) {
    std::multiset<Tri> out;
    for (std::size_t t = 0; t < m.triangle_count(); ++t) {
        Tri tri = {vertex(m, m.indices[3 * t]), vertex(m, m.indices[3 * t + 1]),
                   vertex(m, m.indices[3 * t + 2])};
        std::sort(tri.begin(), tri.end());
        out.insert(tri);
    }
    return out;
}

// Geometric normal (unnormalized) of triangle t.
std::array<double, 3> face_normal(const sc::Mesh& m, std::size_t t) {
    const Vec3 a = vertex(m, m.indices[3 * t]), b = vertex(m, m.indices[3 * t + 1]),
               c = vertex(m, m.indices[3 * t + 2]);
    const double e1[3] = {double(b[0]) - a[0], double(b[1]) - a[1], double(b[2]) - a[2]};
    const double e2[3] = {double(c[0]) - a[0], double(c[1]) - a[1], double(c[2]) - a[2]};
    return {e1[1] * e2[2] - e1[2] * e2[1], e1[2] * e2[0] - e1[0] * e2[2], e1[0] * e2[1] - e1[1] * e2[0]};
}

// Compares the importer's instances with the independent reference walk of the JSON:
// same count and order, same transforms, and a consistent glTF mesh -> Scene mesh map.
std::map<int, std::uint32_t> check_against_reference(const sc::Scene& scene, const fs::path& file) {
    const json gltf = load_gltf_json(file);
    const std::vector<RefInstance> ref = reference_instances(gltf);
    REQUIRE(scene.instances.size() == ref.size());
    std::map<int, std::uint32_t> slot_of;  // glTF mesh -> Scene mesh
    for (std::size_t i = 0; i < ref.size(); ++i) {
        const sc::Instance& inst = scene.instances[i];
        const json& node = gltf["nodes"][std::size_t(ref[i].node)];
        const std::string expected_name =
            node.contains("name") ? node["name"].get<std::string>() : "node_" + std::to_string(ref[i].node);
        CHECK(inst.node_name == expected_name);
        const auto [it, inserted] = slot_of.emplace(ref[i].mesh, inst.mesh);
        CHECK(it->second == inst.mesh);  // one glTF mesh is always the same Scene mesh
        check_transform(inst.transform, ref[i].world,
                        file.filename().string() + " instance " + std::to_string(i));
    }
    std::set<std::uint32_t> slots;
    for (const auto& [mesh, slot] : slot_of) slots.insert(slot);
    CHECK(slots.size() == slot_of.size());  // different glTF meshes never merge
    CHECK(scene.meshes.size() == slot_of.size());
    return slot_of;
}

}  // namespace

TEST_CASE("2CylinderEngine.glb: 29 unique meshes, 67 instances, transforms match an independent walk") {
    const fs::path file = kGltf2Dir / "2CylinderEngine-glTF-Binary/2CylinderEngine.glb";
    const sc::ImportResult r = sc::import_scene(file);
    require_ok(r);
    const sc::Scene& s = r.scene;
    CHECK(s.instances.size() == 67);
    CHECK(s.meshes.size() == 29);
    const auto slot_of = check_against_reference(s, file);

    // Every primitive (all TRIANGLES, indexed) becomes index-count / 3 triangles carrying
    // its material + 1; primitives merge per glTF mesh.
    const json gltf = load_gltf_json(file);
    bool saw_multi_material = false;
    for (const auto& [gmesh, slot] : slot_of) {
        const json& prims = gltf["meshes"][std::size_t(gmesh)]["primitives"];
        std::map<std::uint32_t, std::size_t> want;
        std::size_t vertices = 0;
        std::set<int> position_accessors;
        for (const auto& p : prims) {
            const std::size_t count =
                gltf["accessors"][p["indices"].get<std::size_t>()]["count"].get<std::size_t>();
            want[std::uint32_t(p["material"].get<int>() + 1)] += count / 3;
            const int pa = p["attributes"]["POSITION"].get<int>();
            if (position_accessors.insert(pa).second)
                vertices += gltf["accessors"][std::size_t(pa)]["count"].get<std::size_t>();
        }
        const sc::Mesh& m = s.meshes[slot];
        std::map<std::uint32_t, std::size_t> have;
        for (const std::uint32_t mat : m.triangle_materials) ++have[mat];
        CHECK(have == want);
        CHECK(m.vertex_count() == vertices);
        CHECK(m.normal_origin == sc::NormalOrigin::source);
        CHECK(m.name == gltf["meshes"][std::size_t(gmesh)]["name"].get<std::string>());
        saw_multi_material |= want.size() > 1;
    }
    CHECK(saw_multi_material);
    REQUIRE(s.materials.size() == gltf["materials"].size() + 1);
    CHECK(s.materials[0] == "default");
    CHECK(s.materials[1] == gltf["materials"][0]["name"].get<std::string>());
    CHECK(s.warnings.empty());

    // Content hash: well-formed, deterministic, distinct for distinct geometry.
    std::set<std::string> hashes;
    for (const auto& m : s.meshes) {
        const std::string h = sc::geometry_hash(m);
        CHECK(h.size() == 8 + 16);
        CHECK(h.rfind("fnv1a64:", 0) == 0);
        CHECK(h.find_first_not_of("0123456789abcdef", 8) == std::string::npos);
        CHECK(h == sc::geometry_hash(m));
        hashes.insert(h);
    }
    CHECK(hashes.size() == s.meshes.size());
}

TEST_CASE("TRS nodes, matrices and several primitives: transforms match the independent walk") {
    // TRS with rotations (Cameras, AnimatedMorphCube, simple_skin), translations with many
    // meshes and materials (ClearCoat, TextureTransform), matrices (BoxTextured, Embedded).
    const std::vector<std::string> files = {
        "cameras/Cameras.gltf",
        "glTF-Sample-Models/AnimatedMorphCube-glTF/AnimatedMorphCube.gltf",
        "simple_skin/simple_skin.gltf",
        "ClearCoat-glTF/ClearCoatTest.gltf",
        "textureTransform/TextureTransformTest.gltf",
        "BoxTextured-glTF/BoxTextured.gltf",
        "BoxTextured-glTF-Embedded/BoxTextured.gltf",
        "BoxTextured-glTF-Binary/BoxTextured.glb",
        "BoxTexcoords-glTF/boxTexcoords.gltf",
    };
    for (const std::string& name : files) {
        CAPTURE(name);
        const fs::path file = kGltf2Dir / name;
        const sc::ImportResult r = sc::import_gltf(file);
        require_ok(r);
        check_against_reference(r.scene, file);
    }
    // What is not applied is said.
    const auto morph =
        sc::import_gltf(kGltf2Dir / "glTF-Sample-Models/AnimatedMorphCube-glTF/AnimatedMorphCube.gltf");
    CHECK(has_warning(morph.scene, "morph targets"));
    const auto skin = sc::import_gltf(kGltf2Dir / "simple_skin/simple_skin.gltf");
    CHECK(has_warning(skin.scene, "skinned"));
    // ClearCoat: 27 materials recorded by name, each mesh's triangles carry its material.
    const auto cc = sc::import_gltf(kGltf2Dir / "ClearCoat-glTF/ClearCoatTest.gltf");
    const json gltf = load_gltf_json(kGltf2Dir / "ClearCoat-glTF/ClearCoatTest.gltf");
    REQUIRE(cc.scene.materials.size() == gltf["materials"].size() + 1);
    for (std::size_t i = 0; i < gltf["materials"].size(); ++i) {
        CHECK(cc.scene.materials[i + 1] == gltf["materials"][i]["name"].get<std::string>());
    }
}

TEST_CASE("Mesh_PrimitiveMode: triangle lists, strips and fans, indexed by uint8/16/32 or not") {
    const fs::path dir = kGltf2Dir / "glTF-Asset-Generator/Mesh_PrimitiveMode";
    auto load = [&](int n) {
        const fs::path file =
            dir / ("Mesh_PrimitiveMode_" + std::string(n < 10 ? "0" : "") + std::to_string(n) + ".gltf");
        return sc::import_gltf(file);
    };
    const sc::ImportResult list = load(6);  // non-indexed TRIANGLES: the reference quad
    require_ok(list);
    REQUIRE(list.scene.meshes.size() == 1);
    const sc::Mesh& quad = list.scene.meshes[0];
    CHECK(quad.triangle_count() == 2);
    CHECK(quad.normal_origin == sc::NormalOrigin::computed);  // the file has no normals
    const auto want = triangle_set(quad);
    auto area = [](const sc::Mesh& m) {
        double a = 0;
        for (std::size_t t = 0; t < m.triangle_count(); ++t) a += 0.5 * face_normal(m, t)[2];
        return a;
    };
    auto corners = [](const sc::Mesh& m) {
        std::set<Vec3> c;
        for (const std::uint32_t i : m.indices) c.insert(vertex(m, i));
        return c;
    };
    for (const int n : {4, 5, 11, 12, 13, 14, 15}) {  // strip, fan, indexed strip/fan, u32/u8/u16
        CAPTURE(n);
        const sc::ImportResult r = load(n);
        require_ok(r);
        const sc::Mesh& m = r.scene.meshes[0];
        CHECK(m.triangle_count() == 2);
        // Lists and strips split the quad along the same diagonal as the reference; a fan
        // pivots on its first vertex, so it may use the other one: same quad either way.
        if (n != 5 && n != 12) CHECK(triangle_set(m) == want);
        CHECK(corners(m) == corners(quad));
        CHECK(area(m) == doctest::Approx(area(quad)));
        // Strips alternate winding and fans pivot on v0: converted correctly, every triangle
        // faces the same way as the reference list (+Z, towards the viewer).
        for (std::size_t t = 0; t < m.triangle_count(); ++t) CHECK(face_normal(m, t)[2] > 0.0);
        for (std::size_t v = 0; v < m.vertex_count(); ++v)
            CHECK(m.normals[3 * v + 2] == doctest::Approx(1.0));
    }
    // Points and lines are no triangles: skipped with a warning, then "no triangles".
    for (const int n : {0, 1, 2, 3, 7, 8, 9, 10}) {
        CAPTURE(n);
        const sc::ImportResult r = load(n);
        require_error(
            r,
            (dir / ("Mesh_PrimitiveMode_" + std::string(n < 10 ? "0" : "") + std::to_string(n) + ".gltf"))
                .string(),
            "no triangles");
        CHECK(has_warning(r.scene, "is not a triangle topology; skipped"));
    }
}

TEST_CASE("malformed and unsupported files from the test models give clear errors") {
    struct Case {
        const char* file;
        const char* needle;
    };
    const std::vector<Case> cases = {
        {"IndexOutOfRange/IndexOutOfRange.gltf", "out of range"},
        {"IndexOutOfRange/AllIndicesOutOfRange.gltf", "out of range"},
        {"RecursiveNodes/RecursiveNodes.gltf", "reached a second time"},
        {"MissingBin/BoxTextured.gltf", "invalid glTF"},
        {"IncorrectVertexArrays/Cube.gltf", ""},
        {"BoxWithInfinites-glTF-Binary/BoxWithInfinites.glb", "not finite"},
        {"draco/2CylinderEngine.gltf", "KHR_draco_mesh_compression"},
        {"TestNoRootNode/NoScene.gltf", "scene 0 does not exist"},
        {"TestNoRootNode/SceneWithoutNodes.gltf", "no triangles"},
    };
    for (const Case& c : cases) {
        CAPTURE(c.file);
        const fs::path file = kGltf2Dir / c.file;
        require_error(sc::import_scene(file), file.string(), c.needle);
    }
    // glTF 1.0 files are refused, not misread.
    const fs::path v1 = kAssimpDir / "glTF/TwoBoxes/TwoBoxes.gltf";
    require_error(sc::import_scene(v1), v1.string(), "");
}

TEST_CASE("every glTF file of the test models imports or fails cleanly") {
    std::size_t ok = 0, failed = 0;
    for (const fs::path& root : {kGltf2Dir, kAssimpDir / "glTF"}) {
        for (const auto& entry : fs::recursive_directory_iterator(root)) {
            const std::string ext = entry.path().extension().string();
            if (ext != ".gltf" && ext != ".glb") continue;
            CAPTURE(entry.path().string());
            const sc::ImportResult r = sc::import_scene(entry.path());
            if (r.ok()) {
                ++ok;
                CHECK(sc::check_scene(r.scene).empty());
            } else {
                ++failed;
                CHECK(r.error.rfind(entry.path().string() + ": ", 0) == 0);
                CHECK(r.error.find('\n') == std::string::npos);
            }
        }
    }
    MESSAGE("glTF test models: " << ok << " imported, " << failed << " rejected");
    CHECK(ok >= 25);
}

// ---- generated cases ---------------------------------------------------------------------

namespace {

// An octahedron mesh (no normals) instanced by one root node; `tweak` edits the document.
GltfDoc octahedron_doc() {
    GltfDoc d;
    const int pos = d.add_positions(octahedron_positions());
    const int idx =
        d.add_indices_u16({0, 2, 4, 2, 1, 4, 1, 3, 4, 3, 0, 4, 2, 0, 5, 1, 2, 5, 3, 1, 5, 0, 3, 5});
    const int mesh =
        d.add_mesh(json::array({{{"attributes", {{"POSITION", pos}}}, {"indices", idx}}}), "octa");
    d.add_node({{"mesh", mesh}, {"name", "octa_node"}});
    return d;
}

}  // namespace

TEST_CASE("generated: TRS hierarchy with a matrix child, exact expected transforms") {
    GltfDoc d = octahedron_doc();
    // Root: T(1,2,3) * R(90 deg about Z) * S(2); child: matrix translating by (1,0,0) with
    // uniform scale 0.5; grandchild TRS with a non-normalized-looking but unit quaternion.
    const double h = std::sqrt(0.5);
    d.j["nodes"][0]["translation"] = {1, 2, 3};
    d.j["nodes"][0]["rotation"] = {0, 0, h, h};
    d.j["nodes"][0]["scale"] = {2, 2, 2};
    d.j["nodes"][0]["children"] = {1};
    d.add_node(
        {{"mesh", 0}, {"name", "child"}, {"matrix", {0.5, 0, 0, 0, 0, 0.5, 0, 0, 0, 0, 0.5, 0, 1, 0, 0, 1}}},
        false);
    const fs::path file = d.write_gltf(fresh_dir("trs"), "trs");
    const sc::ImportResult r = sc::import_gltf(file);
    require_ok(r);
    REQUIRE(r.scene.meshes.size() == 1);  // one glTF mesh used twice = one Mesh
    REQUIRE(r.scene.instances.size() == 2);
    const sc::Transform root = {0, -2, 0, 1, 2, 0, 0, 2, 0, 0, 2, 3};
    // child: root * [0.5 I | (1,0,0)] -> A = R*S*0.5 = 90deg about Z, scale 1; b = root(1,0,0) = (1,4,3)
    const sc::Transform child = {0, -1, 0, 1, 1, 0, 0, 4, 0, 0, 1, 3};
    for (int i = 0; i < 12; ++i) {
        CHECK(r.scene.instances[0].transform[std::size_t(i)] ==
              doctest::Approx(root[std::size_t(i)]).epsilon(1e-6));
        CHECK(r.scene.instances[1].transform[std::size_t(i)] ==
              doctest::Approx(child[std::size_t(i)]).epsilon(1e-6));
    }
    CHECK(r.scene.instances[0].node_name == "octa_node");
    CHECK(r.scene.instances[1].node_name == "child");
    CHECK(r.scene.instances[0].mesh == r.scene.instances[1].mesh);
    check_against_reference(r.scene, file);

    // Computed normals of a convex closed mesh: unit and outward (area-weighted average of
    // the 4 incident faces of an octahedron vertex is the vertex direction itself).
    const sc::Mesh& m = r.scene.meshes[0];
    CHECK(m.normal_origin == sc::NormalOrigin::computed);
    for (std::size_t v = 0; v < m.vertex_count(); ++v) {
        for (int a = 0; a < 3; ++a)
            CHECK(m.normals[3 * v + std::size_t(a)] == doctest::Approx(m.positions[3 * v + std::size_t(a)]));
    }
}

TEST_CASE("generated: several primitives, materials, non-indexed and uint8 indices, shared vertices") {
    GltfDoc d;
    // Two triangles sharing POSITION (one indexed u8, one non-indexed), one with a material.
    const int pos = d.add_positions({0, 0, 0, 1, 0, 0, 0, 1, 0});
    const int idx = d.add_indices_u8({0, 1, 2});
    const int pos2 = d.add_positions({0, 0, 1, 1, 0, 1, 0, 1, 1, 1, 1, 1, 0, 0, 1, 1, 1, 1});
    d.j["materials"] = json::array({{{"name", "red"}}, json::object()});
    const int mesh = d.add_mesh(json::array({
        {{"attributes", {{"POSITION", pos}}}, {"indices", idx}, {"material", 1}},
        {{"attributes", {{"POSITION", pos}}}},  // same vertices, default material
        {{"attributes", {{"POSITION", pos2}}}, {"material", 0}, {"mode", 4}},  // non-indexed, 2 triangles
        {{"attributes", {{"POSITION", pos}}}, {"mode", 0}},                    // points: skipped
    }));
    d.add_node({{"mesh", mesh}});
    const fs::path file = d.write_gltf(fresh_dir("prims"), "prims");
    const sc::ImportResult r = sc::import_gltf(file);
    require_ok(r);
    const sc::Scene& s = r.scene;
    REQUIRE(s.meshes.size() == 1);
    const sc::Mesh& m = s.meshes[0];
    CHECK(m.name == "mesh_0");
    CHECK(s.instances[0].node_name == "node_0");
    CHECK(m.vertex_count() == 3 + 6);  // the shared POSITION accessor is stored once
    CHECK(m.triangle_count() == 4);
    CHECK(m.triangle_materials == std::vector<std::uint32_t>{2, 0, 1, 1});
    CHECK(s.materials == std::vector<std::string>{"default", "red", "material_1"});
    CHECK(std::vector<std::uint32_t>(m.indices.begin(), m.indices.begin() + 6) ==
          std::vector<std::uint32_t>{0, 1, 2, 0, 1, 2});
    CHECK(has_warning(s, "mesh 0 primitive 3: POINTS is not a triangle topology; skipped"));
    // Same result from a .glb of the same document.
    const fs::path glb = d.write_glb(fresh_dir("prims_glb"), "prims");
    const sc::ImportResult rb = sc::import_gltf(glb);
    require_ok(rb);
    CHECK(rb.scene.meshes[0].indices == m.indices);
    CHECK(rb.scene.meshes[0].positions == m.positions);
    CHECK(sc::geometry_hash(rb.scene.meshes[0]) == sc::geometry_hash(m));
}

TEST_CASE("generated: sparse accessors, normals from the file, KHR_mesh_quantization") {
    GltfDoc d;
    // POSITION without bufferView (zeros) plus sparse values for vertices 1 and 2.
    const std::vector<std::uint16_t> sparse_idx = {1, 2};
    const std::vector<float> sparse_val = {2, 0, 0, 0, 2, 0};
    const int iv = d.add_view(sparse_idx.data(), 4);
    const int vv = d.add_view(sparse_val.data(), 24);
    d.j["accessors"].push_back({{"componentType", 5126},
                                {"count", 3},
                                {"type", "VEC3"},
                                {"sparse",
                                 {{"count", 2},
                                  {"indices", {{"bufferView", iv}, {"componentType", 5123}}},
                                  {"values", {{"bufferView", vv}}}}}});
    const int pos = int(d.j["accessors"].size() - 1);
    // Normals stored with length 2: normalized on import.
    const std::vector<float> normals = {0, 0, 2, 0, 0, 2, 0, 0, 2};
    const int nrm = d.add_accessor(d.add_view(normals.data(), normals.size() * 4), 5126, 3, "VEC3");
    const int mesh = d.add_mesh(json::array({{{"attributes", {{"POSITION", pos}, {"NORMAL", nrm}}}}}));
    d.add_node({{"mesh", mesh}});
    const fs::path file = d.write_gltf(fresh_dir("sparse"), "sparse");
    const sc::ImportResult r = sc::import_gltf(file);
    require_ok(r);
    const sc::Mesh& m = r.scene.meshes[0];
    CHECK(m.positions == std::vector<float>{0, 0, 0, 2, 0, 0, 0, 2, 0});
    CHECK(m.normals == std::vector<float>{0, 0, 1, 0, 0, 1, 0, 0, 1});
    CHECK(m.normal_origin == sc::NormalOrigin::source);

    // KHR_mesh_quantization: normalized signed shorts (32767 -> 1.0), stride 8 (6 bytes of
    // data, 2 of padding per vertex).
    GltfDoc q;
    const std::vector<std::int16_t> data = {0, 0, 0, 0, 32767, 0, 0, 0, 0, 32767, 0, 0};
    const int view = q.add_view(data.data(), data.size() * 2, 8);
    q.j["accessors"].push_back({{"bufferView", view},
                                {"componentType", 5122},
                                {"normalized", true},
                                {"count", 3},
                                {"type", "VEC3"}});
    q.j["extensionsUsed"] = {"KHR_mesh_quantization"};
    q.j["extensionsRequired"] = {"KHR_mesh_quantization"};
    q.add_node({{"mesh", q.add_mesh(json::array({{{"attributes", {{"POSITION", 0}}}}}))}});
    const fs::path fq = q.write_gltf(fresh_dir("quant"), "quant");
    const sc::ImportResult rq = sc::import_gltf(fq);
    require_ok(rq);
    CHECK(rq.scene.meshes[0].positions == std::vector<float>{0, 0, 0, 1, 0, 0, 0, 1, 0});
    // Without the extension, integer positions are refused.
    q.j.erase("extensionsUsed");
    q.j.erase("extensionsRequired");
    const fs::path fq2 = q.write_gltf(fresh_dir("quant_noext"), "quant");
    require_error(sc::import_gltf(fq2), fq2.string(), "FLOAT is required");
    // A non-indexed triangle list whose vertex count is not a multiple of 3.
    GltfDoc t;
    const int two = t.add_positions({0, 0, 0, 1, 0, 0});
    t.add_node({{"mesh", t.add_mesh(json::array({{{"attributes", {{"POSITION", two}}}}}))}});
    const fs::path ft = t.write_gltf(fresh_dir("two_vertices"), "two");
    require_error(sc::import_gltf(ft), ft.string(), "not a multiple of 3");
}

TEST_CASE("generated bad cases: clear errors, no crash") {
    const fs::path dir = fresh_dir("bad");
    auto expect = [&](GltfDoc d, const std::string& name, const std::string& needle) {
        CAPTURE(name);
        const fs::path file = d.write_gltf(dir, name);
        const sc::ImportResult r = sc::import_gltf(file);
        require_error(r, file.string(), needle);
        return r;
    };
    {  // NaN vertex
        GltfDoc d;
        const float nan = std::nanf("");
        const int pos = d.add_positions({0, 0, 0, 1, 0, 0, 0, nan, 0});
        d.add_node({{"mesh", d.add_mesh(json::array({{{"attributes", {{"POSITION", pos}}}}}))}});
        expect(d, "nan_vertex", "vertex 2 is");
    }
    {  // Inf vertex
        GltfDoc d;
        const int pos = d.add_positions({0, 0, 0, 1, 0, 0, 0, 1, INFINITY});
        d.add_node({{"mesh", d.add_mesh(json::array({{{"attributes", {{"POSITION", pos}}}}}))}});
        expect(d, "inf_vertex", "not finite");
    }
    {  // index out of range
        GltfDoc d = octahedron_doc();
        const int idx = d.add_indices_u32({0, 1, 6});
        d.j["meshes"][0]["primitives"][0]["indices"] = idx;
        expect(d, "index_range", "index 6 at position 2 is out of range (POSITION has 6 vertices");
    }
    {  // node cycle: 0 -> 1 -> 0
        GltfDoc d = octahedron_doc();
        d.j["nodes"][0]["children"] = {1};
        d.add_node({{"children", {0}}}, false);
        expect(d, "cycle", "reached a second time");
    }
    {  // self-cycle and a node with two parents
        GltfDoc d = octahedron_doc();
        d.j["nodes"][0]["children"] = {0};
        expect(d, "self_cycle", "cycle");
        GltfDoc e = octahedron_doc();
        const int shared = e.add_node({{"mesh", 0}}, false);
        e.j["nodes"][0]["children"] = {shared};
        e.add_node({{"children", {shared}}});
        expect(e, "two_parents", "two parents");
    }
    {  // missing buffer file
        GltfDoc d = octahedron_doc();
        const fs::path file = d.write_gltf(dir, "missing_bin");
        fs::remove(dir / "missing_bin.bin");
        const sc::ImportResult r = sc::import_gltf(file);
        require_error(r, file.string(), "missing_bin.bin");
    }
    {  // buffer file shorter than declared
        GltfDoc d = octahedron_doc();
        const fs::path file = d.write_gltf(dir, "short_bin");
        fs::resize_file(dir / "short_bin.bin", 10);
        require_error(sc::import_gltf(file), file.string(), "");
    }
    {  // required extension we do not implement
        GltfDoc d = octahedron_doc();
        d.j["extensionsUsed"] = {"KHR_draco_mesh_compression"};
        d.j["extensionsRequired"] = {"KHR_draco_mesh_compression"};
        expect(d, "draco", "requires extension KHR_draco_mesh_compression");
    }
    {  // points only: warning, then the empty result is an error
        GltfDoc d = octahedron_doc();
        d.j["meshes"][0]["primitives"][0]["mode"] = 0;
        const sc::ImportResult r = expect(d, "points", "no triangles to import");
        CHECK(has_warning(r.scene, "POINTS is not a triangle topology; skipped"));
        CHECK(has_warning(r.scene, "mesh 0 'octa' has no triangles"));
    }
    {  // accessor reads past its bufferView
        GltfDoc d = octahedron_doc();
        d.j["accessors"][0]["count"] = 7;
        expect(d, "accessor_range", "reads past the end of its bufferView");
    }
    {  // bufferView past the end of its buffer
        GltfDoc d = octahedron_doc();
        d.j["bufferViews"][0]["byteLength"] = 4096;
        expect(d, "view_range", "");
    }
    {  // wrong POSITION type / component type, wrong index component type
        GltfDoc d = octahedron_doc();
        d.j["accessors"][0]["type"] = "VEC2";
        expect(d, "pos_type", "not VEC3");
        GltfDoc e = octahedron_doc();
        e.j["accessors"][0]["componentType"] = 5125;
        expect(e, "pos_component", "FLOAT is required");
        GltfDoc f = octahedron_doc();
        f.j["accessors"][1]["componentType"] = 5122;  // SHORT indices
        expect(f, "index_component", "SCALAR of UNSIGNED_BYTE");
    }
    {  // dangling references
        GltfDoc d = octahedron_doc();
        d.j["nodes"][0]["mesh"] = 5;
        expect(d, "bad_mesh", "refers to mesh 5, which does not exist");
        GltfDoc e = octahedron_doc();
        e.j["meshes"][0]["primitives"][0]["material"] = 3;
        expect(e, "bad_material", "refers to material 3");
        GltfDoc f = octahedron_doc();
        f.j["scenes"][0]["nodes"] = {0, 9};
        expect(f, "bad_node", "refers to node 9");
        GltfDoc g = octahedron_doc();
        g.j["scene"] = 2;
        expect(g, "bad_scene", "scene 2 does not exist");
    }
    {  // non-affine matrix, zero quaternion
        GltfDoc d = octahedron_doc();
        d.j["nodes"][0]["matrix"] = {1, 0, 0, 0.5, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1};
        expect(d, "projective", "not affine");
        GltfDoc e = octahedron_doc();
        e.j["nodes"][0]["rotation"] = {0, 0, 0, 0};
        expect(e, "zero_quat", "quaternion");
    }
    {  // sparse indices not increasing
        GltfDoc d = octahedron_doc();
        const std::vector<std::uint8_t> si = {3, 1, 0, 0};
        const std::vector<float> sv = {9, 9, 9, 8, 8, 8};
        const int iv = d.add_view(si.data(), 2);
        const int vv = d.add_view(sv.data(), 24);
        d.j["accessors"][0]["sparse"] = {{"count", 2},
                                         {"indices", {{"bufferView", iv}, {"componentType", 5121}}},
                                         {"values", {{"bufferView", vv}}}};
        expect(d, "sparse_order", "strictly increasing");
    }
    {  // absurdly deep JSON (tinygltf would recurse through it)
        GltfDoc d = octahedron_doc();
        d.j["extras"] = "DEEP";
        const fs::path file = d.write_gltf(dir, "deep");
        const std::vector<std::uint8_t> written = read_bytes(file);
        std::string text(written.begin(), written.end());
        const std::string deep = std::string(100000, '[') + std::string(100000, ']');
        text.replace(text.find("\"DEEP\""), 6, deep);
        write_text(file, text);
        require_error(sc::import_gltf(file), file.string(), "levels deep");
    }
    {  // glTF version other than 2
        GltfDoc d = octahedron_doc();
        d.j["asset"]["version"] = "3.0";
        expect(d, "version", "only glTF 2.x");
    }
    {  // not JSON at all / empty file
        write_text(dir / "garbage.gltf", "this is not json {");
        require_error(sc::import_gltf(dir / "garbage.gltf"), (dir / "garbage.gltf").string(), "invalid glTF");
        write_text(dir / "empty.gltf", "");
        require_error(sc::import_gltf(dir / "empty.gltf"), (dir / "empty.gltf").string(), "empty");
        require_error(sc::import_gltf(dir / "nope.gltf"), (dir / "nope.gltf").string(), "no such file");
        require_error(sc::import_scene(dir / "x.fbx"), (dir / "x.fbx").string(), "unsupported scene format");
    }
}

TEST_CASE("generated: no scenes imports every root node; the node order is depth-first") {
    GltfDoc d = octahedron_doc();
    d.j.erase("scenes");
    d.j.erase("scene");
    d.j["nodes"][0]["children"] = {1};
    d.add_node({{"mesh", 0}, {"name", "kid"}, {"translation", {0, 5, 0}}}, false);
    d.add_node({{"mesh", 0}, {"name", "second_root"}, {"translation", {5, 0, 0}}}, false);
    const fs::path file = d.write_gltf(fresh_dir("noscene"), "noscene");
    const sc::ImportResult r = sc::import_gltf(file);
    require_ok(r);
    REQUIRE(r.scene.instances.size() == 3);
    CHECK(r.scene.instances[0].node_name == "octa_node");
    CHECK(r.scene.instances[1].node_name == "kid");
    CHECK(r.scene.instances[2].node_name == "second_root");
    CHECK(r.scene.instances[1].transform[7] == 5.0f);
    CHECK(has_warning(r.scene, "no scenes"));
}

TEST_CASE("truncated and corrupted .glb files are rejected without crashing") {
    GltfDoc d = octahedron_doc();
    const std::vector<std::uint8_t> glb = d.glb_bytes();
    REQUIRE(sc::import_gltf_from_memory(glb, kWorkDir, "whole.glb").ok());
    // Every truncation.
    for (std::size_t n = 0; n < glb.size(); ++n) {
        CAPTURE(n);
        const sc::ImportResult r = sc::import_gltf_from_memory(std::span(glb.data(), n), kWorkDir, "cut.glb");
        CHECK_FALSE(r.ok());
        CHECK(r.error.rfind("cut.glb: ", 0) == 0);
    }
    // Cut inside the BIN chunk: buffer 0 declares more than the chunk holds (tinygltf would
    // read past the end of the input for it; found by a differential run under ASan).
    const sc::ImportResult short_bin =
        sc::import_gltf_from_memory(std::span(glb.data(), glb.size() - 5), kWorkDir, "short.glb");
    REQUIRE_FALSE(short_bin.ok());
    CHECK(short_bin.error.find("buffer 0 declares") != std::string::npos);
    // A truncated file on disk, through the public path-based entry point.
    const fs::path dir = fresh_dir("truncated");
    write_bytes(dir / "cut.glb", glb.data(), glb.size() - 7);
    require_error(sc::import_scene(dir / "cut.glb"), (dir / "cut.glb").string(), "invalid binary glTF");
    // Every single-byte corruption: import or error, never a crash or an invalid scene.
    std::size_t accepted = 0;
    for (std::size_t i = 0; i < glb.size(); ++i) {
        for (const std::uint8_t x : {std::uint8_t(0xff), std::uint8_t(0x80), std::uint8_t(0x01)}) {
            std::vector<std::uint8_t> bad = glb;
            bad[i] ^= x;
            const sc::ImportResult r = sc::import_gltf_from_memory(bad, kWorkDir, "flip.glb");
            if (r.ok()) {
                ++accepted;
                CHECK(sc::check_scene(r.scene).empty());
            } else {
                CHECK(r.error.rfind("flip.glb: ", 0) == 0);
            }
        }
    }
    MESSAGE("single-byte corruptions still accepted (e.g. in names or float bits): " << accepted);
}
