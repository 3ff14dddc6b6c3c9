#include <lsnif/converter/json_schema.hpp>

#include <cmath>
#include <regex>
#include <set>

namespace lsnif::converter {

using nlohmann::json;

namespace {

const std::set<std::string>& known_keywords() {
    static const std::set<std::string> k = {"$schema",
                                            "$id",
                                            "$comment",
                                            "title",
                                            "description",
                                            "$defs",
                                            "$ref",
                                            "type",
                                            "enum",
                                            "const",
                                            "properties",
                                            "required",
                                            "additionalProperties",
                                            "items",
                                            "minItems",
                                            "maxItems",
                                            "minimum",
                                            "maximum",
                                            "exclusiveMinimum",
                                            "exclusiveMaximum",
                                            "minLength",
                                            "maxLength",
                                            "pattern",
                                            "oneOf",
                                            "anyOf",
                                            "default",
                                            "examples"};
    return k;
}

std::string check_schema(const json& s, const std::string& where) {
    if (s.is_boolean()) return {};
    if (!s.is_object()) return where + ": a schema must be an object or a boolean";
    for (const auto& [key, value] : s.items()) {
        if (!known_keywords().count(key))
            return where + ": keyword '" + key + "' is not supported by lsnif's validator";
        if (key == "properties" || key == "$defs") {
            if (!value.is_object()) return where + "/" + key + ": must be an object";
            for (const auto& [name, sub] : value.items())
                if (auto e = check_schema(sub, where + "/" + key + "/" + name); !e.empty()) return e;
        } else if (key == "items" || key == "additionalProperties") {
            if (auto e = check_schema(value, where + "/" + key); !e.empty()) return e;
        } else if (key == "oneOf" || key == "anyOf") {
            if (!value.is_array() || value.empty()) return where + "/" + key + ": must be a non-empty array";
            for (std::size_t i = 0; i < value.size(); ++i)
                if (auto e = check_schema(value[i], where + "/" + key + "/" + std::to_string(i)); !e.empty())
                    return e;
        } else if (key == "$ref") {
            if (!value.is_string() || value.get<std::string>().rfind("#/$defs/", 0) != 0)
                return where + ": $ref must be a string of the form #/$defs/NAME";
        } else if (key == "pattern") {
            try {
                std::regex re(value.get<std::string>(), std::regex::ECMAScript);
            } catch (const std::exception&) {
                return where + ": pattern is not a valid regular expression";
            }
        }
    }
    return {};
}

bool type_matches(const json& v, const std::string& t) {
    if (t == "object") return v.is_object();
    if (t == "array") return v.is_array();
    if (t == "string") return v.is_string();
    if (t == "boolean") return v.is_boolean();
    if (t == "null") return v.is_null();
    if (t == "number") return v.is_number();
    if (t == "integer")
        return v.is_number_integer() || (v.is_number_float() && std::isfinite(v.get<double>()) &&
                                         v.get<double>() == std::floor(v.get<double>()));
    return false;
}

std::string escape_pointer(const std::string& key) {
    std::string out;
    for (char c : key) {
        if (c == '~')
            out += "~0";
        else if (c == '/')
            out += "~1";
        else
            out += c;
    }
    return out;
}

struct Validator {
    const json& root;
    std::vector<SchemaViolation>& out;
    int depth = 0;

    void fail(const std::string& ptr, std::string msg) { out.push_back({ptr, std::move(msg)}); }

    // Validates `v`, at JSON pointer `ptr`, against schema `s`, appending every violation
    // to `out` in keyword order. Gives up with one violation past 64 nested schemas.
    void run(const json& s, const json& v, const std::string& ptr) {
        if (s.is_boolean()) {
            if (!s.get<bool>()) fail(ptr, "is not allowed here");
            return;
        }
        if (++depth > 64) {  // a $ref cycle in the schema; never hang
            fail(ptr, "schema nesting too deep");
            --depth;
            return;
        }
        if (auto it = s.find("$ref"); it != s.end()) check_ref(it->get<std::string>().substr(8), v, ptr);
        if (!check_type(s, v, ptr)) {
            --depth;
            return;  // the remaining keywords would only repeat the mismatch
        }
        if (auto it = s.find("const"); it != s.end() && v != *it) fail(ptr, "must equal " + it->dump());
        if (auto it = s.find("enum"); it != s.end()) {
            bool found = false;
            for (const auto& e : *it) found = found || e == v;
            if (!found) fail(ptr, "must be one of " + it->dump());
        }
        if (v.is_number()) check_number(s, v.get<double>(), ptr);
        if (v.is_string()) check_string(s, v.get_ref<const std::string&>(), ptr);
        if (v.is_array()) check_array(s, v, ptr);
        if (v.is_object()) check_object(s, v, ptr);
        check_alternatives(s, v, ptr);
        --depth;
    }

    // "$ref": `v` against root's $defs entry `name`, which check_schema cannot prove exists.
    void check_ref(const std::string& name, const json& v, const std::string& ptr) {
        const auto defs = root.find("$defs");
        if (defs == root.end() || !defs->contains(name))
            fail(ptr, "schema $ref '" + name + "' is undefined");
        else
            run((*defs)[name], v, ptr);
    }

    // "type", a name or an array of names: false, after one violation, when `v` has none
    // of them; true when it has one or `s` says no type.
    bool check_type(const json& s, const json& v, const std::string& ptr) {
        const auto it = s.find("type");
        if (it == s.end()) return true;
        bool ok = false;
        std::string names;
        if (it->is_array()) {
            for (const auto& t : *it) {
                ok = ok || type_matches(v, t.get<std::string>());
                names += (names.empty() ? "" : " or ") + t.get<std::string>();
            }
        } else {
            ok = type_matches(v, it->get<std::string>());
            names = it->get<std::string>();
        }
        if (!ok) fail(ptr, "must be of type " + names + ", found " + std::string(v.type_name()));
        return ok;
    }

    // The bounds on a number: minimum, maximum, exclusiveMinimum, exclusiveMaximum.
    void check_number(const json& s, double x, const std::string& ptr) {
        if (auto it = s.find("minimum"); it != s.end() && x < it->get<double>())
            fail(ptr, "must be >= " + it->dump());
        if (auto it = s.find("maximum"); it != s.end() && x > it->get<double>())
            fail(ptr, "must be <= " + it->dump());
        if (auto it = s.find("exclusiveMinimum"); it != s.end() && x <= it->get<double>())
            fail(ptr, "must be > " + it->dump());
        if (auto it = s.find("exclusiveMaximum"); it != s.end() && x >= it->get<double>())
            fail(ptr, "must be < " + it->dump());
    }

    // minLength, maxLength and pattern on a string.
    void check_string(const json& s, const std::string& str, const std::string& ptr) {
        // Length in code points, as the JSON Schema spec defines it.
        std::size_t cps = 0;
        for (unsigned char c : str) cps += (c & 0xC0) != 0x80;
        if (auto it = s.find("minLength"); it != s.end() && cps < it->get<std::size_t>())
            fail(ptr, "must have at least " + it->dump() + " characters");
        if (auto it = s.find("maxLength"); it != s.end() && cps > it->get<std::size_t>())
            fail(ptr, "must have at most " + it->dump() + " characters");
        if (auto it = s.find("pattern"); it != s.end()) {
            std::regex re(it->get<std::string>(), std::regex::ECMAScript);
            if (!std::regex_search(str, re)) fail(ptr, "must match the pattern " + it->dump());
        }
    }

    // minItems and maxItems on array `v`, then each item against "items".
    void check_array(const json& s, const json& v, const std::string& ptr) {
        if (auto it = s.find("minItems"); it != s.end() && v.size() < it->get<std::size_t>())
            fail(ptr, "must have at least " + it->dump() + " items");
        if (auto it = s.find("maxItems"); it != s.end() && v.size() > it->get<std::size_t>())
            fail(ptr, "must have at most " + it->dump() + " items");
        if (auto it = s.find("items"); it != s.end())
            for (std::size_t i = 0; i < v.size(); ++i) run(*it, v[i], ptr + "/" + std::to_string(i));
    }

    // "required" on object `v`, then each member against its "properties" schema, or
    // against "additionalProperties" when it has none (false: any such member fails).
    void check_object(const json& s, const json& v, const std::string& ptr) {
        if (auto it = s.find("required"); it != s.end())
            for (const auto& name : *it)
                if (!v.contains(name.get<std::string>()))
                    fail(ptr, "is missing the required property '" + name.get<std::string>() + "'");
        const auto props = s.find("properties");
        const auto extra = s.find("additionalProperties");
        for (const auto& [key, value] : v.items()) {
            const std::string child = ptr + "/" + escape_pointer(key);
            if (props != s.end() && props->contains(key))
                run((*props)[key], value, child);
            else if (extra != s.end()) {
                if (extra->is_boolean() && !extra->get<bool>())
                    fail(child, "is not a known property");
                else
                    run(*extra, value, child);
            }
        }
    }

    // oneOf (exactly one alternative matches) and anyOf (at least one does). The
    // alternatives' own violations are not reported, only the count.
    void check_alternatives(const json& s, const json& v, const std::string& ptr) {
        for (const char* kw : {"oneOf", "anyOf"}) {
            const auto it = s.find(kw);
            if (it == s.end()) continue;
            int matches = 0;
            for (const auto& alt : *it) {
                std::vector<SchemaViolation> scratch;
                Validator sub{root, scratch, depth};
                sub.run(alt, v, ptr);
                matches += scratch.empty();
            }
            if (std::string(kw) == "oneOf" && matches != 1)
                fail(ptr, "must match exactly one alternative (matched " + std::to_string(matches) + ")");
            if (std::string(kw) == "anyOf" && matches == 0) fail(ptr, "must match at least one alternative");
        }
    }
};

}  // namespace

JsonSchema::JsonSchema(const std::string& schema_text) {
    try {
        root_ = json::parse(schema_text);
    } catch (const json::parse_error& e) {
        error_ = std::string("schema is not valid JSON: ") + e.what();
        return;
    }
    error_ = check_schema(root_, "#");
}

std::vector<SchemaViolation> JsonSchema::validate(const json& instance) const {
    std::vector<SchemaViolation> out;
    if (!valid()) {
        out.push_back({"", "schema unusable: " + error_});
        return out;
    }
    Validator{root_, out}.run(root_, instance, "");
    return out;
}

const JsonSchema& metadata_schema() {
    static const JsonSchema schema(metadata_schema_text());
    return schema;
}

const JsonSchema& manifest_schema() {
    static const JsonSchema schema(manifest_schema_text());
    return schema;
}

const JsonSchema& gltf_extension_schema() {
    static const JsonSchema schema(gltf_extension_schema_text());
    return schema;
}

}  // namespace lsnif::converter
