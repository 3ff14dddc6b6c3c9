// The rendering machinery of `lsnif eval` (eval.cpp) that the per-object views of a
// conversion (object_views.cpp) share: the loaded scene's internals, primary visibility,
// the secondary rays of both tracers, and their comparison with FLIP. Internal to the
// converter: not installed, not an API.
#pragma once

#include <lsnif/converter/eval.hpp>
#include <lsnif/converter/outcome.hpp>
#include <lsnif/image/flip.hpp>
#include <lsnif/scene/scene.hpp>

#include <embree3/rtcore.h>

#include <atomic>
#include <cmath>
#include <filesystem>
#include <optional>
#include <string>
#include <vector>

namespace lsnif::converter {

namespace eval_detail {

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

}  // namespace eval_detail

struct EvalScene::Impl {
    struct Mesh {
        std::vector<float> positions, normals;
        std::vector<std::uint32_t> indices;
        RTCScene scene = nullptr;
        lsnif_model* model = nullptr;  // complex meshes with a shipped asset
        std::string name;
        std::uint64_t bvh_bytes = 0;
        std::uint64_t lsnif_bytes = 0;  // the opened asset's resident bytes (lsnif_info.decoded_bytes)
        std::array<float, 6> box{};     // object-space bounds
    };
    struct Instance {
        std::uint32_t mesh = 0;
        eval_detail::Affine transform{};
        std::array<float, 9> nmat{};
        std::array<float, 6> box{};  // world-space bounds
    };
    RTCDevice device = nullptr;
    RTCScene reference = nullptr, hybrid = nullptr;
    bool hybrid_has_geometry = false;
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
    // Stages of EvalScene::load. Each returns false with `error` set on failure; what was
    // created so far is released by ~Impl.
    // `m`'s triangles (positions, indices; normals and box already set) into an Embree scene
    // of their own, its BVH bytes measured; appended to `meshes`.
    bool upload(Mesh m, std::string& error);
    // Instance number instances.size() of mesh `mesh` with `transform` (object to world, 3x4
    // row-major) in the reference scene, and in the hybrid one unless it is traced through
    // its mesh's model (`as_lsnif`: listed in lsnif_instances).
    bool place(std::uint32_t mesh, const eval_detail::Affine& transform, bool as_lsnif, std::string& error);
    // `config`: Embree's device configuration ("isa=avx2,threads=1"); null: its defaults.
    bool open_device(std::string& error, const char* config = nullptr);
    // Uploads one source mesh to its own Embree scene (measuring its BVH bytes) and opens
    // its shipped asset when the manifest gives one.
    bool add_mesh(const scene::Mesh& sm, const MeshOutcome& outcome, const std::filesystem::path& outdir,
                  lsnif_arithmetic arithmetic, std::string& error);
    // Instance i of the manifest (opt.instance_transforms may override its placement) into
    // the reference scene, and into the hybrid one unless its mesh is traced as an LSNIF.
    bool add_instance(std::size_t i, const nlohmann::json& manifest_instance, const EvalOptions& opt,
                      const std::string& manifest_path, std::string& error);

    static void on_error(void* user, RTCError, const char* str) {
        static_cast<Impl*>(user)->embree_error = str ? str : "unknown";
    }
    static bool on_memory(void* user, ssize_t bytes, bool) {
        static_cast<Impl*>(user)->memory += std::uint64_t(bytes);  // signed: frees are negative
        return true;
    }

    TraceHit embree_hit(const RTCRayHit& rh) const {
        using namespace eval_detail;
        TraceHit h;
        if (rh.hit.geomID == RTC_INVALID_GEOMETRY_ID) return h;
        const std::uint32_t inst = rh.hit.instID[0];
        const Instance& in = instances[inst];
        const Mesh& m = meshes[in.mesh];
        const std::uint32_t* tri = &m.indices[std::size_t(rh.hit.primID) * 3];
        const float u = rh.hit.u, v = rh.hit.v, w = 1.0f - u - v;
        Vec3 n{};
        for (int a = 0; a < 3; ++a)
            n[a] =
                w * m.normals[tri[0] * 3 + a] + u * m.normals[tri[1] * 3 + a] + v * m.normals[tri[2] * 3 + a];
        h.t = rh.ray.tfar;
        h.normal = apply_normal(in.nmat, n);
        h.instance = std::int32_t(inst);
        return h;
    }
};

namespace eval_detail {

// The three effects one at a time, then their combination (docs/eval.md "The renders").
enum { kShadow, kAo, kReflection, kCombined, kEffects };
constexpr int kSeparateEffects = kCombined;  // what the report's overall flip_mean averages
constexpr const char* kEffectNames[kEffects] = {"shadow", "ao", "reflection", "combined"};

// The camera and light of a render: the options' or, by default, framing the bounds given.
struct View {
    EvalCamera cam;
    Vec3 light, fwd, right, up;
    float tan_half, aspect;
    float diag;  // the bounds' diagonal
    std::uint32_t W, H;
};
View make_view(const EvalOptions& opt, const std::array<float, 6>& world);

// Primary visibility: position, camera-facing shading normal, instance (-1: background) and
// secondary-ray offset of every pixel. From the real meshes through Embree (standing in for a
// rasterized G-buffer), or with `through_assets` from the hybrid tracer: the meshes converted
// to LSNIF answered by their assets, the others by Embree (the paper's "all types of rays").
struct GBuffer {
    std::vector<Vec3> p, n;
    std::vector<std::int32_t> inst;
    std::vector<float> eps;
    double trace_seconds = 0;  // tracing the primary rays, summed over threads
};
GBuffer render_primary(const EvalScene& scene, const std::vector<EvalScene::Impl::Instance>& instances,
                       const View& v, std::uint32_t threads, bool through_assets = false);

// Linear RGB images of the effects from one tracer, and the time its secondary rays took
// (summed over threads).
// The three families of secondary rays, in the order a row traces them.
inline constexpr int kRayFamilies = 3;
inline constexpr const char* kRayFamilyNames[kRayFamilies] = {"shadow", "ao", "reflection"};
using SecondaryProfile = std::array<TraceProfile, kRayFamilies>;

struct EffectImages {
    std::vector<float> rgb[kEffects];
    double trace_seconds = 0;
    SecondaryProfile profile;  // of the traces trace_seconds counts (each row's fastest)
};
struct BothImages {
    EffectImages reference, hybrid;
};
// Which tracers render_secondary runs: both (lsnif eval), or one of them (a reference
// rendered once, then one hybrid per candidate model).
enum class Tracers { both, reference, hybrid };
BothImages render_secondary(const EvalScene& scene, const std::vector<EvalScene::Impl::Instance>& instances,
                            const GBuffer& gb, const View& v, const EvalOptions& opt,
                            const std::vector<float>& surface_tmin, std::uint32_t threads,
                            Tracers tracers = Tracers::both);

// One effect's reference and test images compared (sRGB-encoded): FLIP over the frame,
// PSNR (infinite for identical images), FLIP over the LSNIF pixels (their statistics, none
// when there are none, and the errors themselves, so that several views pool them), and the
// PNG files written (reference, test, FLIP heat map), if any.
struct EffectComparison {
    image::FlipStats flip;
    double psnr_db = 0;
    std::optional<image::FlipStats> flip_lsnif_pixels;
    std::vector<float> lsnif_pixel_errors;
    std::vector<std::string> files;
};
struct Comparison {
    EffectComparison effect[kEffects];
    double flip_mean = 0;  // over the separate effects (shadow, AO, reflection)
};
// Compares effect `e` (kShadow ... kCombined) into `c`; writes its PNGs into `images` when
// write_images, named as compare_effects names them. False with `error` when FLIP or a file
// fails.
bool compare_effect(const EffectImages& reference, const EffectImages& test, const View& v, int e,
                    const std::vector<std::uint8_t>& lsnif_pixels, const std::filesystem::path& images,
                    bool write_images, EffectComparison& c, std::string& error,
                    const std::string& label = "hybrid");
// Compares every effect; writes the PNGs into `images` when write_images, named
// reference_<effect>.png, <label>_<effect>.png and flip_<effect>.png (flip_<label>_<effect>.png
// for a label other than "hybrid"). False with `error` when FLIP or a file fails.
bool compare_effects(const EffectImages& reference, const EffectImages& test, const View& v,
                     const std::vector<std::uint8_t>& lsnif_pixels, const std::filesystem::path& images,
                     bool write_images, Comparison& out, std::string& error,
                     const std::string& label = "hybrid");

// 1 for the pixels whose primary hit is an instance the hybrid render traces as an LSNIF.
std::vector<std::uint8_t> lsnif_pixel_mask(const GBuffer& gb, const EvalScene::Impl& im);
// The pixels either mask selects: an object's pixels where the mesh and its asset, each
// seen by its own primary rays, may disagree on its silhouette.
std::vector<std::uint8_t> mask_union(const std::vector<std::uint8_t>& a, const std::vector<std::uint8_t>& b);

}  // namespace eval_detail

}  // namespace lsnif::converter
