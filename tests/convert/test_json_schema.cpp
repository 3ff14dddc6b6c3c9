// The JSON Schema validator (json_schema.hpp) and the schemas it loads.
#include <doctest/doctest.h>

#include <lsnif/converter/json_schema.hpp>

using namespace lsnif::converter;
using nlohmann::json;

TEST_CASE("json schema: types, required, additionalProperties, ranges, patterns, refs") {
    JsonSchema s(R"({
      "type": "object", "required": ["a"], "additionalProperties": false,
      "properties": {
        "a": {"type": "integer", "minimum": 1, "maximum": 3},
        "b": {"type": "array", "items": {"$ref": "#/$defs/name"}, "maxItems": 2},
        "c": {"enum": ["x", "y"]},
        "d": {"type": ["number", "null"], "exclusiveMinimum": 0}
      },
      "$defs": {"name": {"type": "string", "pattern": "^[a-z]+$", "maxLength": 3}}
    })");
    REQUIRE(s.valid());
    CHECK(s.validate(json::parse(R"({"a": 2, "b": ["ab"], "c": "x", "d": null})")).empty());
    CHECK(s.validate(json::parse(R"({"a": 2.0})")).empty());  // integral number is an integer
    auto v = s.validate(json::parse(R"({"b": ["AB", "abcd", "x"], "c": "z", "d": 0, "e": 1})"));
    std::vector<std::string> ptrs;
    for (auto& x : v) ptrs.push_back(x.pointer + " " + x.message);
    REQUIRE(v.size() == 7);
    CHECK(ptrs[0] == " is missing the required property 'a'");
    CHECK(ptrs[1] == "/b must have at most 2 items");
    CHECK(ptrs[2] == "/b/0 must match the pattern \"^[a-z]+$\"");
    CHECK(ptrs[3] == "/b/1 must have at most 3 characters");
    CHECK(ptrs[4] == "/c must be one of [\"x\",\"y\"]");
    CHECK(ptrs[5] == "/d must be > 0");
    CHECK(ptrs[6] == "/e is not a known property");
    CHECK(s.validate(json::parse(R"({"a": 1.5})")).size() == 1);
    CHECK(s.validate(json::parse(R"([1])")).size() == 1);
}

TEST_CASE("json schema: unsupported keywords and bad refs are schema errors, not silent passes") {
    CHECK_FALSE(JsonSchema(R"({"type": "object", "dependentRequired": {}})").valid());
    CHECK_FALSE(JsonSchema(R"({"$ref": "other.json#/x"})").valid());
    CHECK_FALSE(JsonSchema(R"({"pattern": "("})").valid());
    CHECK_FALSE(JsonSchema("{not json").valid());
}

TEST_CASE("the metadata schema loads and accepts the golden metadata") {
    REQUIRE_MESSAGE(metadata_schema().valid(), metadata_schema().error());
}
