// What lsnif::render's sources share: the small float vector algebra of the renders and the
// tracers' state behind EvalScene. Private to lsnif::render (its src/ directory is no
// include directory of any other target).
#pragma once

#include <lsnif/base/triangle_hit.hpp>
#include <lsnif/render/scene.hpp>

#include <embree3/rtcore.h>

#include <algorithm>
#include <array>
#include <atomic>
#include <cmath>
#include <cstdint>
#include <span>
#include <string>
#include <vector>

namespace lsnif::render {

using Vec3 = std::array<float, 3>;
inline Vec3 operator+(Vec3 a, Vec3 b) {
    return {a[0] + b[0], a[1] + b[1], a[2] + b[2]};
}
inline Vec3 operator-(Vec3 a, Vec3 b) {
    return {a[0] - b[0], a[1] - b[1], a[2] - b[2]};
}
inline Vec3 operator*(Vec3 a, float s) {
    return {a[0] * s, a[1] * s, a[2] * s};
}
inline Vec3 mul(Vec3 a, Vec3 b) {
    return {a[0] * b[0], a[1] * b[1], a[2] * b[2]};
}
inline float dot(Vec3 a, Vec3 b) {
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
}
inline Vec3 cross(Vec3 a, Vec3 b) {
    return {a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]};
}
inline float length(Vec3 a) {
    return std::sqrt(dot(a, a));
}
inline Vec3 normalize(Vec3 a) {
    const float l = length(a);
    return l > 0.0f ? a * (1.0f / l) : Vec3{0.0f, 0.0f, 1.0f};
}

using Affine = std::array<float, 12>;  // 3x4 row-major [A | b]

inline Vec3 apply_point(const Affine& m, Vec3 p) {
    return {m[0] * p[0] + m[1] * p[1] + m[2] * p[2] + m[3], m[4] * p[0] + m[5] * p[1] + m[6] * p[2] + m[7],
            m[8] * p[0] + m[9] * p[1] + m[10] * p[2] + m[11]};
}

inline Vec3 apply_normal(const std::array<float, 9>& n, Vec3 v) {
    return normalize({n[0] * v[0] + n[1] * v[1] + n[2] * v[2], n[3] * v[0] + n[4] * v[1] + n[5] * v[2],
                      n[6] * v[0] + n[7] * v[1] + n[8] * v[2]});
}

// Bounds (min xyz, max xyz) of positions (xyz per vertex).
std::array<float, 6> bounds_of(std::span<const float> positions);

struct EvalScene::Impl {
    struct Mesh {
        std::vector<float> positions, normals;
        std::vector<std::uint32_t> indices;
        RTCScene scene = nullptr;
        lsnif_model* model = nullptr;  // the mesh's asset, when it has one
        std::string name;
        std::uint64_t bvh_bytes = 0;
        std::uint64_t lsnif_bytes = 0;  // the opened asset's resident bytes (lsnif_info.decoded_bytes)
        std::array<float, 6> box{};     // object-space bounds
        base::VertexTriangles around;   // with exact_hits only: exact_hit's neighbourhoods
    };
    struct Instance {
        std::uint32_t mesh = 0;
        Affine transform{};
        std::array<float, 9> nmat{};
        std::array<float, 6> box{};  // world-space bounds
    };
    RTCDevice device = nullptr;
    RTCScene reference = nullptr, hybrid = nullptr;
    bool hybrid_has_geometry = false;
    // Single rays unless SceneBuilder::open asks for packets: a conversion's visual check
    // (ObjectViews) keeps the single-ray route its decisions were made with.
    EmbreeRoute embree_route = EmbreeRoute::single;
    // Embree's hits decoded with t, u and v computed again (exact_hit), for images that must
    // be the same on every CPU (ObjectViews: they decide what ships); otherwise Embree's own,
    // whose bits are the CPU's, at no cost to the renders `lsnif eval` times.
    bool exact_hits = false;
    std::vector<Mesh> meshes;
    std::vector<Instance> instances;
    std::vector<std::uint32_t> lsnif_instances;  // indices into instances
    std::array<float, 6> world{};
    std::atomic<std::uint64_t> memory{0};
    std::string embree_error;

    ~Impl() {
        if (reference) rtcReleaseScene(reference);
        if (hybrid) rtcReleaseScene(hybrid);
        for (Mesh& m : meshes) {
            if (m.scene) rtcReleaseScene(m.scene);
            if (m.model) lsnif_close(m.model);
        }
        if (device) rtcReleaseDevice(device);
    }
    // The stages of building a scene (SceneBuilder, ObjectViews::create). Each returns false
    // with `error` set on failure; what was created so far is released by ~Impl.
    // `config`: Embree's device configuration ("isa=avx2,threads=1"); null: its defaults.
    bool open_device(std::string& error, const char* config = nullptr);
    // `m`'s triangles (positions, indices; normals and box already set) into an Embree scene
    // of their own, its BVH bytes measured; appended to `meshes`.
    bool upload(Mesh m, std::string& error);
    // Instance number instances.size() of mesh `mesh` with `transform` (object to world, 3x4
    // row-major) in the reference scene, and in the hybrid one unless it is traced through
    // its mesh's model (`as_lsnif`: listed in lsnif_instances). The first one creates both
    // top-level scenes.
    bool place(std::uint32_t mesh, const Affine& transform, bool as_lsnif, std::string& error);
    // Commits both top-level scenes; false with `error` when Embree reported an error.
    bool commit(std::string& error);

    static void on_error(void* user, RTCError, const char* str) {
        static_cast<Impl*>(user)->embree_error = str ? str : "unknown";
    }
    static bool on_memory(void* user, ssize_t bytes, bool) {
        static_cast<Impl*>(user)->memory += std::uint64_t(bytes);  // signed: frees are negative
        return true;
    }

    // Ray r's hit as Embree reported it in `rh` (r's closest hit, or none).
    TraceHit embree_hit(const RTCRayHit& rh, const lsnif_ray& r) const {
        TraceHit h;
        if (rh.hit.geomID == RTC_INVALID_GEOMETRY_ID) return h;
        const std::uint32_t inst = rh.hit.instID[0];
        const Instance& in = instances[inst];
        const Mesh& m = meshes[in.mesh];
        std::uint32_t prim = rh.hit.primID;
        float t = rh.ray.tfar, u = rh.hit.u, v = rh.hit.v;
        if (exact_hits) prim = exact_hit(in, r, prim, t, u, v);
        const std::uint32_t* tri = &m.indices[std::size_t(prim) * 3];
        const float w = 1.0f - u - v;
        Vec3 n{};
        for (int a = 0; a < 3; ++a)
            n[a] =
                w * m.normals[tri[0] * 3 + a] + u * m.normals[tri[1] * 3 + a] + v * m.normals[tri[2] * 3 + a];
        h.t = t;
        h.normal = apply_normal(in.nmat, n);
        h.instance = std::int32_t(inst);
        return h;
    }

    // Ray r's hit with triangle `prim` of instance `in`, which Embree reported with t, u and
    // v: the three computed again in world space (base::triangle_hit, the same bits on every
    // CPU), on the triangle base::exact_tied_hit chooses where others meet the ray at the same
    // point, t kept within [tmin, tmax] as Embree's exact depth test left it. Embree's values
    // stay where triangle_hit has none. Returns the triangle.
    std::uint32_t exact_hit(const Instance& in, const lsnif_ray& r, std::uint32_t prim, float& t, float& u,
                            float& v) const {
        using base::Vec3d;
        const Mesh& m = meshes[in.mesh];
        const Affine& a = in.transform;
        const auto triangle = [&](std::uint32_t c, Vec3d& v0, Vec3d& e1, Vec3d& e2) {
            Vec3d p[3];
            for (int k = 0; k < 3; ++k) {
                const float* q = &m.positions[std::size_t(m.indices[3 * std::size_t(c) + k]) * 3];
                p[k] = {double(a[0]) * q[0] + double(a[1]) * q[1] + double(a[2]) * q[2] + a[3],
                        double(a[4]) * q[0] + double(a[5]) * q[1] + double(a[6]) * q[2] + a[7],
                        double(a[8]) * q[0] + double(a[9]) * q[1] + double(a[10]) * q[2] + a[11]};
            }
            v0 = p[0];
            e1 = p[1] - p[0];
            e2 = p[2] - p[0];
        };
        const Vec3d org{r.org[0], r.org[1], r.org[2]}, dir{r.dir[0], r.dir[1], r.dir[2]};
        const double lo[3] = {in.box[0], in.box[1], in.box[2]}, hi[3] = {in.box[3], in.box[4], in.box[5]};
        const std::uint32_t* c = &m.indices[3 * std::size_t(prim)];
        const std::uint32_t corners[3] = {c[0], c[1], c[2]};
        const std::optional<base::ChosenHit> chosen = base::exact_tied_hit(
            org, dir, r.tmin, r.tmax, base::tie_margin(lo, hi), prim, corners, m.around, triangle);
        if (!chosen) return prim;
        t = std::clamp(float(chosen->hit.t), r.tmin, r.tmax);
        u = float(chosen->hit.u);
        v = float(chosen->hit.v);
        return chosen->triangle;
    }
};

}  // namespace lsnif::render
