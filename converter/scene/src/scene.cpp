// Format-independent parts of lsnif::scene: dispatch, normals, hashing, invariants.
#include "scene_internal.hpp"

#include <bit>
#include <cctype>
#include <cmath>
#include <cstdio>
#include <exception>
#include <new>
#include <string>

namespace lsnif::scene {

namespace detail {

void WarningSink::add(std::string line) {
    if (lines_.size() < kMaxWarnings) {
        lines_.push_back(std::move(line));
    } else {
        ++dropped_;
    }
}

void WarningSink::finish(std::vector<std::string>& out) {
    for (auto& line : lines_) out.push_back(std::move(line));
    if (dropped_ != 0) {
        out.push_back(std::to_string(dropped_) + " more warnings not shown");
    }
    lines_.clear();
    dropped_ = 0;
}

std::string quote_name(std::string_view name) {
    if (name.empty()) return {};
    std::string out = " '";
    out.append(name);
    out += '\'';
    return out;
}

std::string regular_file_size(const std::filesystem::path& path, std::uintmax_t& size) {
    std::error_code ec;
    if (!std::filesystem::is_regular_file(path, ec))
        return std::filesystem::exists(path, ec) ? "not a regular file" : "cannot open (no such file)";
    size = std::filesystem::file_size(path, ec);
    if (ec) return "cannot read its size: " + ec.message();
    return {};
}

std::string lower_extension(const std::string& path) {
    const auto slash = path.find_last_of('/');
    const auto dot = path.find_last_of('.');
    if (dot == std::string::npos || (slash != std::string::npos && dot < slash)) return {};
    std::string ext = path.substr(dot);
    for (char& c : ext) c = char(std::tolower(static_cast<unsigned char>(c)));
    return ext;
}

namespace {

// Area-weighted vertex normal sums (see compute_vertex_normals), in double.
std::vector<double> weighted_normal_sums(const Mesh& mesh) {
    std::vector<double> sums(mesh.positions.size(), 0.0);
    const float* p = mesh.positions.data();
    for (std::size_t t = 0; t < mesh.triangle_count(); ++t) {
        const std::uint32_t i0 = mesh.indices[3 * t], i1 = mesh.indices[3 * t + 1],
                            i2 = mesh.indices[3 * t + 2];
        double e1[3], e2[3];
        for (int a = 0; a < 3; ++a) {
            e1[a] = double(p[3 * i1 + a]) - double(p[3 * i0 + a]);
            e2[a] = double(p[3 * i2 + a]) - double(p[3 * i0 + a]);
        }
        // |e1 x e2| = 2 * area: summing the raw cross products weights by area.
        const double n[3] = {e1[1] * e2[2] - e1[2] * e2[1], e1[2] * e2[0] - e1[0] * e2[2],
                             e1[0] * e2[1] - e1[1] * e2[0]};
        for (const std::uint32_t v : {i0, i1, i2}) {
            for (int a = 0; a < 3; ++a) sums[3 * std::size_t(v) + a] += n[a];
        }
    }
    return sums;
}

// Writes the unit vector along (x, y, z) to out; false when it has no direction.
bool store_unit(double x, double y, double z, float* out) {
    const double len = std::sqrt(x * x + y * y + z * z);
    if (!(len > 0.0) || !std::isfinite(len)) return false;
    out[0] = float(x / len);
    out[1] = float(y / len);
    out[2] = float(z / len);
    return true;
}

void store_computed(const std::vector<double>& sums, std::size_t v, float* out) {
    if (!store_unit(sums[3 * v], sums[3 * v + 1], sums[3 * v + 2], out)) {
        out[0] = 0.0f;
        out[1] = 0.0f;
        out[2] = 1.0f;
    }
}

}  // namespace

void finalize_normals(Mesh& mesh, const std::vector<std::uint8_t>& has_source_normal, std::string_view what,
                      WarningSink& warnings) {
    const std::size_t n = mesh.vertex_count();
    mesh.normals.resize(3 * n);
    std::vector<double> sums;
    bool sums_ready = false;
    std::size_t from_source = 0, unusable = 0;
    for (std::size_t v = 0; v < n; ++v) {
        float* out = &mesh.normals[3 * v];
        if (has_source_normal[v] != 0 && store_unit(out[0], out[1], out[2], out)) {
            ++from_source;
            continue;
        }
        if (has_source_normal[v] != 0) ++unusable;
        if (!sums_ready) {
            sums = weighted_normal_sums(mesh);
            sums_ready = true;
        }
        store_computed(sums, v, out);
    }
    if (unusable != 0) {
        warnings.add(std::string(what) + ": " + std::to_string(unusable) +
                     " vertex normals in the file are zero or not finite; computed instead");
    }
    mesh.normal_origin = from_source == n   ? NormalOrigin::source
                         : from_source == 0 ? NormalOrigin::computed
                                            : NormalOrigin::mixed;
}

}  // namespace detail

void compute_vertex_normals(Mesh& mesh) {
    const std::vector<double> sums = detail::weighted_normal_sums(mesh);
    mesh.normals.resize(mesh.positions.size());
    for (std::size_t v = 0; v < mesh.vertex_count(); ++v) {
        detail::store_computed(sums, v, &mesh.normals[3 * v]);
    }
    mesh.normal_origin = NormalOrigin::computed;
}

std::string geometry_hash(const Mesh& mesh) {
    static_assert(std::endian::native == std::endian::little,
                  "geometry_hash hashes the in-memory little-endian representation");
    std::uint64_t h = 0xcbf29ce484222325ull;  // FNV-1a 64 offset basis
    auto feed = [&h](const void* data, std::size_t size) {
        const auto* bytes = static_cast<const unsigned char*>(data);
        for (std::size_t i = 0; i < size; ++i) {
            h ^= bytes[i];
            h *= 0x100000001b3ull;  // FNV-1a 64 prime
        }
    };
    const std::uint64_t counts[2] = {mesh.vertex_count(), mesh.triangle_count()};
    feed(counts, sizeof counts);
    feed(mesh.positions.data(), mesh.vertex_count() * 3 * sizeof(float));
    feed(mesh.indices.data(), mesh.triangle_count() * 3 * sizeof(std::uint32_t));
    char text[8 + 16 + 1];
    std::snprintf(text, sizeof text, "fnv1a64:%016llx", static_cast<unsigned long long>(h));
    return text;
}

std::string check_scene(const Scene& scene) {
    if (scene.materials.empty()) return "no materials (materials[0] must be the default)";
    if (scene.meshes.empty()) return "no meshes";
    if (scene.instances.empty()) return "no instances";
    std::vector<std::uint8_t> instanced(scene.meshes.size(), 0);
    for (std::size_t i = 0; i < scene.instances.size(); ++i) {
        const Instance& inst = scene.instances[i];
        const std::string where = "instance " + std::to_string(i) + detail::quote_name(inst.node_name);
        if (inst.mesh >= scene.meshes.size()) return where + ": mesh index out of range";
        instanced[inst.mesh] = 1;
        for (const float x : inst.transform) {
            if (!std::isfinite(x)) return where + ": transform not finite";
        }
    }
    for (std::size_t m = 0; m < scene.meshes.size(); ++m) {
        const Mesh& mesh = scene.meshes[m];
        const std::string where = "mesh " + std::to_string(m) + detail::quote_name(mesh.name);
        if (!instanced[m]) return where + ": not instanced";
        if (mesh.positions.empty() || mesh.positions.size() % 3 != 0)
            return where + ": positions size is not a positive multiple of 3";
        if (mesh.vertex_count() > 0xffffffffull) return where + ": more than 2^32 - 1 vertices";
        if (mesh.indices.empty() || mesh.indices.size() % 3 != 0)
            return where + ": indices size is not a positive multiple of 3";
        if (mesh.normals.size() != mesh.positions.size()) return where + ": normals size differs";
        if (mesh.triangle_materials.size() != mesh.triangle_count())
            return where + ": triangle_materials size differs from the triangle count";
        for (const float x : mesh.positions) {
            if (!std::isfinite(x)) return where + ": position not finite";
        }
        for (const std::uint32_t i : mesh.indices) {
            if (i >= mesh.vertex_count()) return where + ": index out of range";
        }
        for (const std::uint32_t mat : mesh.triangle_materials) {
            if (mat >= scene.materials.size()) return where + ": material index out of range";
        }
        for (std::size_t v = 0; v < mesh.vertex_count(); ++v) {
            const double x = mesh.normals[3 * v], y = mesh.normals[3 * v + 1], z = mesh.normals[3 * v + 2];
            const double len = std::sqrt(x * x + y * y + z * z);
            if (!(std::fabs(len - 1.0) <= 1e-5))
                return where + ": normal of vertex " + std::to_string(v) + " is not unit length";
        }
    }
    return {};
}

bool is_scene_file(const std::filesystem::path& path) {
    try {
        const std::string ext = detail::lower_extension(path.string());
        for (const char* e : {".gltf", ".glb", ".obj", ".ply", ".off", ".stl"})
            if (ext == e) return true;
    } catch (const std::exception&) {
    }
    return false;
}

ImportResult import_scene(const std::filesystem::path& path) {
    std::string ext;
    try {
        ext = detail::lower_extension(path.string());
    } catch (const std::exception& e) {
        return {{}, std::string("scene path: ") + e.what()};
    }
    if (ext == ".gltf" || ext == ".glb") return import_gltf(path);
    if (ext == ".obj" || ext == ".ply" || ext == ".off" || ext == ".stl") {
        return import_mesh_file(path);
    }
    return {{},
            path.string() + ": unsupported scene format '" + ext +
                "' (supported: .gltf .glb .obj .ply .off .stl)"};
}

}  // namespace lsnif::scene
