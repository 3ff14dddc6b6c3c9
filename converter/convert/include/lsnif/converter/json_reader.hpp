// Strict reading of the JSON documents lsnif writes (manifest entries, cache records, plans):
// every field present and of its type, the first problem named by its path
// ("stats.bvh_bytes: missing"): the codec of a mesh's outcome (outcome.cpp) and the library's
// plan (lsnif::library) read with it.
#pragma once

#include <nlohmann/json.hpp>

#include <array>
#include <cstdint>
#include <limits>
#include <optional>
#include <string>
#include <type_traits>
#include <vector>

namespace lsnif::converter::json_reader {

using nlohmann::json;

// Reads the fields of one JSON object strictly; the first problem is kept, naming the field
// by its path ("stats.bvh_bytes: missing").
class Reader {
public:
    Reader(const json& j, std::string where) : j_(j), where_(std::move(where)) {
        if (!j_.is_object()) fail("", "not an object");
    }
    bool ok() const { return error_.empty(); }
    const std::string& error() const { return error_; }
    std::string path(const char* key) const { return where_ + key; }
    void fail(const std::string& key, const std::string& what) {
        if (!error_.empty()) return;
        std::string path = where_ + key;
        if (key.empty() && !path.empty()) path.pop_back();  // the record itself: "stats", not "stats."
        error_ = path.empty() ? what : path + ": " + what;
    }
    bool has(const char* key) const { return ok() && j_.contains(key); }
    // The value of `key`, or null (after recording the problem) when it is missing.
    const json& at(const char* key) {
        static const json null;
        if (!ok()) return null;
        if (!j_.contains(key)) {
            fail(key, "missing");
            return null;
        }
        return j_[key];
    }
    template <class T>
    void read(const char* key, T& out) {
        const json& v = at(key);
        if (ok()) convert(key, v, out);
    }
    template <class T>
    void read(const char* key, std::optional<T>& out) {
        if (!has(key)) return;
        T v{};
        read(key, v);
        out = std::move(v);
    }
    // A nested record, read by `f(Reader&)` with this path as its prefix.
    template <class F>
    void nested(const char* key, F&& f) {
        const json& v = at(key);
        if (!ok()) return;
        Reader inner(v, where_ + key + ".");
        f(inner);
        if (!inner.ok()) error_ = inner.error();
    }
    // An array of records, each read by `f(Reader&, T&)`.
    template <class T, class F>
    void records(const char* key, std::vector<T>& out, F&& f) {
        const json& v = at(key);
        if (!ok()) return;
        if (!v.is_array()) return fail(key, "not an array");
        for (std::size_t i = 0; i < v.size() && ok(); ++i) {
            Reader inner(v[i], where_ + key + "[" + std::to_string(i) + "].");
            f(inner, out.emplace_back());
            if (!inner.ok()) error_ = inner.error();
        }
    }

private:
    void convert(const char* key, const json& v, double& out) {
        if (!v.is_number()) return fail(key, "not a number");
        out = v.get<double>();
    }
    void convert(const char* key, const json& v, float& out) {
        if (!v.is_number()) return fail(key, "not a number");
        out = v.get<float>();
    }
    template <class T>
    requires std::is_unsigned_v<T> &&
        (!std::is_same_v<T, bool>)void convert(const char* key, const json& v, T& out) {
        if (!v.is_number_unsigned() || v.get<std::uint64_t>() > std::numeric_limits<T>::max())
            return fail(key, "not a whole number in range");
        out = v.get<T>();
    }
    void convert(const char* key, const json& v, bool& out) {
        if (!v.is_boolean()) return fail(key, "not true or false");
        out = v.get<bool>();
    }
    void convert(const char* key, const json& v, std::string& out) {
        if (!v.is_string()) return fail(key, "not a string");
        out = v.get<std::string>();
    }
    template <class T>
    void convert(const char* key, const json& v, std::vector<T>& out) {
        if (!v.is_array()) return fail(key, "not an array");
        out.assign(v.size(), T{});
        for (std::size_t i = 0; i < v.size() && ok(); ++i)
            convert((std::string(key) + "[" + std::to_string(i) + "]").c_str(), v[i], out[i]);
    }
    void convert(const char* key, const json& v, std::array<float, 3>& out) {
        if (!v.is_array() || v.size() != 3) return fail(key, "not 3 numbers");
        for (std::size_t i = 0; i < 3 && ok(); ++i) convert(key, v[i], out[i]);
    }

    const json& j_;
    std::string where_;
    std::string error_;
};

}  // namespace lsnif::converter::json_reader
