// `lsnif eval`: reference (Embree everywhere) and hybrid (Embree + LSNIF reader) renders of
// a converted scene, compared with FLIP and PSNR (eval.hpp has the contract).
#include <lsnif/base/affine.hpp>
#include <lsnif/base/clock.hpp>
#include <lsnif/base/parallel.hpp>
#include <lsnif/base/random.hpp>
#include <lsnif/converter/eval.hpp>
#include <lsnif/converter/manifest.hpp>

#include <embree3/rtcore.h>

#include <algorithm>
#include <atomic>
#include <chrono>
#include <cmath>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <limits>

#include <lsnif/eval/flip.hpp>
#include <lsnif/eval/image.hpp>
#include <lsnif/scene/scene.hpp>

namespace lsnif::converter {
namespace fs = std::filesystem;
using nlohmann::json;
using Vec3 = std::array<float, 3>;

namespace {

Vec3 operator+(Vec3 a, Vec3 b) {
    return {a[0] + b[0], a[1] + b[1], a[2] + b[2]};
}
Vec3 operator-(Vec3 a, Vec3 b) {
    return {a[0] - b[0], a[1] - b[1], a[2] - b[2]};
}
Vec3 operator*(Vec3 a, float s) {
    return {a[0] * s, a[1] * s, a[2] * s};
}
Vec3 mul(Vec3 a, Vec3 b) {
    return {a[0] * b[0], a[1] * b[1], a[2] * b[2]};
}
float dot(Vec3 a, Vec3 b) {
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
}
Vec3 cross(Vec3 a, Vec3 b) {
    return {a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]};
}
float length(Vec3 a) {
    return std::sqrt(dot(a, a));
}
Vec3 normalize(Vec3 a) {
    const float l = length(a);
    return l > 0.0f ? a * (1.0f / l) : Vec3{0.0f, 0.0f, 1.0f};
}

using Affine = std::array<float, 12>;  // 3x4 row-major [A | b]

Vec3 apply_point(const Affine& m, Vec3 p) {
    return {m[0] * p[0] + m[1] * p[1] + m[2] * p[2] + m[3], m[4] * p[0] + m[5] * p[1] + m[6] * p[2] + m[7],
            m[8] * p[0] + m[9] * p[1] + m[10] * p[2] + m[11]};
}

Vec3 apply_normal(const std::array<float, 9>& n, Vec3 v) {
    return normalize({n[0] * v[0] + n[1] * v[1] + n[2] * v[2], n[3] * v[0] + n[4] * v[1] + n[5] * v[2],
                      n[6] * v[0] + n[7] * v[1] + n[8] * v[2]});
}

}  // namespace

// ---- the loaded scene -------------------------------------------------------------------

struct EvalScene::Impl {
    struct Mesh {
        std::vector<float> positions, normals;
        std::vector<std::uint32_t> indices;
        RTCScene scene = nullptr;
        lsnif_model* model = nullptr;  // complex meshes with a shipped asset
        std::string name;
        std::uint64_t bvh_bytes = 0;
        std::uint64_t lsnif_bytes = 0;
        std::array<float, 6> box{};  // object-space bounds
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
    static void on_error(void* user, RTCError, const char* str) {
        static_cast<Impl*>(user)->embree_error = str ? str : "unknown";
    }
    static bool on_memory(void* user, ssize_t bytes, bool) {
        static_cast<Impl*>(user)->memory += std::uint64_t(bytes);  // signed: frees are negative
        return true;
    }

    TraceHit embree_hit(const RTCRayHit& rh) const {
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

EvalScene::EvalScene(std::unique_ptr<Impl> impl) : impl_(std::move(impl)) {}
EvalScene::~EvalScene() = default;
std::size_t EvalScene::instance_count() const {
    return impl_->instances.size();
}
std::size_t EvalScene::lsnif_instance_count() const {
    return impl_->lsnif_instances.size();
}
std::array<float, 6> EvalScene::world_bounds() const {
    return impl_->world;
}
std::array<float, 6> EvalScene::instance_bounds(std::size_t i) const {
    return impl_->instances.at(i).box;
}

namespace {

void init_rayhit(const lsnif_ray& r, RTCRayHit& rh) {
    rh.ray.org_x = r.org[0];
    rh.ray.org_y = r.org[1];
    rh.ray.org_z = r.org[2];
    rh.ray.dir_x = r.dir[0];
    rh.ray.dir_y = r.dir[1];
    rh.ray.dir_z = r.dir[2];
    rh.ray.tnear = r.tmin;
    rh.ray.tfar = r.tmax;
    rh.ray.time = 0.0f;
    rh.ray.mask = 0xFFFFFFFFu;
    rh.ray.id = 0;
    rh.ray.flags = 0;
    rh.hit.geomID = RTC_INVALID_GEOMETRY_ID;
    rh.hit.primID = RTC_INVALID_GEOMETRY_ID;
    rh.hit.instID[0] = RTC_INVALID_GEOMETRY_ID;
}

// Ray-box slab test on [tmin, tmax]: the cheap cull before a network query.
bool hits_box(const lsnif_ray& r, const std::array<float, 6>& b, float tmax) {
    float t0 = r.tmin, t1 = tmax;
    for (int a = 0; a < 3; ++a) {
        const float inv = 1.0f / r.dir[a];
        float tn = (b[a] - r.org[a]) * inv, tf = (b[a + 3] - r.org[a]) * inv;
        if (tn > tf) std::swap(tn, tf);
        if (!(tn <= tf)) continue;  // NaN from 0 * inf: the slab does not constrain
        t0 = std::max(t0, tn);
        t1 = std::min(t1, tf);
    }
    return t0 <= t1;
}

constexpr std::size_t kBatch = 256;  // reader batches (lsnif.h: >= 256 amortizes best)

}  // namespace

void EvalScene::closest(bool hybrid, std::span<const lsnif_ray> rays, std::span<TraceHit> hits) const {
    const Impl& im = *impl_;
    RTCIntersectContext ctx;
    for (std::size_t i = 0; i < rays.size(); ++i) {
        hits[i] = TraceHit{};
        if (hybrid && !im.hybrid_has_geometry) continue;
        rtcInitIntersectContext(&ctx);
        RTCRayHit rh;
        init_rayhit(rays[i], rh);
        rtcIntersect1(hybrid ? im.hybrid : im.reference, &ctx, &rh);
        hits[i] = im.embree_hit(rh);
    }
    if (!hybrid) return;
    std::vector<lsnif_ray> batch;
    std::vector<std::uint32_t> idx;
    std::vector<lsnif_hit> out(kBatch);
    batch.reserve(kBatch);
    idx.reserve(kBatch);
    for (const std::uint32_t inst : im.lsnif_instances) {
        const Impl::Instance& in = im.instances[inst];
        const lsnif_model* model = im.meshes[in.mesh].model;
        auto flush = [&] {
            if (batch.empty()) return;
            if (lsnif_intersect_instance(model, in.transform.data(), batch.data(), batch.size(),
                                         out.data()) == LSNIF_OK) {
                for (std::size_t k = 0; k < batch.size(); ++k) {
                    TraceHit& h = hits[idx[k]];
                    const lsnif_hit& o = out[k];
                    const float best = h.instance >= 0 ? h.t : batch[k].tmax;
                    if (o.hit && o.t >= batch[k].tmin && o.t <= best) {
                        h.t = o.t;
                        h.normal = normalize({o.normal[0], o.normal[1], o.normal[2]});
                        h.instance = std::int32_t(inst);
                    }
                }
            }
            batch.clear();
            idx.clear();
        };
        for (std::size_t i = 0; i < rays.size(); ++i) {
            const float tmax = hits[i].instance >= 0 ? hits[i].t : rays[i].tmax;
            if (!hits_box(rays[i], in.box, tmax)) continue;
            batch.push_back(rays[i]);
            idx.push_back(std::uint32_t(i));
            if (batch.size() == kBatch) flush();
        }
        flush();
    }
}

void EvalScene::occluded(bool hybrid, std::span<const lsnif_ray> rays, std::span<std::uint8_t> occ) const {
    const Impl& im = *impl_;
    RTCIntersectContext ctx;
    for (std::size_t i = 0; i < rays.size(); ++i) {
        occ[i] = 0;
        if (hybrid && !im.hybrid_has_geometry) continue;
        rtcInitIntersectContext(&ctx);
        RTCRayHit rh;
        init_rayhit(rays[i], rh);
        rtcOccluded1(hybrid ? im.hybrid : im.reference, &ctx, &rh.ray);
        occ[i] = rh.ray.tfar < 0.0f;  // Embree marks an occluded ray with tfar = -inf
    }
    if (!hybrid) return;
    std::vector<lsnif_ray> batch;
    std::vector<std::uint32_t> idx;
    std::vector<lsnif_hit> out(kBatch);
    for (const std::uint32_t inst : im.lsnif_instances) {
        const Impl::Instance& in = im.instances[inst];
        const lsnif_model* model = im.meshes[in.mesh].model;
        auto flush = [&] {
            if (batch.empty()) return;
            if (lsnif_intersect_instance(model, in.transform.data(), batch.data(), batch.size(),
                                         out.data()) == LSNIF_OK)
                for (std::size_t k = 0; k < batch.size(); ++k)
                    if (out[k].hit && out[k].t >= batch[k].tmin && out[k].t <= batch[k].tmax) occ[idx[k]] = 1;
            batch.clear();
            idx.clear();
        };
        for (std::size_t i = 0; i < rays.size(); ++i) {
            if (occ[i] || !hits_box(rays[i], in.box, rays[i].tmax)) continue;
            batch.push_back(rays[i]);
            idx.push_back(std::uint32_t(i));
            if (batch.size() == kBatch) flush();
        }
        flush();
    }
}

std::unique_ptr<EvalScene> EvalScene::load(const EvalOptions& opt, std::string& error) {
    LoadedManifest loaded;
    if (!load_manifest(opt.outdir, opt.sources, loaded, error)) return nullptr;
    const fs::path dir = opt.outdir;
    const fs::path& manifest_path = loaded.path;
    const json& manifest = loaded.doc;
    const std::vector<std::string>& sources = loaded.sources;
    std::vector<scene::Scene> scenes(sources.size());
    for (std::size_t s = 0; s < sources.size(); ++s) {
        if (manifest["inputs"][s].value("status", "") != "ok")
            continue;  // failed in convert: no meshes from it
        auto r = scene::import_scene(sources[s]);
        if (!r.ok()) {
            error = manifest_path.string() + ": input " + std::to_string(s) + ": " + r.error;
            return nullptr;
        }
        scenes[s] = std::move(r.scene);
    }

    auto impl = std::make_unique<Impl>();
    Impl& im = *impl;
    im.device = rtcNewDevice(nullptr);
    if (!im.device) {
        error = "embree: rtcNewDevice failed";
        return nullptr;
    }
    rtcSetDeviceErrorFunction(im.device, &Impl::on_error, &im);
    rtcSetDeviceMemoryMonitorFunction(im.device, &Impl::on_memory, &im);

    for (const json& mj : manifest["meshes"]) {
        const std::size_t input = mj.value("input", std::size_t(0)),
                          src = mj.value("source_mesh", std::size_t(0));
        if (input >= scenes.size() || src >= scenes[input].meshes.size()) {
            error = manifest_path.string() + ": mesh '" + mj.value("name", "") + "' refers to input " +
                    std::to_string(input) + " mesh " + std::to_string(src) +
                    ", which the source does not have";
            return nullptr;
        }
        const scene::Mesh& sm = scenes[input].meshes[src];
        if (scene::geometry_hash(sm) != mj.value("geometry_hash", "")) {
            error = sources[input] + ": mesh '" + sm.name +
                    "' differs from the converted geometry (geometry hash mismatch): re-run lsnif convert";
            return nullptr;
        }
        Impl::Mesh m;
        m.name = sm.name;
        m.positions = sm.positions;
        m.normals = sm.normals;
        m.indices = sm.indices;
        m.box = {INFINITY, INFINITY, INFINITY, -INFINITY, -INFINITY, -INFINITY};
        for (std::size_t v = 0; v < sm.vertex_count(); ++v)
            for (int a = 0; a < 3; ++a) {
                m.box[a] = std::min(m.box[a], sm.positions[v * 3 + a]);
                m.box[a + 3] = std::max(m.box[a + 3], sm.positions[v * 3 + a]);
            }
        const std::uint64_t before = im.memory;
        m.scene = rtcNewScene(im.device);
        RTCGeometry g = rtcNewGeometry(im.device, RTC_GEOMETRY_TYPE_TRIANGLE);
        auto* vb = static_cast<float*>(rtcSetNewGeometryBuffer(
            g, RTC_BUFFER_TYPE_VERTEX, 0, RTC_FORMAT_FLOAT3, 3 * sizeof(float), sm.vertex_count()));
        auto* ib = static_cast<std::uint32_t*>(rtcSetNewGeometryBuffer(
            g, RTC_BUFFER_TYPE_INDEX, 0, RTC_FORMAT_UINT3, 3 * sizeof(std::uint32_t), sm.triangle_count()));
        if (!vb || !ib) {
            rtcReleaseGeometry(g);
            error = "embree: cannot allocate buffers for mesh '" + sm.name + "': " + im.embree_error;
            return nullptr;
        }
        std::memcpy(vb, sm.positions.data(), sm.positions.size() * sizeof(float));
        std::memcpy(ib, sm.indices.data(), sm.indices.size() * sizeof(std::uint32_t));
        rtcCommitGeometry(g);
        rtcAttachGeometry(m.scene, g);
        rtcReleaseGeometry(g);
        rtcCommitScene(m.scene);
        m.bvh_bytes = im.memory - before;
        if (mj.value("class", "") == "complex" && mj.contains("lsnif") && mj["lsnif"].contains("file")) {
            const fs::path asset = dir / mj["lsnif"]["file"].get<std::string>();
            lsnif_error err{};
            if (lsnif_open_file(asset.c_str(), &m.model, &err) != LSNIF_OK) {
                error = asset.string() + ": cannot open the asset: " + lsnif_status_string(err.status) +
                        " (" + err.message + ")";
                im.meshes.push_back(std::move(m));  // released by ~Impl
                return nullptr;
            }
            std::error_code ec;
            m.lsnif_bytes = fs::file_size(asset, ec);
        }
        im.meshes.push_back(std::move(m));
    }

    im.reference = rtcNewScene(im.device);
    im.hybrid = rtcNewScene(im.device);
    im.world = {INFINITY, INFINITY, INFINITY, -INFINITY, -INFINITY, -INFINITY};
    const json& insts = manifest["instances"];
    for (std::size_t i = 0; i < insts.size(); ++i) {
        Impl::Instance in;
        in.mesh = insts[i].value("mesh", 0u);
        if (in.mesh >= im.meshes.size() || !insts[i].contains("transform") ||
            insts[i]["transform"].size() != 12) {
            error = manifest_path.string() + ": instance " + std::to_string(i) + " is malformed";
            return nullptr;
        }
        for (int k = 0; k < 12; ++k) in.transform[k] = insts[i]["transform"][k].get<float>();
        for (const auto& [which, m] : opt.instance_transforms)
            if (which == i) in.transform = m;
        const auto inverse = base::invert_linear(in.transform.data());
        if (!inverse) {
            error = manifest_path.string() + ": instance " + std::to_string(i) +
                    " has a singular or non-finite transform";
            return nullptr;
        }
        in.nmat = base::normal_matrix(*inverse);
        const auto& ob = im.meshes[in.mesh].box;
        in.box = {INFINITY, INFINITY, INFINITY, -INFINITY, -INFINITY, -INFINITY};
        for (int c = 0; c < 8; ++c) {
            const Vec3 p =
                apply_point(in.transform, {ob[c & 1 ? 3 : 0], ob[c & 2 ? 4 : 1], ob[c & 4 ? 5 : 2]});
            for (int a = 0; a < 3; ++a) {
                in.box[a] = std::min(in.box[a], p[a]);
                in.box[a + 3] = std::max(in.box[a + 3], p[a]);
            }
        }
        for (int a = 0; a < 3; ++a) {
            im.world[a] = std::min(im.world[a], in.box[a]);
            im.world[a + 3] = std::max(im.world[a + 3], in.box[a + 3]);
        }
        const bool as_lsnif = im.meshes[in.mesh].model != nullptr;
        for (RTCScene top : {im.reference, im.hybrid}) {
            if (top == im.hybrid && as_lsnif) continue;
            RTCGeometry g = rtcNewGeometry(im.device, RTC_GEOMETRY_TYPE_INSTANCE);
            rtcSetGeometryInstancedScene(g, im.meshes[in.mesh].scene);
            rtcSetGeometryTransform(g, 0, RTC_FORMAT_FLOAT3X4_ROW_MAJOR, in.transform.data());
            rtcCommitGeometry(g);
            rtcAttachGeometryByID(top, g, std::uint32_t(i));
            rtcReleaseGeometry(g);
        }
        if (as_lsnif)
            im.lsnif_instances.push_back(std::uint32_t(i));
        else
            im.hybrid_has_geometry = true;
        im.instances.push_back(in);
    }
    if (im.instances.empty()) {
        error = manifest_path.string() + ": no instances";
        return nullptr;
    }
    rtcCommitScene(im.reference);
    rtcCommitScene(im.hybrid);
    if (!im.embree_error.empty()) {
        error = "embree: " + im.embree_error;
        return nullptr;
    }
    return std::unique_ptr<EvalScene>(new EvalScene(std::move(impl)));
}

// ---- rendering ---------------------------------------------------------------------------

namespace {

// Pleasant, distinct per-mesh albedo: hue by the golden ratio, fixed saturation and value.
Vec3 albedo(std::uint32_t mesh) {
    const float h = std::fmod(0.13f + 0.618034f * float(mesh), 1.0f) * 6.0f, s = 0.45f, v = 0.85f;
    const float c = v * s, x = c * (1.0f - std::fabs(std::fmod(h, 2.0f) - 1.0f)), m = v - c;
    const int k = int(h) % 6;
    const Vec3 rgb = k == 0   ? Vec3{c, x, 0}
                     : k == 1 ? Vec3{x, c, 0}
                     : k == 2 ? Vec3{0, c, x}
                     : k == 3 ? Vec3{0, x, c}
                     : k == 4 ? Vec3{x, 0, c}
                              : Vec3{c, 0, x};
    return rgb + Vec3{m, m, m};
}

Vec3 sky(Vec3 d) {
    const float u = 0.5f * (normalize(d)[1] + 1.0f);
    return Vec3{0.85f, 0.85f, 0.8f} * (1.0f - u) + Vec3{0.45f, 0.6f, 0.9f} * u;
}

const Vec3 kBackground{0.02f, 0.02f, 0.03f};

struct GBuffer {
    std::vector<Vec3> p, n;
    std::vector<std::int32_t> inst;  // -1 = background
    std::vector<float> eps;          // origin offset of secondary rays
};

using base::seconds_since;

json flip_json(const eval::FlipStats& s, double psnr) {
    json j = {{"flip_mean", s.mean}, {"flip_median", s.median}, {"flip_p95", s.p95}, {"flip_max", s.max}};
    j["psnr_db"] = std::isfinite(psnr) ? json(psnr) : json(nullptr);  // identical images: null (infinite)
    return j;
}

}  // namespace

EvalResult evaluate(const EvalOptions& opt) {
    EvalResult res;
    std::string err;
    auto scene = EvalScene::load(opt, err);
    if (!scene) {
        res.errors.push_back(err);
        return res;
    }
    const EvalScene::Impl& im = *scene->impl_;
    if (opt.width == 0 || opt.height == 0 || opt.width > 8192 || opt.height > 8192) {
        res.errors.push_back("image size " + std::to_string(opt.width) + "x" + std::to_string(opt.height) +
                             " out of range (1..8192)");
        return res;
    }
    const std::uint32_t W = opt.width, H = opt.height, S = std::max(1u, opt.ao_samples);
    const std::uint32_t threads = base::resolve_threads(opt.threads);
    const Vec3 lo{im.world[0], im.world[1], im.world[2]}, hi{im.world[3], im.world[4], im.world[5]};
    const Vec3 center = (lo + hi) * 0.5f;
    const float diag = std::max(length(hi - lo), 1e-20f);
    EvalCamera cam;
    if (opt.camera)
        cam = *opt.camera;
    else {
        cam.target = center;
        cam.eye = center + normalize({0.55f, 0.4f, 1.0f}) * (1.15f * diag);
    }
    const Vec3 light = opt.light ? *opt.light : center + Vec3{0.5f, 1.2f, 0.7f} * diag;
    const Vec3 fwd = normalize(cam.target - cam.eye);
    Vec3 right = cross(fwd, cam.up);
    if (length(right) < 1e-6f) right = cross(fwd, {1.0f, 0.0f, 0.0f});
    right = normalize(right);
    const Vec3 up = cross(right, fwd);
    const float tan_half = std::tan(0.5f * cam.fov_deg * 3.14159265f / 180.0f), aspect = float(W) / float(H);

    // ---- primary visibility: real meshes, Embree (the G-buffer) ----
    auto t0 = std::chrono::steady_clock::now();
    GBuffer gb;
    gb.p.resize(std::size_t(W) * H);
    gb.n.resize(gb.p.size());
    gb.inst.assign(gb.p.size(), -1);
    gb.eps.resize(gb.p.size());
    base::parallel_chunks(H, threads, 1, [&](std::uint32_t, std::size_t y, std::size_t) {
        std::vector<lsnif_ray> rays(W);
        std::vector<TraceHit> hits(W);
        for (std::uint32_t x = 0; x < W; ++x) {
            const float sx = (2.0f * (float(x) + 0.5f) / float(W) - 1.0f) * tan_half * aspect;
            const float sy = (1.0f - 2.0f * (float(y) + 0.5f) / float(H)) * tan_half;
            const Vec3 d = normalize(fwd + right * sx + up * sy);
            rays[x] = {{cam.eye[0], cam.eye[1], cam.eye[2]}, 0.0f, {d[0], d[1], d[2]}, INFINITY};
        }
        scene->closest(false, rays, hits);
        for (std::uint32_t x = 0; x < W; ++x) {
            const std::size_t i = std::size_t(y) * W + x;
            if (hits[x].instance < 0) continue;
            const Vec3 d{rays[x].dir[0], rays[x].dir[1], rays[x].dir[2]};
            gb.p[i] = cam.eye + d * hits[x].t;
            Vec3 n = hits[x].normal;
            if (dot(n, d) > 0.0f) n = n * -1.0f;  // shade the side the camera sees
            gb.n[i] = n;
            gb.inst[i] = hits[x].instance;
            // Same offset rule as the training family (b) rays (sampling.hpp): a fraction of
            // the object's diagonal plus a relative term for far-from-origin geometry.
            const auto& b = im.instances[hits[x].instance].box;
            const float m = std::max({std::fabs(gb.p[i][0]), std::fabs(gb.p[i][1]), std::fabs(gb.p[i][2])});
            gb.eps[i] = 1e-4f * length(Vec3{b[3] - b[0], b[4] - b[1], b[5] - b[2]}) + 1e-5f * m;
        }
    });
    const double primary_seconds = seconds_since(t0);

    // ---- secondary rays, traced by each tracer over identical rays ----
    enum { kShadow, kAo, kReflection, kEffects };
    const char* names[kEffects] = {"shadow", "ao", "reflection"};
    std::vector<float> img[2][kEffects];
    double trace_seconds[2] = {0, 0};
    for (int hybrid = 0; hybrid < 2; ++hybrid) {
        for (auto& v : img[hybrid]) v.assign(std::size_t(W) * H * 3, 0.0f);
        std::vector<double> per_thread(threads, 0.0);
        base::parallel_chunks(H, threads, 1, [&](std::uint32_t t, std::size_t y, std::size_t) {
            std::vector<lsnif_ray> shadow, ao, refl;
            std::vector<std::uint32_t> px;
            for (std::uint32_t x = 0; x < W; ++x) {
                const std::size_t i = std::size_t(y) * W + x;
                if (gb.inst[i] < 0) continue;
                px.push_back(x);
                const Vec3 n = gb.n[i], o = gb.p[i] + n * gb.eps[i];
                const Vec3 tl = light - o;
                const float dist = length(tl);
                shadow.push_back(
                    {{o[0], o[1], o[2]}, 0.0f, {tl[0] / dist, tl[1] / dist, tl[2] / dist}, dist});
                // Cosine-weighted hemisphere about n (Malley's method), per-pixel stream.
                base::SplitMix64 rng{opt.seed * base::kGoldenGamma + i * 0xD1B54A32D192ED03ull};
                const Vec3 a = std::fabs(n[0]) > 0.5f ? Vec3{0, 1, 0} : Vec3{1, 0, 0};
                const Vec3 tx = normalize(cross(a, n)), ty = cross(n, tx);
                for (std::uint32_t k = 0; k < S; ++k) {
                    const float r = std::sqrt(rng.uniform01f()), phi = 6.2831853f * rng.uniform01f();
                    const float lx = r * std::cos(phi), ly = r * std::sin(phi);
                    const Vec3 d = normalize(tx * lx + ty * ly + n * std::sqrt(std::max(0.0f, 1.0f - r * r)));
                    ao.push_back({{o[0], o[1], o[2]}, 0.0f, {d[0], d[1], d[2]}, opt.ao_radius * diag});
                }
                const Vec3 v = normalize(gb.p[i] - cam.eye);
                const Vec3 rd = v - n * (2.0f * dot(v, n));
                refl.push_back({{o[0], o[1], o[2]}, 0.0f, {rd[0], rd[1], rd[2]}, INFINITY});
            }
            std::vector<std::uint8_t> shadow_occ(shadow.size()), ao_occ(ao.size());
            std::vector<TraceHit> refl_hit(refl.size());
            const auto tt = std::chrono::steady_clock::now();
            scene->occluded(hybrid, shadow, shadow_occ);
            scene->occluded(hybrid, ao, ao_occ);
            scene->closest(hybrid, refl, refl_hit);
            per_thread[t] += seconds_since(tt);
            for (std::uint32_t x = 0; x < W; ++x)  // background everywhere first
                for (int e = 0; e < kEffects; ++e)
                    for (int c = 0; c < 3; ++c)
                        img[hybrid][e][(std::size_t(y) * W + x) * 3 + c] = kBackground[c];
            for (std::size_t k = 0; k < px.size(); ++k) {
                const std::size_t i = std::size_t(y) * W + px[k];
                const Vec3 base = albedo(im.instances[gb.inst[i]].mesh);
                const Vec3 ldir = normalize(light - gb.p[i]);
                const float lambert = std::max(0.0f, dot(gb.n[i], ldir));
                const Vec3 sh = base * (0.12f + 0.88f * lambert * (shadow_occ[k] ? 0.0f : 1.0f));
                std::uint32_t open = 0;
                for (std::uint32_t q = 0; q < S; ++q) open += ao_occ[k * S + q] ? 0u : 1u;
                const float aov = float(open) / float(S);
                Vec3 rc;
                const TraceHit& h = refl_hit[k];
                const Vec3 rd{refl[k].dir[0], refl[k].dir[1], refl[k].dir[2]};
                if (h.instance >= 0) {
                    const Vec3 hp = Vec3{refl[k].org[0], refl[k].org[1], refl[k].org[2]} + rd * h.t;
                    Vec3 hn = h.normal;
                    if (dot(hn, rd) > 0.0f) hn = hn * -1.0f;
                    rc = albedo(im.instances[h.instance].mesh) *
                         (0.2f + 0.8f * std::max(0.0f, dot(hn, normalize(light - hp))));
                } else {
                    rc = sky(rd);
                }
                const Vec3 out[kEffects] = {sh, Vec3{aov, aov, aov}, mul(rc, Vec3{0.9f, 0.9f, 0.9f})};
                for (int e = 0; e < kEffects; ++e)
                    for (int c = 0; c < 3; ++c) img[hybrid][e][i * 3 + c] = out[e][c];
            }
        });
        for (double s : per_thread) trace_seconds[hybrid] += s;
    }

    // ---- compare, write ----
    const fs::path images = opt.images_dir.empty() ? fs::path(opt.outdir) / "eval" : fs::path(opt.images_dir);
    if (opt.write_images) {
        std::error_code ec;
        fs::create_directories(images, ec);
        if (ec) {
            res.errors.push_back(images.string() + ": cannot create directory: " + ec.message());
            return res;
        }
    }
    json report;
    json per = json::object();
    double flip_sum = 0;
    for (int e = 0; e < kEffects; ++e) {
        eval::Image ref{W, H, img[0][e]}, hyb{W, H, img[1][e]};
        for (auto* im2 : {&ref, &hyb})
            for (float& v : im2->rgb) v = eval::linear_to_srgb(std::clamp(v, 0.0f, 1.0f));
        auto f = eval::flip(ref, hyb, eval::FlipOptions{});
        if (!f) {
            res.errors.push_back(std::string("flip: ") + names[e] + ": " + f.error());
            return res;
        }
        const double psnr = eval::psnr(ref, hyb);
        json j = flip_json(f->stats, psnr);
        if (opt.write_images) {
            const std::string stem = names[e];
            const std::pair<std::string, const eval::Image*> files[] = {{"reference_" + stem + ".png", &ref},
                                                                        {"hybrid_" + stem + ".png", &hyb}};
            for (const auto& [file, image] : files) {
                auto w = eval::write_png((images / file).string(), *image);
                if (!w) {
                    res.errors.push_back(w.error());
                    return res;
                }
            }
            auto w = eval::write_png((images / ("flip_" + stem + ".png")).string(),
                                     eval::heatmap(f->error_map, W, H));
            if (!w) {
                res.errors.push_back(w.error());
                return res;
            }
            j["files"] = {{"reference", "reference_" + stem + ".png"},
                          {"hybrid", "hybrid_" + stem + ".png"},
                          {"flip", "flip_" + stem + ".png"}};
        }
        flip_sum += f->stats.mean;
        per[names[e]] = j;
    }
    std::uint64_t lsnif_bytes = 0, bvh_replaced = 0;
    for (const auto& m : im.meshes)
        if (m.model) lsnif_bytes += m.lsnif_bytes, bvh_replaced += m.bvh_bytes;
    report["images"] = per;
    report["flip_mean"] = flip_sum / double(int(kEffects));
    report["width"] = W;
    report["height"] = H;
    report["ao_samples"] = S;
    report["ao_radius"] = opt.ao_radius * diag;
    report["camera"] = {{"eye", cam.eye}, {"target", cam.target}, {"up", cam.up}, {"fov_deg", cam.fov_deg}};
    report["light"] = light;
    report["instances"] = im.instances.size();
    report["lsnif_instances"] = im.lsnif_instances.size();
    report["memory"] = {{"lsnif_bytes", lsnif_bytes}, {"bvh_bytes_replaced", bvh_replaced}};
    report["timings"] = {{"primary", primary_seconds},
                         {"secondary_reference", trace_seconds[0]},
                         {"secondary_hybrid", trace_seconds[1]}};
    report["secondary_time_ratio"] = trace_seconds[0] > 0 ? trace_seconds[1] / trace_seconds[0] : 0.0;
    report["images_dir"] = images.string();
    if (opt.write_images) {
        const fs::path rp = images / "report.json", tmp = images / "report.json.tmp";
        {
            std::ofstream o(tmp);
            o << report.dump(2) << "\n";
            if (!o) {
                res.errors.push_back(tmp.string() + ": cannot write");
                std::error_code ec;
                fs::remove(tmp, ec);
                return res;
            }
        }
        std::error_code ec;
        fs::rename(tmp, rp, ec);
        if (ec) {
            res.errors.push_back(rp.string() + ": " + ec.message());
            return res;
        }
    }
    res.report = std::move(report);
    return res;
}

}  // namespace lsnif::converter
