// mesh::check: every rule on its own, in the documented order, with the message a user sees.
#include <lsnif/mesh/mesh.hpp>

#include <doctest/doctest.h>

#include <cmath>
#include <limits>
#include <vector>

using lsnif::mesh::check;
using lsnif::mesh::MeshView;
using lsnif::mesh::Normals;

namespace {

// Two triangles sharing an edge (a unit square in z = 0), with normals and materials.
struct Square {
    std::vector<float> positions{0, 0, 0, 1, 0, 0, 1, 1, 0, 0, 1, 0};
    std::vector<std::uint32_t> indices{0, 1, 2, 0, 2, 3};
    std::vector<float> normals{0, 0, 1, 0, 0, 1, 0, 0, 1, 0, 0, 1};
    std::vector<std::uint32_t> materials{0, 1};
    MeshView view() const { return {positions, indices, normals, materials}; }
};

}  // namespace

TEST_CASE("a well-formed mesh passes, with or without the optional arrays") {
    const Square s;
    CHECK(check(s.view()).empty());
    CHECK(check(s.view(), Normals::required).empty());
    CHECK(check({s.positions, s.indices}).empty());
    CHECK(check(MeshView{}).empty());  // empty is the caller's business
}

TEST_CASE("each rule fails on its own, naming what is wrong") {
    Square s;
    SUBCASE("sizes") {
        s.positions.pop_back();
        CHECK(check(s.view()) == "positions: 11 floats is not a multiple of 3");
        s = Square{};
        s.indices.pop_back();
        CHECK(check(s.view()) == "indices: 5 indices is not a multiple of 3");
    }
    SUBCASE("non-finite positions, referenced or not") {
        s.positions[4] = std::numeric_limits<float>::quiet_NaN();
        CHECK(check(s.view()) == "vertex 1: coordinate y is NaN");
        s.positions[4] = 0;
        s.positions.insert(s.positions.end(), {0, 0, -INFINITY});  // vertex 4, unreferenced
        s.normals.insert(s.normals.end(), {0, 0, 1});
        CHECK(check(s.view()) == "vertex 4: coordinate z is infinite");
    }
    SUBCASE("indices in range") {
        s.indices[4] = 4;
        CHECK(check(s.view()) == "triangle 1: index 4 is out of range (4 vertices)");
    }
    SUBCASE("normals: optional but whole when given, required when asked") {
        s.normals.resize(9);
        CHECK(check(s.view()) == "normals: 9 floats, expected one xyz per vertex (12)");
        s.normals.clear();
        CHECK(check(s.view()).empty());
        CHECK(check(s.view(), Normals::required) == "normals: 0 floats, expected one xyz per vertex (12)");
        s = Square{};
        s.normals[11] = std::numeric_limits<float>::infinity();
        CHECK(check(s.view()) == "normal 3: coordinate z is infinite");
    }
    SUBCASE("materials: none or one per triangle") {
        s.materials.push_back(0);
        CHECK(check(s.view()) == "materials: 3 entries, expected none or one per triangle (2)");
    }
    SUBCASE("the first problem in the documented order wins") {
        s.indices[0] = 9;
        s.positions[0] = std::numeric_limits<float>::quiet_NaN();
        CHECK(check(s.view()) == "vertex 0: coordinate x is NaN");
    }
}
