// lsnif::scene OBJ / PLY / OFF / STL import: CGAL's data set (libcgal-demo), assimp's test
// models, and small files the test writes itself.
#include "scene_test_util.hpp"

#include <algorithm>
#include <span>
#include <sstream>
#include <string>
#include <utility>

using namespace scene_test;

namespace {

std::array<double, 3> triangle_cross(const sc::Mesh& m, std::size_t t) {
    const float* a = &m.positions[3 * std::size_t(m.indices[3 * t])];
    const float* b = &m.positions[3 * std::size_t(m.indices[3 * t + 1])];
    const float* c = &m.positions[3 * std::size_t(m.indices[3 * t + 2])];
    const double e1[3] = {double(b[0]) - a[0], double(b[1]) - a[1], double(b[2]) - a[2]};
    const double e2[3] = {double(c[0]) - a[0], double(c[1]) - a[1], double(c[2]) - a[2]};
    return {e1[1] * e2[2] - e1[2] * e2[1], e1[2] * e2[0] - e1[0] * e2[2], e1[0] * e2[1] - e1[1] * e2[0]};
}

// "nv nf" from an OFF header (the reference for the CGAL meshes).
std::pair<std::size_t, std::size_t> off_header_counts(const fs::path& path) {
    std::ifstream in(path);
    std::string word;
    in >> word;
    REQUIRE(word == "OFF");
    std::size_t nv = 0, nf = 0;
    in >> nv >> nf;
    return {nv, nf};
}

// Imports a closed mesh centred at the origin and checks that it is convex-outward: every
// face normal and every vertex normal points away from the centre.
void check_outward(const sc::Mesh& m) {
    for (std::size_t t = 0; t < m.triangle_count(); ++t) {
        const auto n = triangle_cross(m, t);
        double centroid[3] = {0, 0, 0};
        for (int k = 0; k < 3; ++k) {
            for (int a = 0; a < 3; ++a)
                centroid[a] +=
                    m.positions[3 * std::size_t(m.indices[3 * t + std::size_t(k)]) + std::size_t(a)];
        }
        CHECK(n[0] * centroid[0] + n[1] * centroid[1] + n[2] * centroid[2] > 0.0);
    }
    for (std::size_t v = 0; v < m.vertex_count(); ++v) {
        const float* n = &m.normals[3 * v];
        const float* p = &m.positions[3 * v];
        CHECK(std::sqrt(double(n[0]) * n[0] + double(n[1]) * n[1] + double(n[2]) * n[2]) ==
              doctest::Approx(1.0).epsilon(1e-6));
        CHECK(n[0] * p[0] + n[1] * p[1] + n[2] * p[2] > 0.0f);
        for (int a = 0; a < 3; ++a) {
            if (p[a] != 0.0f) CHECK((n[a] > 0.0f) == (p[a] > 0.0f));
        }
    }
}

const char* kCubeObj =
    "# unit cube, quads, counter-clockwise seen from outside, no normals\n"
    "v -1 -1 -1\nv 1 -1 -1\nv 1 1 -1\nv -1 1 -1\nv -1 -1 1\nv 1 -1 1\nv 1 1 1\nv -1 1 1\n"
    "f 1 4 3 2\nf 5 6 7 8\nf 1 2 6 5\nf 4 8 7 3\nf 1 5 8 4\nf 2 3 7 6\n";

// Writes each case's text to DIR/STEM<i>EXT and checks that importing it fails with an error
// that names the file and contains the case's expected text.
void check_rejected(const fs::path& dir, const std::string& stem, const std::string& ext,
                    std::span<const std::pair<std::string, std::string>> cases) {
    int k = 0;
    for (const auto& [text, expected] : cases) {
        std::string name = stem;
        name += std::to_string(k++);  // (not stem + to_string(): GCC 12 -Wrestrict false positive)
        const fs::path file = dir / (name + ext);
        write_text(file, text);
        const sc::ImportResult r = sc::import_scene(file);
        CAPTURE(expected);
        REQUIRE_FALSE(r.ok());
        CHECK(r.error.rfind(file.string(), 0) == 0);
        CHECK(r.error.find(expected) != std::string::npos);
    }
}

// Each text, written to DIR/ok.EXT in turn, imports.
void check_imported(const fs::path& dir, const std::string& ext, std::initializer_list<std::string> texts) {
    for (const std::string& text : texts) {
        const fs::path file = dir / ("ok" + ext);
        write_text(file, text);
        const sc::ImportResult r = sc::import_scene(file);
        CHECK_MESSAGE(r.ok(), r.error);
    }
}

}  // namespace

TEST_CASE("CGAL's OFF meshes load with the counts of their headers") {
    for (const char* name : {"ChineseDragon-10kv.off", "armadillo.off"}) {
        CAPTURE(name);
        const fs::path file = kCgalMeshDir / name;
        const auto [nv, nf] = off_header_counts(file);
        const sc::ImportResult r = sc::import_scene(file);
        require_ok(r);
        const sc::Scene& s = r.scene;
        REQUIRE(s.meshes.size() == 1);
        REQUIRE(s.instances.size() == 1);
        const sc::Mesh& m = s.meshes[0];
        CHECK(m.vertex_count() == nv);
        CHECK(m.triangle_count() == nf);  // all faces of these files are triangles
        CHECK(m.name == fs::path(name).stem().string());
        CHECK(s.instances[0].node_name == m.name);
        CHECK(s.instances[0].transform == sc::kIdentityTransform);
        CHECK(m.normal_origin == sc::NormalOrigin::computed);
        CHECK(s.materials == std::vector<std::string>{"default"});
        CHECK(std::all_of(m.triangle_materials.begin(), m.triangle_materials.end(),
                          [](std::uint32_t x) { return x == 0; }));
        CHECK(s.warnings.empty());
    }
    // The dragon's first vertex and face, read from the file by hand.
    const sc::ImportResult r = sc::import_mesh_file(kCgalMeshDir / "ChineseDragon-10kv.off");
    std::ifstream in(kCgalMeshDir / "ChineseDragon-10kv.off");
    std::string word;
    std::size_t nv = 0, nf = 0, ne = 0;
    in >> word >> nv >> nf >> ne;
    float x, y, z;
    in >> x >> y >> z;
    CHECK(r.scene.meshes[0].positions[0] == x);
    CHECK(r.scene.meshes[0].positions[1] == y);
    CHECK(r.scene.meshes[0].positions[2] == z);
    for (std::size_t v = 1; v < nv; ++v) in >> x >> y >> z;
    std::uint32_t n, a, b, c;
    in >> n >> a >> b >> c;
    CHECK(n == 3);
    CHECK(r.scene.meshes[0].indices[0] == a);
    CHECK(r.scene.meshes[0].indices[1] == b);
    CHECK(r.scene.meshes[0].indices[2] == c);
}

TEST_CASE("OBJ: quads triangulated, computed normals unit and outward on a closed convex mesh") {
    const fs::path dir = fresh_dir("obj");
    write_text(dir / "cube.obj", kCubeObj);
    const sc::ImportResult r = sc::import_scene(dir / "cube.obj");
    require_ok(r);
    const sc::Mesh& m = r.scene.meshes[0];
    CHECK(m.vertex_count() == 8);
    CHECK(m.triangle_count() == 12);
    CHECK(m.normal_origin == sc::NormalOrigin::computed);
    check_outward(m);

    // Octahedron: each vertex normal is exactly the vertex direction (4 equal faces).
    std::ostringstream obj;
    const auto p = octahedron_positions();
    const auto idx = octahedron_indices();
    for (std::size_t v = 0; v < p.size(); v += 3)
        obj << "v " << p[v] << ' ' << p[v + 1] << ' ' << p[v + 2] << '\n';
    for (std::size_t t = 0; t < idx.size(); t += 3)
        obj << "f " << idx[t] + 1 << ' ' << idx[t + 1] + 1 << ' ' << idx[t + 2] + 1 << '\n';
    write_text(dir / "octa.obj", obj.str());
    const sc::ImportResult ro = sc::import_scene(dir / "octa.obj");
    require_ok(ro);
    const sc::Mesh& o = ro.scene.meshes[0];
    CHECK(o.indices == idx);
    check_outward(o);
    for (std::size_t i = 0; i < p.size(); ++i) CHECK(o.normals[i] == doctest::Approx(p[i]));

    // compute_vertex_normals on the importer's mesh gives the same normals.
    sc::Mesh copy = o;
    copy.normals.assign(copy.normals.size(), 0.0f);
    sc::compute_vertex_normals(copy);
    CHECK(copy.normals == o.normals);
}

TEST_CASE("OBJ: concave polygons are ear-clipped, non-manifold faces are kept") {
    const fs::path dir = fresh_dir("obj_poly");
    // A dart (concave quad) in the z = 0 plane, counter-clockwise, area 4. A fan around
    // vertex 1 would produce a flipped triangle and total |area| 8.
    write_text(dir / "dart.obj", "v 0 0 0\nv 2 1 0\nv 4 0 0\nv 2 3 0\nf 1 2 3 4\n");
    const sc::ImportResult r = sc::import_mesh_file(dir / "dart.obj");
    require_ok(r);
    const sc::Mesh& m = r.scene.meshes[0];
    REQUIRE(m.triangle_count() == 2);
    double area = 0;
    for (std::size_t t = 0; t < 2; ++t) {
        const auto n = triangle_cross(m, t);
        CHECK(n[2] > 0.0);
        area += 0.5 * n[2];
    }
    CHECK(area == doctest::Approx(4.0));

    // assimp's 64-corner concave polygon: triangle areas add up to the polygon's area and
    // all triangles face the polygon's way.
    const sc::ImportResult rc = sc::import_mesh_file(kAssimpDir / "OBJ/concave_polygon.obj");
    require_ok(rc);
    const sc::Mesh& c = rc.scene.meshes[0];
    CHECK(c.triangle_count() == 62);
    double newell[3] = {0, 0, 0};
    {
        // The polygon is the single face, in file order: recover it from the OBJ text.
        std::ifstream in(kAssimpDir / "OBJ/concave_polygon.obj");
        std::vector<std::array<double, 3>> v;
        std::vector<int> face;
        for (std::string line; std::getline(in, line);) {
            std::istringstream ls(line);
            std::string tag;
            ls >> tag;
            if (tag == "v") {
                std::array<double, 3> p{};
                ls >> p[0] >> p[1] >> p[2];
                v.push_back(p);
            } else if (tag == "f") {
                for (std::string corner; ls >> corner;)
                    face.push_back(std::stoi(corner.substr(0, corner.find('/'))) - 1);
            }
        }
        // The face lists 66 corners: it returns to an edge it already used (31-32) at its end.
        // OpenMesh's OBJ reader drops corners that repeat a vertex of the face, which leaves
        // the 64-corner simple polygon we compare with.
        std::vector<int> simple;
        for (const int c : face) {
            if (std::find(simple.begin(), simple.end(), c) == simple.end()) simple.push_back(c);
        }
        face = simple;
        REQUIRE(face.size() == 64);
        for (std::size_t i = 0; i < face.size(); ++i) {
            const auto& a = v[std::size_t(face[i])];
            const auto& b = v[std::size_t(face[(i + 1) % face.size()])];
            newell[0] += (a[1] - b[1]) * (a[2] + b[2]);
            newell[1] += (a[2] - b[2]) * (a[0] + b[0]);
            newell[2] += (a[0] - b[0]) * (a[1] + b[1]);
        }
    }
    const double polygon_area =
        0.5 * std::sqrt(newell[0] * newell[0] + newell[1] * newell[1] + newell[2] * newell[2]);
    double sum = 0;
    for (std::size_t t = 0; t < c.triangle_count(); ++t) {
        const auto n = triangle_cross(c, t);
        const double a = 0.5 * std::sqrt(n[0] * n[0] + n[1] * n[1] + n[2] * n[2]);
        sum += a;
        if (a > 1e-9 * polygon_area) CHECK(n[0] * newell[0] + n[1] * newell[1] + n[2] * newell[2] > 0.0);
    }
    CHECK(sum == doctest::Approx(polygon_area).epsilon(1e-5));
    CHECK_FALSE(has_warning(rc.scene, "fan-triangulated"));

    // Three triangles on one edge (a "fin") plus a duplicate: a half-edge mesh would drop
    // some; the soup keeps all four.
    write_text(dir / "fin.obj",
               "v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 -1 0\nv 0 0 1\n"
               "f 1 2 3\nf 1 2 4\nf 1 2 5\nf 1 2 3\n");
    const sc::ImportResult rf = sc::import_mesh_file(dir / "fin.obj");
    require_ok(rf);
    CHECK(rf.scene.meshes[0].triangle_count() == 4);
}

TEST_CASE("PLY and STL, ASCII and binary; normals from the file") {
    const fs::path dir = fresh_dir("ply_stl");
    const auto p = octahedron_positions();
    const auto idx = octahedron_indices();
    {  // ASCII PLY with normals of length 3: used (normalized), origin "source"
        std::ostringstream ply;
        ply << "ply\nformat ascii 1.0\nelement vertex 6\nproperty float x\nproperty float y\nproperty float "
               "z\n"
               "property float nx\nproperty float ny\nproperty float nz\nelement face 8\n"
               "property list uchar int vertex_indices\nend_header\n";
        for (std::size_t v = 0; v < 6; ++v) {
            ply << p[3 * v] << ' ' << p[3 * v + 1] << ' ' << p[3 * v + 2] << ' ' << 3 * p[3 * v] << ' '
                << 3 * p[3 * v + 1] << ' ' << 3 * p[3 * v + 2] << '\n';
        }
        for (std::size_t t = 0; t < 8; ++t)
            ply << "3 " << idx[3 * t] << ' ' << idx[3 * t + 1] << ' ' << idx[3 * t + 2] << '\n';
        write_text(dir / "octa.ply", ply.str());
        const sc::ImportResult r = sc::import_scene(dir / "octa.ply");
        require_ok(r);
        const sc::Mesh& m = r.scene.meshes[0];
        CHECK(m.normal_origin == sc::NormalOrigin::source);
        CHECK(m.indices == idx);
        for (std::size_t i = 0; i < p.size(); ++i) CHECK(m.normals[i] == doctest::Approx(p[i]));
    }
    // Binary little-endian PLY: vertices + faces.
    auto binary_ply = [&](const std::vector<float>& xyz, const std::vector<std::uint32_t>& tris) {
        std::string s =
            "ply\nformat binary_little_endian 1.0\nelement vertex " + std::to_string(xyz.size() / 3) +
            "\nproperty float x\nproperty float y\nproperty float z\nelement face " +
            std::to_string(tris.size() / 3) + "\nproperty list uchar int vertex_indices\nend_header\n";
        std::vector<std::uint8_t> out(s.begin(), s.end());
        const auto* fb = reinterpret_cast<const std::uint8_t*>(xyz.data());
        out.insert(out.end(), fb, fb + xyz.size() * 4);
        for (std::size_t t = 0; t < tris.size(); t += 3) {
            out.push_back(3);
            const auto* ib = reinterpret_cast<const std::uint8_t*>(&tris[t]);
            out.insert(out.end(), ib, ib + 12);
        }
        return out;
    };
    {
        const auto bytes = binary_ply(p, idx);
        write_bytes(dir / "octa_bin.ply", bytes.data(), bytes.size());
        const sc::ImportResult r = sc::import_scene(dir / "octa_bin.ply");
        require_ok(r);
        CHECK(r.scene.meshes[0].positions == p);
        CHECK(r.scene.meshes[0].indices == idx);
        check_outward(r.scene.meshes[0]);
    }
    {  // NaN coordinate in a binary PLY
        std::vector<float> bad = p;
        bad[4] = std::nanf("");
        const auto bytes = binary_ply(bad, idx);
        write_bytes(dir / "nan.ply", bytes.data(), bytes.size());
        require_error(sc::import_scene(dir / "nan.ply"), (dir / "nan.ply").string(), "vertex 1 is");
    }
    {  // ASCII STL: OpenMesh merges the facets' repeated corners
        std::ostringstream stl;
        stl << "solid octa\n";
        for (std::size_t t = 0; t < 8; ++t) {
            stl << " facet normal 0 0 0\n  outer loop\n";
            for (int k = 0; k < 3; ++k) {
                const std::size_t v = idx[3 * t + std::size_t(k)];
                stl << "   vertex " << p[3 * v] << ' ' << p[3 * v + 1] << ' ' << p[3 * v + 2] << '\n';
            }
            stl << "  endloop\n endfacet\n";
        }
        stl << "endsolid octa\n";
        write_text(dir / "octa.stl", stl.str());
        const sc::ImportResult r = sc::import_scene(dir / "octa.stl");
        require_ok(r);
        const sc::Mesh& m = r.scene.meshes[0];
        CHECK(m.vertex_count() == 6);
        CHECK(m.triangle_count() == 8);
        CHECK(m.normal_origin == sc::NormalOrigin::computed);  // facet normals are not vertex normals
        check_outward(m);
    }
    // Binary STL: 80-byte header, count, 50 bytes per facet.
    auto binary_stl = [&](const std::vector<float>& xyz) {
        std::vector<std::uint8_t> out(80, ' ');
        const std::uint32_t n = 8;
        out.insert(out.end(), reinterpret_cast<const std::uint8_t*>(&n),
                   reinterpret_cast<const std::uint8_t*>(&n) + 4);
        for (std::size_t t = 0; t < 8; ++t) {
            float rec[12] = {};
            for (int k = 0; k < 3; ++k) {
                for (int a = 0; a < 3; ++a)
                    rec[3 + 3 * k + a] = xyz[3 * idx[3 * t + std::size_t(k)] + std::size_t(a)];
            }
            const auto* b = reinterpret_cast<const std::uint8_t*>(rec);
            out.insert(out.end(), b, b + 48);
            out.push_back(0);
            out.push_back(0);
        }
        return out;
    };
    {
        const auto bytes = binary_stl(p);
        write_bytes(dir / "octa_bin.stl", bytes.data(), bytes.size());
        const sc::ImportResult r = sc::import_scene(dir / "octa_bin.stl");
        require_ok(r);
        CHECK(r.scene.meshes[0].vertex_count() == 6);
        CHECK(r.scene.meshes[0].triangle_count() == 8);
        check_outward(r.scene.meshes[0]);
    }
    {
        std::vector<float> bad = p;
        bad[0] = INFINITY;
        const auto bytes = binary_stl(bad);
        write_bytes(dir / "inf.stl", bytes.data(), bytes.size());
        require_error(sc::import_scene(dir / "inf.stl"), (dir / "inf.stl").string(), "not finite");
    }
    // assimp's own test files.
    for (const char* name : {"PLY/cube.ply", "PLY/cube_binary.ply", "PLY/Wuson.ply", "STL/Spider_binary.stl",
                             "STL/Spider_ascii.stl", "OBJ/box.obj", "OBJ/WusonOBJ.obj", "OFF/Cube.off"}) {
        CAPTURE(name);
        require_ok(sc::import_scene(kAssimpDir / name));
    }
}

TEST_CASE("OFF: comments and polygons; bad files give errors naming the file") {
    const fs::path dir = fresh_dir("off");
    write_text(dir / "cube.off",
               "OFF\n# a cube with quad faces\n8 6 12\n-1 -1 -1\n1 -1 -1\n1 1 -1\n-1 1 -1\n"
               "-1 -1 1\n1 -1 1\n1 1 1\n-1 1 1\n4 0 3 2 1\n4 4 5 6 7\n4 0 1 5 4\n4 3 7 6 2\n"
               "4 0 4 7 3\n4 1 2 6 5\n");
    const sc::ImportResult r = sc::import_scene(dir / "cube.off");
    require_ok(r);
    CHECK(r.scene.meshes[0].triangle_count() == 12);
    check_outward(r.scene.meshes[0]);

    write_text(dir / "range.off", "OFF\n3 1 0\n0 0 0\n1 0 0\n0 1 0\n3 0 1 3\n");
    require_error(sc::import_scene(dir / "range.off"), (dir / "range.off").string(),
                  "face 0 refers to vertex 3, but the file has 3 vertices");
    write_text(dir / "huge.off", "OFF\n4000000000 1 0\n0 0 0\n");
    require_error(sc::import_scene(dir / "huge.off"), (dir / "huge.off").string(), "more than a file of");
    write_text(dir / "huge.ply",
               "ply\nformat ascii 1.0\nelement vertex 900000000000\nproperty float x\nend_header\n");
    require_error(sc::import_scene(dir / "huge.ply"), (dir / "huge.ply").string(), "more than a file of");
    write_text(dir / "noface.off", "OFF\n3 0 0\n0 0 0\n1 0 0\n0 1 0\n");
    require_error(sc::import_scene(dir / "noface.off"), (dir / "noface.off").string(), "no triangles");
    write_text(dir / "short_faces.off", "OFF\n3 2 0\n0 0 0\n1 0 0\n0 1 0\n2 0 1\n1 2\n");
    const sc::ImportResult rs = sc::import_scene(dir / "short_faces.off");
    require_error(rs, (dir / "short_faces.off").string(), "no triangles");
    CHECK(has_warning(rs.scene, "2 faces with fewer than 3 corners skipped"));
    write_text(dir / "empty.off", "");
    require_error(sc::import_scene(dir / "empty.off"), (dir / "empty.off").string(), "empty");
    require_error(sc::import_scene(dir / "missing.off"), (dir / "missing.off").string(), "no such file");
    fs::create_directories(dir / "folder.obj");
    require_error(sc::import_scene(dir / "folder.obj"), (dir / "folder.obj").string(), "not a regular file");

    // assimp's invalid and degenerate files: errors, never crashes.
    for (const char* name :
         {"invalid/OutOfMemory.off", "invalid/empty.off", "invalid/empty.obj", "invalid/empty.ply",
          "invalid/malformed.obj", "OFF/invalid.off", "OBJ/point_cloud.obj", "PLY/points.ply",
          "OBJ/testline.obj", "OBJ/testpoints.obj"}) {
        CAPTURE(name);
        const fs::path file = kAssimpDir / name;
        require_error(sc::import_scene(file), file.string(), "");
    }
}

TEST_CASE("geometry_hash: FNV-1a 64 over counts, positions and indices") {
    sc::Mesh m;
    m.positions = {0, 0, 0, 1, 0, 0, 0, 1, 0};
    m.indices = {0, 1, 2};
    const std::string h = sc::geometry_hash(m);
    // Reference computed here byte by byte from the documented layout.
    std::vector<std::uint8_t> bytes;
    auto put = [&bytes](const void* p, std::size_t n) {
        bytes.insert(bytes.end(), static_cast<const std::uint8_t*>(p),
                     static_cast<const std::uint8_t*>(p) + n);
    };
    const std::uint64_t counts[2] = {3, 1};
    put(counts, 16);
    put(m.positions.data(), 36);
    put(m.indices.data(), 12);
    std::uint64_t ref = 14695981039346656037ull;
    for (const std::uint8_t b : bytes) ref = (ref ^ b) * 1099511628211ull;
    char want[32];
    std::snprintf(want, sizeof want, "fnv1a64:%016llx", static_cast<unsigned long long>(ref));
    CHECK(h == want);
    // Normals, names and materials do not change it; geometry does.
    sc::Mesh n = m;
    n.name = "other";
    n.normals = {0, 0, 1, 0, 0, 1, 0, 0, 1};
    n.triangle_materials = {3};
    CHECK(sc::geometry_hash(n) == h);
    n.indices = {0, 2, 1};
    CHECK(sc::geometry_hash(n) != h);
    n = m;
    n.positions[4] = 1e-7f;
    CHECK(sc::geometry_hash(n) != h);
}

TEST_CASE("check_scene catches broken invariants") {
    sc::Scene s;
    s.materials = {"default"};
    sc::Mesh m;
    m.positions = {0, 0, 0, 1, 0, 0, 0, 1, 0};
    m.indices = {0, 1, 2};
    m.triangle_materials = {0};
    sc::compute_vertex_normals(m);
    s.meshes.push_back(m);
    s.instances.push_back({});
    CHECK(sc::check_scene(s).empty());
    sc::Scene bad = s;
    bad.meshes[0].indices[2] = 3;
    CHECK(sc::check_scene(bad).find("index out of range") != std::string::npos);
    bad = s;
    bad.meshes[0].normals[0] = 2;
    CHECK(sc::check_scene(bad).find("not unit length") != std::string::npos);
    bad = s;
    bad.meshes[0].triangle_materials[0] = 1;
    CHECK(sc::check_scene(bad).find("material index out of range") != std::string::npos);
    bad = s;
    bad.instances[0].transform[3] = NAN;
    CHECK(sc::check_scene(bad).find("transform not finite") != std::string::npos);
    bad = s;
    bad.instances.clear();
    CHECK_FALSE(sc::check_scene(bad).empty());
}

TEST_CASE("PLY headers OpenMesh would hang on are errors: no end_header, bad grammar") {
    const fs::path dir = fresh_dir("ply_headers");
    const std::string props = "element vertex 2\nproperty float x\nproperty float y\nproperty float z\n";
    const std::pair<std::string, std::string> cases[] = {
        // Found by fuzz_import: OpenMesh 9 loops forever when the header never ends.
        {"ply\nformat ascii 1.0\n" + props + "elem int 2 1\n3 0 1 3\n", "no end_header"},
        {"ply\nformat ascii 2.0\n" + props + "end_header\n", "expected 'format"},
        {"ply\nformat ascii 1.0\nelement vertex two\nend_header\n", "expected 'element NAME COUNT'"},
        {"ply\nformat ascii 1.0\nproperty float x\nend_header\n", "property before any element"},
        {"ply\nformat ascii 1.0\nelement vertex 1\nproperty real x\nend_header\n0\n",
         "expected 'property TYPE"},
        {std::string("ply\nformat ascii 1.0\ncomment a") + '\0' + "b\n" + props + "end_header\n",
         "control byte"},
        {"plyx\nformat ascii 1.0\nend_header\n", "must start with a line 'ply'"},
        {"ply\n" + props + "format ascii 1.0\nend_header\n0 0 0\n1 0 0\n",
         "line 2: 'element' before the format line"},
        {"ply\nend_header\n", "'end_header' before the format line"},
        {"ply\nformat ascii 1.0\nformat ascii 1.0\n" + props + "end_header\n0 0 0\n1 0 0\n",
         "a second format line"},
    };
    check_rejected(dir, "h", ".ply", cases);
}

TEST_CASE("PLY element counts beyond OpenMesh's unsigned int are errors, even in a file that large") {
    // OpenMesh reads a count into an unsigned int and, when it does not fit, loops forever on
    // the failed stream. The file is sparse: 5 GB of size, a few bytes on disk, and only its
    // header is read.
    const fs::path file = fresh_dir("ply_huge_count") / "huge.ply";
    write_text(file,
               "ply\nformat binary_little_endian 1.0\nelement vertex 4294967296\nproperty uchar x\n"
               "end_header\n");
    std::error_code ec;
    fs::resize_file(file, 5'000'000'000ull, ec);
    if (ec) {
        MESSAGE("skipped: cannot make a 5 GB sparse file here (" << ec.message() << ")");
        return;
    }
    require_error(sc::import_scene(file), file.string(), "more than 2^32 - 1 'vertex' elements");
    fs::remove(file);
}

TEST_CASE("PLY headers are read as the format defines them, not as OpenMesh reads words") {
    // OpenMesh 9 reads a PLY header word by word: every word of a line it does not know is a
    // keyword to it, it takes the three words after 'ply' for the format, and it finds a
    // binary body 12 bytes past the end of the last word before end_header. Read alone, these
    // files crashed it, hung it, or (a comment or trailing blanks before end_header in a
    // binary file) gave vertices shifted by a byte without an error. Each must import the
    // octahedron it holds, exactly.
    const fs::path dir = fresh_dir("ply_header_words");
    const std::vector<float> p = {1, 0, 0, -1, 0, 0, 0, 1, 0, 0, -1, 0, 0, 0, 1, 0, 0, -1};
    const std::vector<std::uint32_t> idx = {0, 2, 4, 2, 1, 4, 1, 3, 4, 3, 0, 4,
                                            2, 0, 5, 1, 2, 5, 3, 1, 5, 0, 3, 5};
    const std::string vertex = "element vertex 6\nproperty float x\nproperty float y\nproperty float z\n";
    const std::string face = "element face 8\nproperty list uchar int vertex_indices\n";
    std::string binary_body, ascii_body;
    for (std::size_t v = 0; v < 6; ++v) {
        binary_body.append(reinterpret_cast<const char*>(&p[3 * v]), 12);
        ascii_body += std::to_string(int(p[3 * v])) + " " + std::to_string(int(p[3 * v + 1])) + " " +
                      std::to_string(int(p[3 * v + 2])) + "\n";
    }
    for (std::size_t t = 0; t < idx.size(); t += 3) {
        binary_body += char(3);
        binary_body.append(reinterpret_cast<const char*>(&idx[t]), 12);
        ascii_body += "3 " + std::to_string(idx[t]) + " " + std::to_string(idx[t + 1]) + " " +
                      std::to_string(idx[t + 2]) + "\n";
    }
    const std::string bin = "ply\nformat binary_little_endian 1.0\n";
    const std::string asc = "ply\nformat ascii 1.0\n";
    std::string crlf;
    for (const char c : bin + vertex + face + "end_header\n") {
        if (c == '\n') crlf += '\r';
        crlf += c;
    }
    const std::pair<std::string, std::string> files[] = {
        {"comment before end_header",
         bin + vertex + face + "comment written last\nend_header\n" + binary_body},
        {"blanks before end_header", bin + vertex +
                                         "element face 8 \nproperty list uchar int vertex_indices  "
                                         "\nend_header\n" +
                                         binary_body},
        {"CRLF line ends", crlf + binary_body},
        {"a count with leading zeros", bin +
                                           "element vertex 0006\nproperty float x\nproperty float y\n"
                                           "property float z\n" +
                                           face + "end_header\n" + binary_body},
        {"comment before the format line", "ply\ncomment ascii world\nformat binary_little_endian 1.0\n" +
                                               vertex + face + "end_header\n" + binary_body},
        {"keywords inside skipped lines",
         asc + "obj_info element 2 property end_header\nelemeXt vertb property float x\n" + vertex + face +
             "note end_header\nend_header\n" + ascii_body},
        {"format words inside a skipped line",
         asc + "formatx binary_little_endian\n" + vertex + face + "end_header\n" + ascii_body},
        {"an exporter's unprefixed note",
         asc + "Created by some exporter\n" + vertex + face + "end_header\n" + ascii_body},
    };
    for (const auto& [what, text] : files) {
        CAPTURE(what);
        const fs::path file = dir / "octa.ply";
        write_text(file, text);
        const sc::ImportResult r = sc::import_scene(file);
        REQUIRE_MESSAGE(r.ok(), r.error);
        CHECK(r.scene.meshes[0].positions == p);
        CHECK(r.scene.meshes[0].indices == idx);
    }
}

TEST_CASE("PLY lists longer than the rest of the file are errors, not allocations") {
    const fs::path dir = fresh_dir("ply_lists");
    const std::string vertices = "element vertex 3\nproperty float x\nproperty float y\nproperty float z\n";
    const std::string ascii =
        "ply\nformat ascii 1.0\n" + vertices +
        "element face 2\nproperty list uchar int vertex_indices\nend_header\n0 0 0\n1 0 0\n0 1 0\n";
    // Binary: three vertices of 12 bytes, then one face whose list length is `length` (an int).
    const auto binary = [&](const std::string& endian, const std::string& length) {
        std::string b = "ply\nformat " + endian + " 1.0\n" + vertices +
                        "element face 1\nproperty list int int vertex_indices\nend_header\n";
        b += std::string(36, '\0') + length + std::string(12, '\0');
        return b;
    };
    const std::pair<std::string, std::string> bad[] = {
        // Found by fuzz_import: OpenMesh reserved a list of the length it read (gigabytes).
        {ascii + "3 0 2 1\n35555555555555555555555555555555555 0 1 3\n",
         "element 'face' 1 has a list length '35555555555555555555...', not a count"},
        {ascii + "3 0 2 1\n4000000000 0 1 2\n", "list of 4000000000 values, more than the remaining"},
        {ascii + "3 0 2 1\n-1 0 1 2\n", "list length '-1', not a count"},
        {ascii + "3 0 2 1\n9 0 1 2\n", "more than the remaining 7 bytes can hold"},
        {binary("binary_little_endian", std::string("\xff\xff\xff\x7f", 4)), "list of 2147483647 values"},
        {binary("binary_big_endian", std::string("\x00\x00\x00\x04", 4)), "list of 4 values"},
        {binary("binary_little_endian", std::string("\xfd\xff\xff\xff", 4)), "a negative number of values"},
    };
    check_rejected(dir, "l", ".ply", bad);
    // The same files with lists that fit import.
    check_imported(
        dir, ".ply",
        {ascii + "3 0 2 1\n3 0 1 2\n", binary("binary_big_endian", std::string("\x00\x00\x00\x03", 4)),
         binary("binary_little_endian", std::string("\x03\x00\x00\x00", 4))});
}

TEST_CASE("binary OFF is refused with an error, not read as garbage counts") {
    const fs::path dir = fresh_dir("off_binary");
    // The format's layout: big-endian counts (4 vertices, 1 face), then the vertices.
    std::string b = "OFF BINARY\n";
    b += std::string("\0\0\0\x04\0\0\0\x01\0\0\0\0", 12) + std::string(48, '\0');
    b += std::string("\0\0\0\x03\0\0\0\0\0\0\0\x01\0\0\0\x02\0\0\0\0", 20);
    const std::string refused = "binary OFF ('OFF BINARY') is not supported";
    const std::pair<std::string, std::string> cases[] = {
        {b, refused},
        // Found by fuzz_import: bytes after the keyword read as a count of 589 million vertices.
        {"OFF BINARY# >tetrc", refused},
    };
    check_rejected(dir, "binary", ".off", cases);
}

TEST_CASE("OBJ face corners OpenMesh would abort on are errors with the line number") {
    const fs::path dir = fresh_dir("obj_corners");
    const std::string verts = "v 0 0 0\nv 1 0 0\nv 0 1 0\nvn 0 0 1\n";
    // Found by fuzz_import: Debian's OpenMesh asserts (aborts) on a corner without a vertex.
    const std::pair<std::string, std::string> bad[] = {
        {verts + "f /1 2 3\n", "line 5: face corner '/1'"},
        {verts + "f 1 2 0\n", "line 5: face corner '0'"},
        {verts + "f 1 2 3x\n", "face corner '3x'"},
        {verts + "f 1/x 2 3\n", "face corner '1/x'"},
        {verts + "f 1/1/1/1 2 3\n", "face corner '1/1/1/1'"},
        {verts + "f 1//0 2 3\n", "face corner '1//0'"},
        {verts + "f\t\n", "face without corners"},
        // Found by fuzz_import: a form feed or vertical tab separates tokens for OpenMesh too.
        {verts + "f\f/1 3//1 4//1\n", "line 5: face corner '/1'"},
        {verts + "f\v\n", "face without corners"},
    };
    check_rejected(dir, "c", ".obj", bad);
    check_imported(dir, ".obj",
                   {verts + "f 1 2 3\n", verts + "f 1//1 2//1 3//1\n", verts + "vt 0 0\nf 1/1 2/1 3/1/1\n",
                    verts + "f -3 -2 -1\n"});
}

// Corners with an empty texture or normal index, as 3D-printing software writes its
// printer-bed models ("f 1/ 2/ 3/") and other exporters write "1//" or "1/2/": read as the
// indices that are there, as Blender, assimp and tinyobjloader read them.
TEST_CASE("OBJ: corners with an empty texture or normal index read as the indices that are there") {
    const fs::path dir = fresh_dir("obj_empty_parts");
    const std::string verts = "v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\nvt 0 0\nvt 1 0\nvn 0 0 1\n";
    const std::string plain = verts + "f 1 2 3\nf 1 2 4\nf 1 3 4\n";
    const fs::path reference = dir / "plain.obj";
    write_text(reference, plain);
    const sc::ImportResult want = sc::import_scene(reference);
    REQUIRE_MESSAGE(want.ok(), want.error);
    for (const char* const faces :
         {"f 1/ 2/ 3/\nf 1/ 2/ 4/\nf 1/ 3/ 4/\n", "f 1// 2// 3//\nf 1// 2// 4//\nf 1// 3// 4//\n",
          "f 1/1/ 2/2/ 3/1/\nf 1/ 2// 4/2/\nf 1 3/ 4//\n"}) {
        const fs::path file = dir / "bed.obj";
        write_text(file, verts + faces);
        const sc::ImportResult r = sc::import_scene(file);
        CAPTURE(faces);
        REQUIRE_MESSAGE(r.ok(), r.error);
        REQUIRE(r.scene.meshes.size() == 1);
        CHECK(r.scene.meshes[0].triangle_count() == 3);
        CHECK(r.scene.meshes[0].positions == want.scene.meshes[0].positions);
        CHECK(r.scene.meshes[0].indices == want.scene.meshes[0].indices);
    }
}
