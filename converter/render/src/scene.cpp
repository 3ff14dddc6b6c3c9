// The two tracers (scene.hpp): Embree everywhere, and Embree with the LSNIF reader for the
// meshes that have an asset; and how a scene is built.
#include <lsnif/base/affine.hpp>
#include <lsnif/base/clock.hpp>
#include "scene_impl.hpp"

#include <algorithm>
#include <chrono>
#include <cstring>
#include <vector>

namespace lsnif::render {

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

// Packet `p` of rays b, b + 1, ... (at most 16; each lane as init_rayhit sets a single ray)
// with `valid` switching off the lanes past the end of `rays`; returns how many are on.
std::size_t load_packet(RTCRay16& p, int (&valid)[16], std::span<const lsnif_ray> rays, std::size_t b) {
    const std::size_t n = std::min<std::size_t>(16, rays.size() - b);
    for (std::size_t k = 0; k < 16; ++k) {
        const lsnif_ray& r = rays[b + (k < n ? k : 0)];
        valid[k] = k < n ? -1 : 0;
        p.org_x[k] = r.org[0];
        p.org_y[k] = r.org[1];
        p.org_z[k] = r.org[2];
        p.dir_x[k] = r.dir[0];
        p.dir_y[k] = r.dir[1];
        p.dir_z[k] = r.dir[2];
        p.tnear[k] = r.tmin;
        p.tfar[k] = r.tmax;
        p.time[k] = 0.0f;
        p.mask[k] = 0xFFFFFFFFu;
        p.id[k] = 0;
        p.flags[k] = 0;
    }
    return n;
}

// Embree's answers for `rays` (the tracer's top-level scene `top`) by `route`: closest hits
// into `hits` (decoded by im.embree_hit), or whether each ray is occluded into `occ`.
// Packets hold 16 consecutive rays (load_packet).
void embree_closest(const EvalScene::Impl& im, RTCScene top, EmbreeRoute route,
                    std::span<const lsnif_ray> rays, std::span<TraceHit> hits) {
    RTCIntersectContext ctx;
    rtcInitIntersectContext(&ctx);
    if (route == EmbreeRoute::single) {
        for (std::size_t i = 0; i < rays.size(); ++i) {
            RTCRayHit rh;
            init_rayhit(rays[i], rh);
            rtcIntersect1(top, &ctx, &rh);
            hits[i] = im.embree_hit(rh, rays[i]);
        }
        return;
    }
    alignas(64) RTCRayHit16 p;
    alignas(64) int valid[16];
    for (std::size_t b = 0; b < rays.size(); b += 16) {
        const std::size_t n = load_packet(p.ray, valid, rays, b);
        for (std::size_t k = 0; k < 16; ++k) {
            p.hit.geomID[k] = RTC_INVALID_GEOMETRY_ID;
            p.hit.primID[k] = RTC_INVALID_GEOMETRY_ID;
            p.hit.instID[0][k] = RTC_INVALID_GEOMETRY_ID;
        }
        rtcIntersect16(valid, top, &ctx, &p);
        for (std::size_t k = 0; k < n; ++k) {
            RTCRayHit rh;
            rh.ray.tfar = p.ray.tfar[k];
            rh.hit.geomID = p.hit.geomID[k];
            rh.hit.primID = p.hit.primID[k];
            rh.hit.instID[0] = p.hit.instID[0][k];
            rh.hit.u = p.hit.u[k];
            rh.hit.v = p.hit.v[k];
            hits[b + k] = im.embree_hit(rh, rays[b + k]);
        }
    }
}

void embree_occluded(RTCScene top, EmbreeRoute route, std::span<const lsnif_ray> rays,
                     std::span<std::uint8_t> occ) {
    RTCIntersectContext ctx;
    rtcInitIntersectContext(&ctx);
    // Embree marks an occluded ray with tfar = -inf.
    if (route == EmbreeRoute::single) {
        for (std::size_t i = 0; i < rays.size(); ++i) {
            RTCRayHit rh;
            init_rayhit(rays[i], rh);
            rtcOccluded1(top, &ctx, &rh.ray);
            occ[i] = rh.ray.tfar < 0.0f;
        }
        return;
    }
    alignas(64) RTCRay16 p;
    alignas(64) int valid[16];
    for (std::size_t b = 0; b < rays.size(); b += 16) {
        const std::size_t n = load_packet(p, valid, rays, b);
        rtcOccluded16(valid, top, &ctx, &p);
        for (std::size_t k = 0; k < n; ++k) occ[b + k] = p.tfar[k] < 0.0f;
    }
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

// The reader's share of a trace call: for every LSNIF instance, the rays that reach its box
// (reach_box within boxes.tmax, which `bound(inst)` sets first) and that `wanted(i)` still
// keeps, in batches of kBatch, each batch answered by `query(model, transform, rays, n)` (the
// reader's instance call, which writes the answers) and each answer k of ray i handed to
// `take(inst, k, i)`, which returns whether it was a hit (for the profile).
template <class Bound, class Wanted, class Query, class Take>
void through_assets(const EvalScene::Impl& im, std::span<const lsnif_ray> rays, BoxTests& boxes,
                    TraceProfile& profile, Bound&& bound, Wanted&& wanted, Query&& query, Take&& take) {
    thread_local std::vector<lsnif_ray> gathered;
    thread_local std::vector<std::uint32_t> idx;
    gathered.resize(kBatch);
    idx.resize(kBatch);
    for (const std::uint32_t inst : im.lsnif_instances) {
        const EvalScene::Impl::Instance& in = im.instances[inst];
        const lsnif_model* model = im.meshes[in.mesh].model;
        std::size_t n = 0;
        // The batch idx[0..n): where its indices are one run (every ray of a stretch reaches
        // the box, as the rays leaving an asset's own surface do) the caller's rays are
        // passed as they are, else copied together.
        const auto flush = [&] {
            if (!n) return;
            const lsnif_ray* batch = rays.data() + idx[0];
            if (idx[n - 1] - idx[0] + 1 != n) {
                for (std::size_t k = 0; k < n; ++k) gathered[k] = rays[idx[k]];
                batch = gathered.data();
            }
            const auto t0 = base::Clock::now();
            const lsnif_status st = query(model, in.transform.data(), batch, n);
            profile.reader_seconds += base::seconds_since(t0);
            ++profile.reader_calls;
            profile.box_hits += n;
            if (st == LSNIF_OK)
                for (std::size_t k = 0; k < n; ++k) profile.reader_hits += take(inst, k, idx[k]);
            n = 0;
        };
        bound(inst);
        reach_box(boxes.slabs, in.box, boxes.tmax.data(), boxes.reach.data(), rays.size());
        for (std::size_t i = 0; i < rays.size(); ++i) {
            if (!boxes.reach[i] || !wanted(i)) continue;
            idx[n++] = std::uint32_t(i);
            if (n == kBatch) flush();
        }
        flush();
    }
}

}  // namespace

void EvalScene::closest(bool hybrid, std::span<const lsnif_ray> rays, std::span<TraceHit> hits,
                        TraceProfile* profile) const {
    const Impl& im = *impl_;
    ProfileScope prof(profile, rays.size());
    if (hybrid && !im.hybrid_has_geometry)
        std::fill(hits.begin(), hits.end(), TraceHit{});
    else
        embree_closest(im, hybrid ? im.hybrid : im.reference, im.embree_route, rays, hits);
    prof.embree_done = base::Clock::now();
    if (!hybrid) return;
    std::vector<lsnif_hit> out(kBatch);
    BoxTests& boxes = box_tests_for(rays);
    // An instance's box test is bounded by the closest hit so far.
    const auto bound = [&](std::uint32_t) {
        for (std::size_t i = 0; i < rays.size(); ++i)
            boxes.tmax[i] = hits[i].instance >= 0 ? hits[i].t : rays[i].tmax;
    };
    const auto query = [&](const lsnif_model* model, const float* transform, const lsnif_ray* batch,
                           std::size_t n) {
        return lsnif_intersect_instance(model, transform, batch, n, out.data());
    };
    const auto take = [&](std::uint32_t inst, std::size_t k, std::uint32_t i) {
        TraceHit& h = hits[i];
        const lsnif_hit& o = out[k];
        const float best = h.instance >= 0 ? h.t : rays[i].tmax;
        if (o.hit && o.t >= rays[i].tmin && o.t <= best) {
            h.t = o.t;
            h.normal = normalize({o.normal[0], o.normal[1], o.normal[2]});
            h.instance = std::int32_t(inst);
        }
        return o.hit != 0;
    };
    through_assets(
        im, rays, boxes, prof.p, bound, [](std::size_t) { return true; }, query, take);
}

void EvalScene::occluded(bool hybrid, std::span<const lsnif_ray> rays, std::span<std::uint8_t> occ,
                         TraceProfile* profile) const {
    const Impl& im = *impl_;
    ProfileScope prof(profile, rays.size());
    if (hybrid && !im.hybrid_has_geometry)
        std::fill(occ.begin(), occ.end(), std::uint8_t{0});
    else
        embree_occluded(hybrid ? im.hybrid : im.reference, im.embree_route, rays, occ);
    prof.embree_done = base::Clock::now();
    if (!hybrid) return;
    std::vector<std::uint8_t> out(kBatch);
    // The any-hit query: a hit within the ray's [tmin, tmax] (lsnif.h), as Embree's; a ray
    // already occluded is not traced again.
    const auto query = [&](const lsnif_model* model, const float* transform, const lsnif_ray* batch,
                           std::size_t n) {
        return lsnif_occluded_instance(model, transform, batch, n, out.data());
    };
    const auto take = [&](std::uint32_t, std::size_t k, std::uint32_t i) {
        if (out[k]) occ[i] = 1;
        return out[k] != 0;
    };
    through_assets(
        im, rays, box_tests_for(rays), prof.p, [](std::uint32_t) {}, [&](std::size_t i) { return !occ[i]; },
        query, take);
}

AssetMemory EvalScene::asset_memory() const {
    AssetMemory m;
    for (const Impl::Mesh& mesh : impl_->meshes)
        if (mesh.model) {
            m.lsnif_resident_bytes += mesh.lsnif_bytes;
            m.bvh_bytes_replaced += mesh.bvh_bytes;
            m.arithmetic = lsnif_get_arithmetic(mesh.model);  // every asset gets the same request
        }
    return m;
}

std::array<float, 6> bounds_of(std::span<const float> positions) {
    std::array<float, 6> box{INFINITY, INFINITY, INFINITY, -INFINITY, -INFINITY, -INFINITY};
    for (std::size_t v = 0; v + 2 < positions.size(); v += 3)
        for (int a = 0; a < 3; ++a) {
            box[a] = std::min(box[a], positions[v + a]);
            box[a + 3] = std::max(box[a + 3], positions[v + a]);
        }
    return box;
}

namespace {

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
    if (exact_hits) m.around = base::VertexTriangles(m.indices, m.positions.size() / 3);
    meshes.push_back(std::move(m));
    return true;
}

bool EvalScene::Impl::place(std::uint32_t mesh, const Affine& transform, bool as_lsnif, std::string& error) {
    if (!reference) {
        reference = rtcNewScene(device);
        hybrid = rtcNewScene(device);
        world = {INFINITY, INFINITY, INFINITY, -INFINITY, -INFINITY, -INFINITY};
    }
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

bool EvalScene::Impl::commit(std::string& error) {
    rtcCommitScene(reference);
    rtcCommitScene(hybrid);
    if (!embree_error.empty()) {
        error = "embree: " + embree_error;
        return false;
    }
    return true;
}

SceneBuilder::SceneBuilder() : impl_(std::make_unique<EvalScene::Impl>()) {}
SceneBuilder::~SceneBuilder() = default;

const char* embree_route_name(EmbreeRoute route) {
    return route == EmbreeRoute::single ? "single" : "packets16";
}

bool SceneBuilder::open(std::string& error, EmbreeRoute route) {
    impl_->embree_route = route;
    return impl_->open_device(error);
}

bool SceneBuilder::add_mesh(const SceneMesh& mesh, const AssetSettings& settings, std::string& error) {
    EvalScene::Impl::Mesh m;
    m.name = mesh.name;
    m.positions.assign(mesh.positions.begin(), mesh.positions.end());
    m.normals.assign(mesh.normals.begin(), mesh.normals.end());
    m.indices.assign(mesh.indices.begin(), mesh.indices.end());
    m.box = bounds_of(mesh.positions);
    if (!impl_->upload(std::move(m), error)) return false;
    if (mesh.asset.empty()) return true;
    EvalScene::Impl::Mesh& added = impl_->meshes.back();  // released by ~Impl whatever happens next
    lsnif_error err{};
    if (lsnif_open_file(mesh.asset.c_str(), &added.model, &err) != LSNIF_OK) {
        error = mesh.asset + ": cannot open the asset: " + lsnif_status_string(err.status) + " (" +
                err.message + ")";
        return false;
    }
    if (lsnif_set_arithmetic(added.model, settings.arithmetic, nullptr) != LSNIF_OK) {
        error = mesh.asset + ": cannot set the arithmetic " + lsnif_arithmetic_string(settings.arithmetic);
        return false;
    }
    lsnif_info info{};
    lsnif_get_info(added.model, &info);
    if (lsnif_set_escape_points(added.model, settings.escape_points) != LSNIF_OK) {
        error = mesh.asset + ": escape points " + std::to_string(settings.escape_points) +
                " exceed the asset's " + std::to_string(info.max_points) + " entry points per ray";
        return false;
    }
    if (lsnif_set_enclosed_rule(added.model, settings.enclosed_rule) != LSNIF_OK) {
        error = mesh.asset + ": out of memory turning the enclosed rule on";
        return false;
    }
    added.lsnif_bytes = info.decoded_bytes;  // what this scene holds, in the arithmetic it traces with
    return true;
}

std::size_t SceneBuilder::mesh_count() const {
    return impl_->meshes.size();
}

bool SceneBuilder::add_instance(std::uint32_t mesh, const std::array<float, 12>& transform,
                                std::string& error) {
    if (mesh >= impl_->meshes.size()) {
        error = "instance " + std::to_string(impl_->instances.size()) + " names mesh " +
                std::to_string(mesh) + " of " + std::to_string(impl_->meshes.size());
        return false;
    }
    return impl_->place(mesh, transform, impl_->meshes[mesh].model != nullptr, error);
}

std::size_t SceneBuilder::instance_count() const {
    return impl_->instances.size();
}

std::unique_ptr<EvalScene> SceneBuilder::finish(std::string& error) {
    if (impl_->instances.empty()) {
        error = "a scene without instances";
        return nullptr;
    }
    if (!impl_->commit(error)) return nullptr;
    return std::unique_ptr<EvalScene>(new EvalScene(std::move(impl_)));
}

}  // namespace lsnif::render
