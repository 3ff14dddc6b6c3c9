// `lsnif eval`: reference (Embree everywhere) and hybrid (Embree + LSNIF reader) renders of
// a converted scene, compared with FLIP and PSNR (eval.hpp has the contract).
#include <lsnif/base/affine.hpp>
#include <lsnif/base/clock.hpp>
#include <lsnif/base/parallel.hpp>
#include <lsnif/base/random.hpp>
#include <lsnif/converter/eval.hpp>
#include <lsnif/converter/manifest.hpp>
#include "eval_render.hpp"

#include <embree3/rtcore.h>

#include <algorithm>
#include <atomic>
#include <chrono>
#include <cmath>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <limits>

#include <lsnif/image/flip.hpp>
#include <lsnif/image/image.hpp>
#include <lsnif/scene/scene.hpp>

namespace lsnif::converter {
namespace fs = std::filesystem;
using nlohmann::json;
using namespace eval_detail;

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

// One trace call's rays as the box tests read them: origins, reciprocal directions and tmin,
// one array each, so that a test of every ray against one box is a loop the compiler
// vectorizes, and the three divisions are paid once per ray, not once per ray and box.
struct RaySlabs {
    std::vector<float> o[3], inv[3], tmin;
    void assign(std::span<const lsnif_ray> rays) {
        for (int a = 0; a < 3; ++a) {
            o[a].resize(rays.size());
            inv[a].resize(rays.size());
        }
        tmin.resize(rays.size());
        for (std::size_t i = 0; i < rays.size(); ++i) {
            for (int a = 0; a < 3; ++a) {
                o[a][i] = rays[i].org[a];
                inv[a][i] = 1.0f / rays[i].dir[a];
            }
            tmin[i] = rays[i].tmin;
        }
    }
};

// reach[i] = whether ray i meets box b (min xyz, max xyz) within [tmin_i, tmax[i]]: the slab
// test, the cheap cull before a network query. A ray that starts inside the box with
// tmin <= 0 <= tmax meets it at t = 0 (every secondary ray leaving an LSNIF object's
// surface). A slab distance that is NaN (a direction component of 0 from a plane of the box:
// 0 * inf) does not constrain. Branch-free, so it vectorizes.
void reach_box(const RaySlabs& r, const std::array<float, 6>& box, const float* tmax,
               std::uint8_t* __restrict reach, std::size_t n) {
    const float lo[3] = {box[0], box[1], box[2]}, hi[3] = {box[3], box[4], box[5]};
    const float* __restrict ox = r.o[0].data(), * __restrict oy = r.o[1].data(), * __restrict oz = r.o[2].data();
    const float *__restrict ix = r.inv[0].data(), *__restrict iy = r.inv[1].data(), *__restrict iz = r.inv[2].data();
    const float* __restrict tmin = r.tmin.data();
    for (std::size_t i = 0; i < n; ++i) {
        const float o[3] = {ox[i], oy[i], oz[i]}, inv[3] = {ix[i], iy[i], iz[i]};
        bool inside = true;
        float t0 = tmin[i], t1 = tmax[i];
        for (int a = 0; a < 3; ++a) {
            inside &= (o[a] >= lo[a]) & (o[a] <= hi[a]);
            const float dl = (lo[a] - o[a]) * inv[a], dh = (hi[a] - o[a]) * inv[a];
            const bool swap = dl > dh;
            const float tn = swap ? dh : dl, tf = swap ? dl : dh;
            t0 = t0 < tn ? tn : t0;  // a NaN distance fails both comparisons: no constraint
            t1 = tf < t1 ? tf : t1;
        }
        reach[i] = (inside & (tmin[i] <= 0.0f) & (tmax[i] >= 0.0f)) | (t0 <= t1);
    }
}

// One thread's box-test scratch, set up for a trace call's `rays`: their slabs, each ray's
// own tmax (closest() lowers it to the hit so far) and room for the results.
struct BoxTests {
    RaySlabs slabs;
    std::vector<float> tmax;
    std::vector<std::uint8_t> reach;
};
BoxTests& box_tests_for(std::span<const lsnif_ray> rays) {
    thread_local BoxTests b;
    b.slabs.assign(rays);
    b.tmax.resize(rays.size());
    for (std::size_t i = 0; i < rays.size(); ++i) b.tmax[i] = rays[i].tmax;
    b.reach.resize(rays.size());
    return b;
}

constexpr std::size_t kBatch = 256;  // reader batches (lsnif.h: >= 256 amortizes best)

}  // namespace

TraceProfile& TraceProfile::operator+=(const TraceProfile& o) {
    seconds += o.seconds;
    embree_seconds += o.embree_seconds;
    reader_seconds += o.reader_seconds;
    rays += o.rays;
    box_hits += o.box_hits;
    reader_calls += o.reader_calls;
    reader_hits += o.reader_hits;
    return *this;
}

namespace {

// Adds a trace call's clock readings and counts to a caller's profile on return (nothing
// when the caller gave none). `embree_done`: when Embree's part ended; the reader's time is
// summed by the call as it goes.
struct ProfileScope {
    TraceProfile* out;
    TraceProfile p;
    base::Clock::time_point start = base::Clock::now(), embree_done = start;
    ProfileScope(TraceProfile* profile, std::size_t rays) : out(profile) { p.rays = rays; }
    ~ProfileScope() {
        if (!out) return;
        p.seconds = base::seconds_since(start);
        p.embree_seconds = std::chrono::duration<double>(embree_done - start).count();
        *out += p;
    }
    ProfileScope(const ProfileScope&) = delete;
    ProfileScope& operator=(const ProfileScope&) = delete;
};

}  // namespace

void EvalScene::closest(bool hybrid, std::span<const lsnif_ray> rays, std::span<TraceHit> hits,
                        TraceProfile* profile) const {
    const Impl& im = *impl_;
    ProfileScope prof(profile, rays.size());
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
    prof.embree_done = base::Clock::now();
    if (!hybrid) return;
    std::vector<lsnif_ray> batch;
    std::vector<std::uint32_t> idx;
    std::vector<lsnif_hit> out(kBatch);
    batch.reserve(kBatch);
    idx.reserve(kBatch);
    BoxTests& boxes = box_tests_for(rays);
    for (const std::uint32_t inst : im.lsnif_instances) {
        const Impl::Instance& in = im.instances[inst];
        const lsnif_model* model = im.meshes[in.mesh].model;
        auto flush = [&] {
            if (batch.empty()) return;
            const auto t0 = base::Clock::now();
            const lsnif_status st =
                lsnif_intersect_instance(model, in.transform.data(), batch.data(), batch.size(), out.data());
            prof.p.reader_seconds += base::seconds_since(t0);
            ++prof.p.reader_calls;
            prof.p.box_hits += batch.size();
            if (st == LSNIF_OK) {
                for (std::size_t k = 0; k < batch.size(); ++k) {
                    TraceHit& h = hits[idx[k]];
                    const lsnif_hit& o = out[k];
                    prof.p.reader_hits += o.hit;
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
        for (std::size_t i = 0; i < rays.size(); ++i)
            boxes.tmax[i] = hits[i].instance >= 0 ? hits[i].t : rays[i].tmax;
        reach_box(boxes.slabs, in.box, boxes.tmax.data(), boxes.reach.data(), rays.size());
        for (std::size_t i = 0; i < rays.size(); ++i) {
            if (!boxes.reach[i]) continue;
            batch.push_back(rays[i]);
            idx.push_back(std::uint32_t(i));
            if (batch.size() == kBatch) flush();
        }
        flush();
    }
}

void EvalScene::occluded(bool hybrid, std::span<const lsnif_ray> rays, std::span<std::uint8_t> occ,
                         TraceProfile* profile) const {
    const Impl& im = *impl_;
    ProfileScope prof(profile, rays.size());
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
    prof.embree_done = base::Clock::now();
    if (!hybrid) return;
    std::vector<lsnif_ray> batch;
    std::vector<std::uint32_t> idx;
    std::vector<std::uint8_t> out(kBatch);
    BoxTests& boxes = box_tests_for(rays);
    for (const std::uint32_t inst : im.lsnif_instances) {
        const Impl::Instance& in = im.instances[inst];
        const lsnif_model* model = im.meshes[in.mesh].model;
        // The any-hit query: a hit within the ray's [tmin, tmax] (lsnif.h), as rtcOccluded1.
        auto flush = [&] {
            if (batch.empty()) return;
            const auto t0 = base::Clock::now();
            const lsnif_status st =
                lsnif_occluded_instance(model, in.transform.data(), batch.data(), batch.size(), out.data());
            prof.p.reader_seconds += base::seconds_since(t0);
            ++prof.p.reader_calls;
            prof.p.box_hits += batch.size();
            if (st == LSNIF_OK)
                for (std::size_t k = 0; k < batch.size(); ++k) {
                    prof.p.reader_hits += out[k];
                    if (out[k]) occ[idx[k]] = 1;
                }
            batch.clear();
            idx.clear();
        };
        reach_box(boxes.slabs, in.box, boxes.tmax.data(), boxes.reach.data(), rays.size());
        for (std::size_t i = 0; i < rays.size(); ++i) {
            if (occ[i] || !boxes.reach[i]) continue;
            batch.push_back(rays[i]);
            idx.push_back(std::uint32_t(i));
            if (batch.size() == kBatch) flush();
        }
        flush();
    }
}

namespace {

// The source scene of every input that converted; an input that failed in convert
// (InputRecord::error) contributed no meshes and stays empty.
bool import_sources(const LoadedManifest& loaded, std::vector<scene::Scene>& scenes, std::string& error) {
    scenes.assign(loaded.sources.size(), {});
    for (std::size_t s = 0; s < loaded.sources.size(); ++s) {
        if (!loaded.inputs[s].ok()) continue;
        auto r = scene::import_scene(loaded.sources[s]);
        if (!r.ok()) {
            error = loaded.path.string() + ": input " + std::to_string(s) + ": " + r.error;
            return false;
        }
        scenes[s] = std::move(r.scene);
    }
    return true;
}

// Object-space bounds (min xyz, max xyz) of a mesh's vertices.
std::array<float, 6> vertex_bounds(const scene::Mesh& sm) {
    std::array<float, 6> box{INFINITY, INFINITY, INFINITY, -INFINITY, -INFINITY, -INFINITY};
    for (std::size_t v = 0; v < sm.vertex_count(); ++v)
        for (int a = 0; a < 3; ++a) {
            box[a] = std::min(box[a], sm.positions[v * 3 + a]);
            box[a + 3] = std::max(box[a + 3], sm.positions[v * 3 + a]);
        }
    return box;
}

// World-space bounds of an object-space box under an affine transform (its 8 corners).
std::array<float, 6> transformed_bounds(const Affine& transform, const std::array<float, 6>& ob) {
    std::array<float, 6> box{INFINITY, INFINITY, INFINITY, -INFINITY, -INFINITY, -INFINITY};
    for (int c = 0; c < 8; ++c) {
        const Vec3 p = apply_point(transform, {ob[c & 1 ? 3 : 0], ob[c & 2 ? 4 : 1], ob[c & 4 ? 5 : 2]});
        for (int a = 0; a < 3; ++a) {
            box[a] = std::min(box[a], p[a]);
            box[a + 3] = std::max(box[a + 3], p[a]);
        }
    }
    return box;
}

}  // namespace

bool EvalScene::Impl::open_device(std::string& error, const char* config) {
    device = rtcNewDevice(config);
    if (!device) {
        error = "embree: rtcNewDevice failed";
        return false;
    }
    rtcSetDeviceErrorFunction(device, &Impl::on_error, this);
    rtcSetDeviceMemoryMonitorFunction(device, &Impl::on_memory, this);
    return true;
}

bool EvalScene::Impl::upload(Mesh m, std::string& error) {
    const std::uint64_t before = memory;
    m.scene = rtcNewScene(device);
    RTCGeometry g = rtcNewGeometry(device, RTC_GEOMETRY_TYPE_TRIANGLE);
    auto* vb = static_cast<float*>(rtcSetNewGeometryBuffer(g, RTC_BUFFER_TYPE_VERTEX, 0, RTC_FORMAT_FLOAT3,
                                                           3 * sizeof(float), m.positions.size() / 3));
    auto* ib = static_cast<std::uint32_t*>(rtcSetNewGeometryBuffer(
        g, RTC_BUFFER_TYPE_INDEX, 0, RTC_FORMAT_UINT3, 3 * sizeof(std::uint32_t), m.indices.size() / 3));
    if (!vb || !ib) {
        rtcReleaseGeometry(g);
        error = "embree: cannot allocate buffers for mesh '" + m.name + "': " + embree_error;
        meshes.push_back(std::move(m));  // released by ~Impl
        return false;
    }
    std::memcpy(vb, m.positions.data(), m.positions.size() * sizeof(float));
    std::memcpy(ib, m.indices.data(), m.indices.size() * sizeof(std::uint32_t));
    rtcCommitGeometry(g);
    rtcAttachGeometry(m.scene, g);
    rtcReleaseGeometry(g);
    rtcCommitScene(m.scene);
    m.bvh_bytes = memory - before;
    meshes.push_back(std::move(m));
    return true;
}

bool EvalScene::Impl::add_mesh(const scene::Mesh& sm, const MeshOutcome& mo, const fs::path& outdir,
                               lsnif_arithmetic arithmetic, std::string& error) {
    Mesh m;
    m.name = sm.name;
    m.positions = sm.positions;
    m.normals = sm.normals;
    m.indices = sm.indices;
    m.box = vertex_bounds(sm);
    if (!upload(std::move(m), error)) return false;
    if (mo.cls() != MeshClass::complex || !mo.asset) return true;
    Mesh& added = meshes.back();  // released by ~Impl whatever happens next
    const fs::path asset = outdir / mo.asset->file;
    lsnif_error err{};
    if (lsnif_open_file(asset.c_str(), &added.model, &err) != LSNIF_OK) {
        error = asset.string() + ": cannot open the asset: " + lsnif_status_string(err.status) + " (" +
                err.message + ")";
        return false;
    }
    if (lsnif_set_arithmetic(added.model, arithmetic, nullptr) != LSNIF_OK) {
        error = asset.string() + ": cannot set the arithmetic " + lsnif_arithmetic_string(arithmetic);
        return false;
    }
    lsnif_info info{};
    lsnif_get_info(added.model, &info);
    added.lsnif_bytes = info.decoded_bytes;  // what this render holds, in the arithmetic it traces with
    return true;
}

bool EvalScene::Impl::place(std::uint32_t mesh, const Affine& transform, bool as_lsnif, std::string& error) {
    Instance in;
    in.mesh = mesh;
    in.transform = transform;
    const std::size_t i = instances.size();
    const auto inverse = base::invert_linear(in.transform.data());
    if (!inverse) {
        error = "instance " + std::to_string(i) + " has a singular or non-finite transform";
        return false;
    }
    in.nmat = base::normal_matrix(*inverse);
    in.box = transformed_bounds(in.transform, meshes[in.mesh].box);
    for (int a = 0; a < 3; ++a) {
        world[a] = std::min(world[a], in.box[a]);
        world[a + 3] = std::max(world[a + 3], in.box[a + 3]);
    }
    for (RTCScene top : {reference, hybrid}) {
        if (top == hybrid && as_lsnif) continue;
        RTCGeometry g = rtcNewGeometry(device, RTC_GEOMETRY_TYPE_INSTANCE);
        rtcSetGeometryInstancedScene(g, meshes[in.mesh].scene);
        rtcSetGeometryTransform(g, 0, RTC_FORMAT_FLOAT3X4_ROW_MAJOR, in.transform.data());
        rtcCommitGeometry(g);
        rtcAttachGeometryByID(top, g, std::uint32_t(i));
        rtcReleaseGeometry(g);
    }
    if (as_lsnif)
        lsnif_instances.push_back(std::uint32_t(i));
    else
        hybrid_has_geometry = true;
    instances.push_back(in);
    return true;
}

bool EvalScene::Impl::add_instance(std::size_t i, const json& ij, const EvalOptions& opt,
                                   const std::string& manifest_path, std::string& error) {
    const auto malformed = [&] {
        const json& t = ij.is_object() ? ij.value("transform", json()) : json();
        if (!ij.is_object() || !ij.value("mesh", json()).is_number_unsigned() || !t.is_array() ||
            t.size() != 12)
            return true;
        return std::any_of(t.begin(), t.end(), [](const json& x) { return !x.is_number(); });
    };
    if (malformed() || ij["mesh"].get<std::uint64_t>() >= meshes.size()) {
        error = manifest_path + ": instance " + std::to_string(i) + " is malformed";
        return false;
    }
    Affine transform{};
    for (int k = 0; k < 12; ++k) transform[k] = ij["transform"][k].get<float>();
    for (const auto& [which, m] : opt.instance_transforms)
        if (which == i) transform = m;
    const std::uint32_t mesh = ij["mesh"].get<std::uint32_t>();
    if (!place(mesh, transform, meshes[mesh].model != nullptr, error)) {
        error = manifest_path + ": " + error;
        return false;
    }
    return true;
}

std::unique_ptr<EvalScene> EvalScene::load(const EvalOptions& opt, std::string& error) {
    LoadedManifest loaded;
    if (!load_manifest(opt.outdir, opt.sources, loaded, error)) return nullptr;
    const std::string manifest_path = loaded.path.string();
    std::vector<scene::Scene> scenes;
    if (!import_sources(loaded, scenes, error)) return nullptr;
    auto impl = std::make_unique<Impl>();
    Impl& im = *impl;
    if (!im.open_device(error)) return nullptr;
    for (const MeshOutcome& mo : loaded.meshes) {
        const std::size_t input = mo.input, src = mo.source_mesh;
        if (input >= scenes.size() || src >= scenes[input].meshes.size()) {
            error = manifest_path + ": mesh '" + mo.name + "' refers to input " + std::to_string(input) +
                    " mesh " + std::to_string(src) + ", which the source does not have";
            return nullptr;
        }
        const scene::Mesh& sm = scenes[input].meshes[src];
        if (scene::geometry_hash(sm) != mo.geometry_hash) {
            error = loaded.sources[input] + ": mesh '" + sm.name +
                    "' differs from the converted geometry (geometry hash mismatch): re-run lsnif convert";
            return nullptr;
        }
        if (!im.add_mesh(sm, mo, opt.outdir, opt.arithmetic, error)) return nullptr;
    }
    im.reference = rtcNewScene(im.device);
    im.hybrid = rtcNewScene(im.device);
    im.world = {INFINITY, INFINITY, INFINITY, -INFINITY, -INFINITY, -INFINITY};
    const json& insts = loaded.doc["instances"];
    for (std::size_t i = 0; i < insts.size(); ++i)
        if (!im.add_instance(i, insts[i], opt, manifest_path, error)) return nullptr;
    if (im.instances.empty()) {
        error = manifest_path + ": no instances";
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

namespace eval_detail {

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

using base::seconds_since;

View make_view(const EvalOptions& opt, const std::array<float, 6>& world) {
    View v;
    v.W = opt.width;
    v.H = opt.height;
    const Vec3 lo{world[0], world[1], world[2]}, hi{world[3], world[4], world[5]};
    const Vec3 center = (lo + hi) * 0.5f;
    v.diag = std::max(length(hi - lo), 1e-20f);
    if (opt.camera)
        v.cam = *opt.camera;
    else {
        v.cam.target = center;
        v.cam.eye = center + normalize({0.55f, 0.4f, 1.0f}) * (1.15f * v.diag);
    }
    v.light = opt.light ? *opt.light : center + Vec3{0.5f, 1.2f, 0.7f} * v.diag;
    v.fwd = normalize(v.cam.target - v.cam.eye);
    v.right = cross(v.fwd, v.cam.up);
    if (length(v.right) < 1e-6f) v.right = cross(v.fwd, {1.0f, 0.0f, 0.0f});
    v.right = normalize(v.right);
    v.up = cross(v.right, v.fwd);
    v.tan_half = std::tan(0.5f * v.cam.fov_deg * 3.14159265f / 180.0f);
    v.aspect = float(v.W) / float(v.H);
    return v;
}

GBuffer render_primary(const EvalScene& scene, const std::vector<EvalScene::Impl::Instance>& instances,
                       const View& v, std::uint32_t threads, bool through_assets) {
    const std::uint32_t W = v.W, H = v.H;
    GBuffer gb;
    gb.p.resize(std::size_t(W) * H);
    gb.n.resize(gb.p.size());
    gb.inst.assign(gb.p.size(), -1);
    gb.eps.resize(gb.p.size());
    std::vector<double> per_thread(threads, 0.0);
    base::parallel_chunks(H, threads, 1, [&](std::uint32_t t, std::size_t y, std::size_t) {
        std::vector<lsnif_ray> rays(W);
        std::vector<TraceHit> hits(W);
        for (std::uint32_t x = 0; x < W; ++x) {
            const float sx = (2.0f * (float(x) + 0.5f) / float(W) - 1.0f) * v.tan_half * v.aspect;
            const float sy = (1.0f - 2.0f * (float(y) + 0.5f) / float(H)) * v.tan_half;
            const Vec3 d = normalize(v.fwd + v.right * sx + v.up * sy);
            rays[x] = {{v.cam.eye[0], v.cam.eye[1], v.cam.eye[2]}, 0.0f, {d[0], d[1], d[2]}, INFINITY};
        }
        const auto t0 = std::chrono::steady_clock::now();
        scene.closest(through_assets, rays, hits);
        per_thread[t] += seconds_since(t0);
        for (std::uint32_t x = 0; x < W; ++x) {
            const std::size_t i = std::size_t(y) * W + x;
            if (hits[x].instance < 0) continue;
            const Vec3 d{rays[x].dir[0], rays[x].dir[1], rays[x].dir[2]};
            gb.p[i] = v.cam.eye + d * hits[x].t;
            Vec3 n = hits[x].normal;
            if (dot(n, d) > 0.0f) n = n * -1.0f;  // shade the side the camera sees
            gb.n[i] = n;
            gb.inst[i] = hits[x].instance;
            // Same offset rule as the training family (b) rays (sampling.hpp): a fraction of
            // the object's diagonal plus a relative term for far-from-origin geometry.
            const auto& b = instances[hits[x].instance].box;
            const float m = std::max({std::fabs(gb.p[i][0]), std::fabs(gb.p[i][1]), std::fabs(gb.p[i][2])});
            gb.eps[i] = 1e-4f * length(Vec3{b[3] - b[0], b[4] - b[1], b[5] - b[2]}) + 1e-5f * m;
        }
    });
    for (double t : per_thread) gb.trace_seconds += t;
    return gb;
}

// The secondary rays of one row: a shadow ray to the light, S cosine-distributed AO rays
// and a mirror reflection per covered pixel, identical for both tracers (per-pixel random
// streams).
struct RowRays {
    std::vector<lsnif_ray> shadow, ao, refl;
    std::vector<std::uint32_t> px;  // the covered pixels' x
};

void make_row_rays(const GBuffer& gb, const View& v, const EvalOptions& opt, std::size_t y, std::uint32_t S,
                   RowRays& rr) {
    for (std::uint32_t x = 0; x < v.W; ++x) {
        const std::size_t i = y * v.W + x;
        if (gb.inst[i] < 0) continue;
        rr.px.push_back(x);
        const Vec3 n = gb.n[i], o = gb.p[i] + n * gb.eps[i];
        const Vec3 tl = v.light - o;
        const float dist = length(tl);
        rr.shadow.push_back({{o[0], o[1], o[2]}, 0.0f, {tl[0] / dist, tl[1] / dist, tl[2] / dist}, dist});
        // Cosine-weighted hemisphere about n (Malley's method), per-pixel stream.
        base::SplitMix64 rng{opt.seed * base::kGoldenGamma + i * 0xD1B54A32D192ED03ull};
        const Vec3 a = std::fabs(n[0]) > 0.5f ? Vec3{0, 1, 0} : Vec3{1, 0, 0};
        const Vec3 tx = normalize(cross(a, n)), ty = cross(n, tx);
        for (std::uint32_t k = 0; k < S; ++k) {
            const float r = std::sqrt(rng.uniform01f()), phi = 6.2831853f * rng.uniform01f();
            const float lx = r * std::cos(phi), ly = r * std::sin(phi);
            const Vec3 d = normalize(tx * lx + ty * ly + n * std::sqrt(std::max(0.0f, 1.0f - r * r)));
            rr.ao.push_back({{o[0], o[1], o[2]}, 0.0f, {d[0], d[1], d[2]}, opt.ao_radius * v.diag});
        }
        const Vec3 vd = normalize(gb.p[i] - v.cam.eye);
        const Vec3 rd = vd - n * (2.0f * dot(vd, n));
        rr.refl.push_back({{o[0], o[1], o[2]}, 0.0f, {rd[0], rd[1], rd[2]}, INFINITY});
    }
}

// Shades pixel k of a row from its traced secondary rays: Lambert with shadow, the open
// fraction of AO rays, the mirror bounce (the hit object's Lambert, or the sky), and the
// three combined as one picture: ambient light scaled by the AO fraction plus shadowed
// direct light, under a 20 % mirror coat.
void shade_pixel(const GBuffer& gb, const View& v, const std::vector<EvalScene::Impl::Instance>& instances,
                 const RowRays& rr, std::size_t k, std::size_t i, std::uint32_t S,
                 const std::vector<std::uint8_t>& shadow_occ, const std::vector<std::uint8_t>& ao_occ,
                 const TraceHit& h, EffectImages& out) {
    const Vec3 base = albedo(instances[gb.inst[i]].mesh);
    const Vec3 ldir = normalize(v.light - gb.p[i]);
    const float lambert = std::max(0.0f, dot(gb.n[i], ldir));
    const float direct = lambert * (shadow_occ[k] ? 0.0f : 1.0f);  // shadowed Lambert term
    const Vec3 sh = base * (0.12f + 0.88f * direct);
    std::uint32_t open = 0;
    for (std::uint32_t q = 0; q < S; ++q) open += ao_occ[k * S + q] ? 0u : 1u;
    const float aov = float(open) / float(S);
    Vec3 rc;
    const lsnif_ray& refl = rr.refl[k];
    const Vec3 rd{refl.dir[0], refl.dir[1], refl.dir[2]};
    if (h.instance >= 0) {
        const Vec3 hp = Vec3{refl.org[0], refl.org[1], refl.org[2]} + rd * h.t;
        Vec3 hn = h.normal;
        if (dot(hn, rd) > 0.0f) hn = hn * -1.0f;
        rc = albedo(instances[h.instance].mesh) *
             (0.2f + 0.8f * std::max(0.0f, dot(hn, normalize(v.light - hp))));
    } else {
        rc = sky(rd);
    }
    const Vec3 diffuse = base * (0.25f * aov + 0.75f * direct);
    const Vec3 combined = diffuse * 0.8f + rc * 0.2f;
    const Vec3 px[kEffects] = {sh, Vec3{aov, aov, aov}, mul(rc, Vec3{0.9f, 0.9f, 0.9f}), combined};
    for (int e = 0; e < kEffects; ++e)
        for (int c = 0; c < 3; ++c) out.rgb[e][i * 3 + c] = px[e][c];
}

// EvalOptions::surface_tmin_voxels in world units per instance: `voxels` times the edge of
// one occupancy voxel (the model box's largest extent over its grid resolution, times the
// instance transform's largest axis scale); 0 for instances not traced through LSNIF.
// Empty when `voxels` is 0: the option is off.
std::vector<float> surface_tmins(const EvalScene::Impl& im, float voxels) {
    if (!(voxels > 0)) return {};
    std::vector<float> tmin(im.instances.size(), 0.0f);
    for (const std::uint32_t i : im.lsnif_instances) {
        const EvalScene::Impl::Instance& in = im.instances[i];
        lsnif_info info{};
        if (lsnif_get_info(im.meshes[in.mesh].model, &info) != LSNIF_OK || info.grid_resolution == 0)
            continue;
        float extent = 0;
        for (int a = 0; a < 3; ++a) extent = std::max(extent, info.box_max[a] - info.box_min[a]);
        float scale = 0;
        for (int c = 0; c < 3; ++c)
            scale = std::max(scale, length(Vec3{in.transform[c], in.transform[4 + c], in.transform[8 + c]}));
        tmin[i] = voxels * (extent / float(info.grid_resolution) * scale);
    }
    return tmin;
}

// surface_tmins() on one row's rays: every secondary ray of a pixel whose primary hit is an
// LSNIF instance starts that far from the surface.
void start_later(const GBuffer& gb, const std::vector<float>& surface_tmin, std::size_t row0, std::uint32_t S,
                 RowRays& rr) {
    const auto later = [](lsnif_ray& r, float tmin) { r.tmin = std::min(tmin, r.tmax); };
    for (std::size_t k = 0; k < rr.px.size(); ++k) {
        const float tmin = surface_tmin[gb.inst[row0 + rr.px[k]]];
        if (tmin <= 0) continue;
        later(rr.shadow[k], tmin);
        for (std::uint32_t q = 0; q < S; ++q) later(rr.ao[k * S + q], tmin);
        later(rr.refl[k], tmin);
    }
}

// What one tracer answers for a row's rays.
struct RowHits {
    std::vector<std::uint8_t> shadow_occ, ao_occ;
    std::vector<TraceHit> refl_hit;
};

// Traces a row's secondary rays with one tracer into `hits`, and where the time went into
// `profile` (overwritten); returns the seconds it took.
double trace_row(const EvalScene& scene, bool hybrid, const RowRays& rr, RowHits& hits,
                 SecondaryProfile& profile) {
    hits.shadow_occ.resize(rr.shadow.size());
    hits.ao_occ.resize(rr.ao.size());
    hits.refl_hit.resize(rr.refl.size());
    profile = {};
    const auto t0 = std::chrono::steady_clock::now();
    scene.occluded(hybrid, rr.shadow, hits.shadow_occ, &profile[0]);
    scene.occluded(hybrid, rr.ao, hits.ao_occ, &profile[1]);
    scene.closest(hybrid, rr.refl, hits.refl_hit, &profile[2]);
    return seconds_since(t0);
}

// The three effect images and their combination, traced row by row with both tracers: the
// reference (Embree only) and the hybrid (LSNIF reader for complex meshes), whose secondary
// rays from LSNIF pixels start `surface_tmin` (per instance, world units; empty = at the
// surface) from it. The traces of a row run back to back on one thread, alternating between
// the tracers EvalOptions::timing_repeats times, and each tracer's fastest counts: the
// machine's drifts (shared hosts, frequency) hit both sides of the time ratio alike, and a
// stall that hits one trace is left out.
BothImages render_secondary(const EvalScene& scene, const std::vector<EvalScene::Impl::Instance>& instances,
                            const GBuffer& gb, const View& v, const EvalOptions& opt,
                            const std::vector<float>& surface_tmin, std::uint32_t threads, Tracers tracers) {
    const std::uint32_t W = v.W, S = std::max(1u, opt.ao_samples);
    BothImages out;
    for (EffectImages* side : {&out.reference, &out.hybrid})
        for (auto& img : side->rgb) img.assign(std::size_t(W) * v.H * 3, 0.0f);
    std::vector<double> per_thread[2] = {std::vector<double>(threads, 0.0),
                                         std::vector<double>(threads, 0.0)};
    std::vector<SecondaryProfile> profiles[2] = {std::vector<SecondaryProfile>(threads),
                                                 std::vector<SecondaryProfile>(threads)};
    const std::uint32_t repeats = std::max(1u, opt.timing_repeats);
    base::parallel_chunks(v.H, threads, 1, [&](std::uint32_t t, std::size_t y, std::size_t) {
        RowRays rays[2];
        make_row_rays(gb, v, opt, y, S, rays[0]);
        rays[1] = rays[0];
        if (!surface_tmin.empty()) start_later(gb, surface_tmin, y * W, S, rays[1]);
        RowHits hits[2];
        double fastest[2] = {INFINITY, INFINITY};
        SecondaryProfile profile, fastest_profile[2];
        const bool traced[2] = {tracers != Tracers::hybrid, tracers != Tracers::reference};
        for (std::uint32_t r = 0; r < repeats; ++r)
            for (const int side : {0, 1}) {
                if (!traced[side]) continue;
                const double s = trace_row(scene, side == 1, rays[side], hits[side], profile);
                if (s < fastest[side]) fastest[side] = s, fastest_profile[side] = profile;
            }
        for (const int side : {0, 1}) {
            if (!traced[side]) continue;
            per_thread[side][t] += fastest[side];
            for (int f = 0; f < kRayFamilies; ++f) profiles[side][t][f] += fastest_profile[side][f];
            const RowRays& rr = rays[side];
            EffectImages& img = side ? out.hybrid : out.reference;
            const auto& [shadow_occ, ao_occ, refl_hit] = hits[side];
            for (std::uint32_t x = 0; x < W; ++x)  // background everywhere first
                for (int e = 0; e < kEffects; ++e)
                    for (int c = 0; c < 3; ++c) img.rgb[e][(y * W + x) * 3 + c] = kBackground[c];
            for (std::size_t k = 0; k < rr.px.size(); ++k)
                shade_pixel(gb, v, instances, rr, k, y * W + rr.px[k], S, shadow_occ, ao_occ, refl_hit[k],
                            img);
        }
    });
    for (double s : per_thread[0]) out.reference.trace_seconds += s;
    for (double s : per_thread[1]) out.hybrid.trace_seconds += s;
    for (std::uint32_t t = 0; t < threads; ++t)
        for (int f = 0; f < kRayFamilies; ++f) {
            out.reference.profile[f] += profiles[0][t][f];
            out.hybrid.profile[f] += profiles[1][t][f];
        }
    return out;
}

// The FLIP errors of the pixels `mask` selects, in pixel order.
std::vector<float> masked_errors(const std::vector<float>& error_map, const std::vector<std::uint8_t>& mask) {
    std::vector<float> out;
    for (std::size_t i = 0; i < mask.size(); ++i)
        if (mask[i]) out.push_back(error_map[i]);
    return out;
}

bool write_effect_images(const image::Image& ref, const image::Image& test, const image::FlipResult& f, int e,
                         const std::string& label, const fs::path& images, EffectComparison& c,
                         std::string& error) {
    const std::string stem = kEffectNames[e];
    const std::string flip_stem = label == "hybrid" ? "flip_" : "flip_" + label + "_";
    const image::Image heat = image::heatmap(f.error_map, ref.width, ref.height);
    const std::pair<std::string, const image::Image*> files[] = {{"reference_" + stem + ".png", &ref},
                                                                 {label + "_" + stem + ".png", &test},
                                                                 {flip_stem + stem + ".png", &heat}};
    for (const auto& [file, img] : files) {
        auto w = image::write_png((images / file).string(), *img);
        if (!w) {
            error = w.error().message;
            return false;
        }
    }
    c.files = {files[0].first, files[1].first, files[2].first};
    return true;
}

bool compare_effect(const EffectImages& reference, const EffectImages& test, const View& v, int e,
                    const std::vector<std::uint8_t>& lsnif_pixels, const fs::path& images, bool write_images,
                    EffectComparison& c, std::string& error, const std::string& label) {
    image::Image ref{v.W, v.H, reference.rgb[e]}, hyb{v.W, v.H, test.rgb[e]};
    for (auto* im2 : {&ref, &hyb})
        for (float& x : im2->rgb) x = image::linear_to_srgb(std::clamp(x, 0.0f, 1.0f));
    auto f = image::flip(ref, hyb, image::FlipOptions{});
    if (!f) {
        error = std::string("flip: ") + kEffectNames[e] + ": " + f.error().message;
        return false;
    }
    c.flip = f->stats;
    c.psnr_db = image::psnr(ref, hyb);
    c.lsnif_pixel_errors = masked_errors(f->error_map, lsnif_pixels);
    if (!c.lsnif_pixel_errors.empty()) c.flip_lsnif_pixels = image::error_stats(c.lsnif_pixel_errors);
    return !write_images || write_effect_images(ref, hyb, *f, e, label, images, c, error);
}

bool compare_effects(const EffectImages& reference, const EffectImages& test, const View& v,
                     const std::vector<std::uint8_t>& lsnif_pixels, const fs::path& images, bool write_images,
                     Comparison& out, std::string& error, const std::string& label) {
    double flip_sum = 0;
    for (int e = 0; e < kEffects; ++e) {
        if (!compare_effect(reference, test, v, e, lsnif_pixels, images, write_images, out.effect[e], error,
                            label))
            return false;
        if (e < kSeparateEffects) flip_sum += out.effect[e].flip.mean;
    }
    out.flip_mean = flip_sum / double(kSeparateEffects);
    return true;
}

// The report's "images": per effect its FLIP, PSNR (null for identical images: infinite),
// FLIP over the LSNIF pixels (null when there are none) and its files.
json comparison_json(const Comparison& c) {
    json per = json::object();
    for (int e = 0; e < kEffects; ++e) {
        const EffectComparison& x = c.effect[e];
        json j = {{"flip_mean", x.flip.mean},
                  {"flip_median", x.flip.median},
                  {"flip_p95", x.flip.p95},
                  {"flip_max", x.flip.max}};
        j["psnr_db"] = std::isfinite(x.psnr_db) ? json(x.psnr_db) : json(nullptr);
        j["flip_mean_lsnif_pixels"] = x.flip_lsnif_pixels ? json(x.flip_lsnif_pixels->mean) : json(nullptr);
        j["flip_p95_lsnif_pixels"] = x.flip_lsnif_pixels ? json(x.flip_lsnif_pixels->p95) : json(nullptr);
        if (!x.files.empty())
            j["files"] = {{"reference", x.files[0]}, {"hybrid", x.files[1]}, {"flip", x.files[2]}};
        per[kEffectNames[e]] = j;
    }
    return per;
}

std::vector<std::uint8_t> mask_union(const std::vector<std::uint8_t>& a, const std::vector<std::uint8_t>& b) {
    std::vector<std::uint8_t> out(a.size());
    for (std::size_t i = 0; i < a.size(); ++i) out[i] = a[i] | b[i];
    return out;
}

// 1 for the pixels whose primary hit is an instance the hybrid render traces as an LSNIF.
std::vector<std::uint8_t> lsnif_pixel_mask(const GBuffer& gb, const EvalScene::Impl& im) {
    std::vector<std::uint8_t> traced(im.instances.size(), 0), mask(gb.inst.size(), 0);
    for (const std::uint32_t i : im.lsnif_instances) traced[i] = 1;
    for (std::size_t i = 0; i < gb.inst.size(); ++i) mask[i] = gb.inst[i] >= 0 && traced[gb.inst[i]];
    return mask;
}

// `text` to `path` through a temporary file and a rename: no half-written file.
bool write_text_atomically(const fs::path& path, const std::string& text, std::string& error) {
    const fs::path tmp = path.string() + ".tmp";
    {
        std::ofstream o(tmp);
        o << text;
        if (!o) {
            error = tmp.string() + ": cannot write";
            std::error_code ec;
            fs::remove(tmp, ec);
            return false;
        }
    }
    std::error_code ec;
    fs::rename(tmp, path, ec);
    if (ec) {
        error = path.string() + ": " + ec.message();
        return false;
    }
    return true;
}

// The report's account of what was rendered and how: the LSNIF models' arithmetic and
// memory, the image size, ambient occlusion and timing settings, camera, light and
// instance counts. The results (images, FLIP, timings) are added by the caller.
json describe_run(const EvalScene::Impl& im, const EvalOptions& opt, const View& view) {
    std::uint64_t lsnif_bytes = 0, bvh_replaced = 0;
    lsnif_arithmetic arithmetic = LSNIF_ARITHMETIC_FP32;  // every model gets the same request
    for (const auto& m : im.meshes)
        if (m.model) {
            lsnif_bytes += m.lsnif_bytes, bvh_replaced += m.bvh_bytes;
            arithmetic = lsnif_get_arithmetic(m.model);
        }
    json report;
    report["lsnif_arithmetic"] = lsnif_arithmetic_string(arithmetic);
    report["width"] = view.W;
    report["height"] = view.H;
    report["ao_samples"] = std::max(1u, opt.ao_samples);
    report["ao_radius"] = opt.ao_radius * view.diag;
    report["surface_tmin_voxels"] = opt.surface_tmin_voxels;
    report["timing_repeats"] = std::max(1u, opt.timing_repeats);
    report["camera"] = {{"eye", view.cam.eye},
                        {"target", view.cam.target},
                        {"up", view.cam.up},
                        {"fov_deg", view.cam.fov_deg}};
    report["light"] = view.light;
    report["instances"] = im.instances.size();
    report["lsnif_instances"] = im.lsnif_instances.size();
    // Resident bytes of the opened assets (lsnif_info.decoded_bytes) against Embree's BVHs of
    // the meshes they replace, measured in this render's device.
    report["memory"] = {{"lsnif_resident_bytes", lsnif_bytes}, {"bvh_bytes_replaced", bvh_replaced}};
    return report;
}

}  // namespace eval_detail

using namespace eval_detail;

namespace {

// A tracer's profile per ray family, for the report (docs/eval.md "Where the secondary rays'
// time goes"): seconds summed over threads, counts over the frame.
json profile_json(const SecondaryProfile& profile) {
    json j = json::object();
    for (int f = 0; f < kRayFamilies; ++f) {
        const TraceProfile& p = profile[f];
        j[kRayFamilyNames[f]] = {
            {"seconds", p.seconds},
            {"embree_seconds", p.embree_seconds},
            {"reader_seconds", p.reader_seconds},
            {"cull_and_batch_seconds", std::max(0.0, p.seconds - p.embree_seconds - p.reader_seconds)},
            {"rays", p.rays},
            {"reader_rays", p.box_hits},
            {"reader_calls", p.reader_calls},
            {"reader_hits", p.reader_hits}};
    }
    return j;
}

}  // namespace

EvalResult render_and_compare(const EvalOptions& opt) {
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
    const std::uint32_t threads = base::resolve_threads(opt.threads);
    const View view = make_view(opt, im.world);

    // Primary visibility twice: from the meshes (the hybrid render's, as a rasterizer would)
    // and through the assets (the all-neural render's); each timed at its fastest of the
    // repeats, alternating.
    double primary_seconds = INFINITY, neural_primary_seconds = INFINITY;
    GBuffer gb, neural_gb;
    for (std::uint32_t r = 0; r < std::max(1u, opt.timing_repeats); ++r) {
        gb = render_primary(*scene, im.instances, view, threads);
        primary_seconds = std::min(primary_seconds, gb.trace_seconds);
        neural_gb = render_primary(*scene, im.instances, view, threads, true);
        neural_primary_seconds = std::min(neural_primary_seconds, neural_gb.trace_seconds);
    }
    const std::vector<float> tmins = surface_tmins(im, opt.surface_tmin_voxels);
    const BothImages both = render_secondary(*scene, im.instances, gb, view, opt, tmins, threads);
    const EffectImages& reference = both.reference;
    const EffectImages& hybrid = both.hybrid;
    const EffectImages neural =
        render_secondary(*scene, im.instances, neural_gb, view, opt, tmins, threads, Tracers::hybrid).hybrid;

    const fs::path images = opt.images_dir.empty() ? fs::path(opt.outdir) / "eval" : fs::path(opt.images_dir);
    if (opt.write_images) {
        std::error_code ec;
        fs::create_directories(images, ec);
        if (ec) {
            res.errors.push_back(images.string() + ": cannot create directory: " + ec.message());
            return res;
        }
    }
    Comparison compared, compared_neural;
    const std::vector<std::uint8_t> lsnif_pixels = lsnif_pixel_mask(gb, im);
    // The all-neural render's LSNIF pixels: where the mesh or the asset is what the camera sees.
    const std::vector<std::uint8_t> neural_pixels = mask_union(lsnif_pixels, lsnif_pixel_mask(neural_gb, im));
    if (!compare_effects(reference, hybrid, view, lsnif_pixels, images, opt.write_images, compared, err) ||
        !compare_effects(reference, neural, view, neural_pixels, images, opt.write_images, compared_neural,
                         err, "neural")) {
        res.errors.push_back(err);
        return res;
    }
    json report = describe_run(im, opt, view);
    report["images"] = comparison_json(compared);
    report["flip_mean"] = compared.flip_mean;
    report["lsnif_pixels"] = std::count(lsnif_pixels.begin(), lsnif_pixels.end(), 1);
    const double reference_seconds = primary_seconds + reference.trace_seconds;
    const double neural_seconds = neural_primary_seconds + neural.trace_seconds;
    report["all_neural"] = {{"images", comparison_json(compared_neural)},
                            {"flip_mean", compared_neural.flip_mean},
                            {"lsnif_pixels", std::count(neural_pixels.begin(), neural_pixels.end(), 1)},
                            {"time_ratio", reference_seconds > 0 ? neural_seconds / reference_seconds : 0.0}};
    report["timings"] = {{"primary", primary_seconds},
                         {"primary_neural", neural_primary_seconds},
                         {"secondary_reference", reference.trace_seconds},
                         {"secondary_hybrid", hybrid.trace_seconds},
                         {"secondary_neural", neural.trace_seconds}};
    report["secondary_time_ratio"] =
        reference.trace_seconds > 0 ? hybrid.trace_seconds / reference.trace_seconds : 0.0;
    report["secondary_profile"] = {{"reference", profile_json(reference.profile)},
                                   {"hybrid", profile_json(hybrid.profile)}};
    report["images_dir"] = images.string();
    if (opt.write_images && !write_text_atomically(images / "report.json", report.dump(2) + "\n", err)) {
        res.errors.push_back(err);
        return res;
    }
    res.report = std::move(report);
    return res;
}

}  // namespace lsnif::converter
