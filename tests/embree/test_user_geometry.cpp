// The Embree user geometry (lsnif_embree.h) against the reader's own batched calls, on an
// asset trained on CGAL's Chinese dragon (the embree_asset fixture): the same hits from
// rtcIntersect1/4/8/16 and rtcOccluded1/4/8/16 as from lsnif_intersect_instance and
// lsnif_occluded_instance on the same rays, in object space and under a rotation with a
// non-uniform scale, next to a triangle mesh, through filter functions, with the model's
// enclosed rule and inside an Embree instance.
#include <doctest/doctest.h>

#include <lsnif/lsnif_embree.h>
#include <lsnif/base/random.hpp>

#include "../format/asset_rays.hpp"

#include <algorithm>
#include <array>
#include <atomic>
#include <cmath>
#include <cstring>
#include <filesystem>
#include <limits>
#include <string>
#include <vector>

namespace {

constexpr float kInf = std::numeric_limits<float>::infinity();

// The fixture's asset: the only .lsnif file the embree_asset test wrote.
std::string fixture_asset() {
    for (const auto& e : std::filesystem::directory_iterator(LSNIF_EMBREE_ASSET_DIR))
        if (e.path().extension() == ".lsnif") return e.path().string();
    FAIL("no .lsnif in " LSNIF_EMBREE_ASSET_DIR " (run the embree_asset test first)");
    return {};
}

struct Model {
    lsnif_model* m = nullptr;
    lsnif_info info{};
    Model() {
        REQUIRE(lsnif_open_file(fixture_asset().c_str(), &m, nullptr) == LSNIF_OK);
        REQUIRE(lsnif_get_info(m, &info) == LSNIF_OK);
    }
    ~Model() { lsnif_close(m); }
    Model(const Model&) = delete;
    Model& operator=(const Model&) = delete;
};

struct Device {
    RTCDevice d = rtcNewDevice(nullptr);
    ~Device() { rtcReleaseDevice(d); }
    Device() = default;
    Device(const Device&) = delete;
    Device& operator=(const Device&) = delete;
};

// A rotation of 50 degrees about (1, 2, 3), then a scale of (1.5, 0.6, 2.2) along the
// rotated axes, then a translation: object_to_world = [R S | b].
std::array<float, 12> rotated_scaled() {
    const double a = 50.0 * 3.14159265358979 / 180.0, c = std::cos(a), s = std::sin(a);
    const double n = std::sqrt(14.0), x = 1 / n, y = 2 / n, z = 3 / n;
    const double R[3][3] = {{c + x * x * (1 - c), x * y * (1 - c) - z * s, x * z * (1 - c) + y * s},
                            {y * x * (1 - c) + z * s, c + y * y * (1 - c), y * z * (1 - c) - x * s},
                            {z * x * (1 - c) - y * s, z * y * (1 - c) + x * s, c + z * z * (1 - c)}};
    const double S[3] = {1.5, 0.6, 2.2}, b[3] = {3.0, -1.0, 0.5};
    std::array<float, 12> m{};
    for (int r = 0; r < 3; ++r) {
        for (int k = 0; k < 3; ++k) m[4 * r + k] = float(R[r][k] * S[k]);
        m[4 * r + 3] = float(b[r]);
    }
    return m;
}

std::array<float, 3> apply(const float* m, const float* p) {
    if (!m) return {p[0], p[1], p[2]};
    std::array<float, 3> w{};
    for (int r = 0; r < 3; ++r)
        w[r] = m[4 * r] * p[0] + m[4 * r + 1] * p[1] + m[4 * r + 2] * p[2] + m[4 * r + 3];
    return w;
}

// Rays from a sphere around the placed asset towards random points of its box (most reach
// the dragon's voxels, some miss it), with tmax = +infinity or, with `finite`, cut at a
// random point between the origin and twice the distance to the box's centre.
std::vector<lsnif_ray> rays_at(const lsnif_info& info, const float* m, std::size_t count, bool finite) {
    lsnif::base::SplitMix64 rng{finite ? 7u : 3u};
    const float* lo = info.box_min;
    const float* hi = info.box_max;
    const float centre_o[3] = {0.5f * (lo[0] + hi[0]), 0.5f * (lo[1] + hi[1]), 0.5f * (lo[2] + hi[2])};
    const auto centre = apply(m, centre_o);
    const float diag = std::sqrt((hi[0] - lo[0]) * (hi[0] - lo[0]) + (hi[1] - lo[1]) * (hi[1] - lo[1]) +
                                 (hi[2] - lo[2]) * (hi[2] - lo[2]));
    const float radius = 3.0f * diag * (m ? 2.2f : 1.0f);
    std::vector<lsnif_ray> rays(count);
    for (lsnif_ray& r : rays) {
        float u[3];
        float len2 = 0;
        do {
            len2 = 0;
            for (float& v : u) v = rng.uniform(-1, 1), len2 += v * v;
        } while (len2 > 1 || len2 < 1e-4f);
        const float target_o[3] = {rng.uniform(lo[0], hi[0]), rng.uniform(lo[1], hi[1]),
                                   rng.uniform(lo[2], hi[2])};
        const auto target = apply(m, target_o);
        for (int a = 0; a < 3; ++a) {
            r.org[a] = centre[a] + radius * u[a] / std::sqrt(len2);
            r.dir[a] = target[a] - r.org[a];
        }
        r.tmin = 0.0f;
        r.tmax = finite ? rng.uniform(0.0f, 2.0f) : kInf;
    }
    return rays;
}

// The reader's batched answers: object space without a transform, else the instance's.
std::vector<lsnif_hit> batched_hits(const Model& model, const float* m, const std::vector<lsnif_ray>& rays) {
    std::vector<lsnif_hit> hits(rays.size());
    const lsnif_status s = m ? lsnif_intersect_instance(model.m, m, rays.data(), rays.size(), hits.data())
                             : lsnif_intersect(model.m, rays.data(), rays.size(), hits.data());
    REQUIRE(s == LSNIF_OK);
    return hits;
}

std::vector<std::uint8_t> batched_occluded(const Model& model, const float* m,
                                           const std::vector<lsnif_ray>& rays) {
    std::vector<std::uint8_t> occ(rays.size());
    const lsnif_status s = m ? lsnif_occluded_instance(model.m, m, rays.data(), rays.size(), occ.data())
                             : lsnif_occluded(model.m, rays.data(), rays.size(), occ.data());
    REQUIRE(s == LSNIF_OK);
    return occ;
}

// What one Embree query returns for one ray.
struct EmbreeHit {
    bool hit = false;
    float t = kInf;
    float ng[3] = {0, 0, 0};
    unsigned prim = RTC_INVALID_GEOMETRY_ID, geom = RTC_INVALID_GEOMETRY_ID, inst = RTC_INVALID_GEOMETRY_ID;
};

// A packet of width N in Embree's SOA layout (RTCRayHit4/8/16 have this layout).
template <int N>
struct alignas(64) Packet {
    RTCRayHitNt<N> rh;
    int valid[N];
};

// Rays [base, base + N) into a packet. In packets (N > 1) every seventh ray's lane is switched
// off: the geometry must leave it alone.
template <int N>
void load(Packet<N>& p, const std::vector<lsnif_ray>& rays, std::size_t base) {
    for (int i = 0; i < N; ++i) {
        const bool on = base + i < rays.size() && (N == 1 || (base + i) % 7 != 3);
        p.valid[i] = on ? -1 : 0;
        const lsnif_ray& r = rays[on ? base + i : 0];
        p.rh.ray.org_x[i] = r.org[0], p.rh.ray.org_y[i] = r.org[1], p.rh.ray.org_z[i] = r.org[2];
        p.rh.ray.dir_x[i] = r.dir[0], p.rh.ray.dir_y[i] = r.dir[1], p.rh.ray.dir_z[i] = r.dir[2];
        p.rh.ray.tnear[i] = r.tmin;
        p.rh.ray.tfar[i] = on ? r.tmax : -12345.0f;  // a value the geometry must not touch
        p.rh.ray.time[i] = 0;
        p.rh.ray.mask[i] = 0xFFFFFFFFu;
        p.rh.ray.id[i] = 0;
        p.rh.ray.flags[i] = 0;
        p.rh.hit.geomID[i] = RTC_INVALID_GEOMETRY_ID;
        p.rh.hit.primID[i] = RTC_INVALID_GEOMETRY_ID;
        p.rh.hit.instID[0][i] = RTC_INVALID_GEOMETRY_ID;
    }
}

template <int N>
void query_packet(RTCScene scene, RTCIntersectContext* ctx, Packet<N>& p) {
    if constexpr (N == 4) rtcIntersect4(p.valid, scene, ctx, reinterpret_cast<RTCRayHit4*>(&p.rh));
    if constexpr (N == 8) rtcIntersect8(p.valid, scene, ctx, reinterpret_cast<RTCRayHit8*>(&p.rh));
    if constexpr (N == 16) rtcIntersect16(p.valid, scene, ctx, reinterpret_cast<RTCRayHit16*>(&p.rh));
}

template <int N>
void occlusion_packet(RTCScene scene, RTCIntersectContext* ctx, Packet<N>& p) {
    if constexpr (N == 4) rtcOccluded4(p.valid, scene, ctx, reinterpret_cast<RTCRay4*>(&p.rh.ray));
    if constexpr (N == 8) rtcOccluded8(p.valid, scene, ctx, reinterpret_cast<RTCRay8*>(&p.rh.ray));
    if constexpr (N == 16) rtcOccluded16(p.valid, scene, ctx, reinterpret_cast<RTCRay16*>(&p.rh.ray));
}

// Closest hits of every ray through packets of width N (N = 1: rtcIntersect1). A switched-off
// lane is traced alone afterwards, and its packet's copy must be untouched.
template <int N>
std::vector<EmbreeHit> embree_closest(RTCScene scene, const std::vector<lsnif_ray>& rays,
                                      RTCIntersectContext* context = nullptr) {
    std::vector<EmbreeHit> out(rays.size());
    RTCIntersectContext own;
    rtcInitIntersectContext(&own);
    RTCIntersectContext* ctx = context ? context : &own;
    auto take = [&](std::size_t k, const RTCRayNt<N>& ray, const RTCHitNt<N>& hit, int i) {
        EmbreeHit& h = out[k];
        h.hit = hit.geomID[i] != RTC_INVALID_GEOMETRY_ID;
        h.t = h.hit ? ray.tfar[i] : kInf;
        h.ng[0] = hit.Ng_x[i], h.ng[1] = hit.Ng_y[i], h.ng[2] = hit.Ng_z[i];
        h.prim = hit.primID[i], h.geom = hit.geomID[i], h.inst = hit.instID[0][i];
    };
    for (std::size_t base = 0; base < rays.size(); base += N) {
        if constexpr (N == 1) {
            Packet<1> p;
            load(p, rays, base);
            rtcIntersect1(scene, ctx, reinterpret_cast<RTCRayHit*>(&p.rh));
            take(base, p.rh.ray, p.rh.hit, 0);
        } else {
            Packet<N> p;
            load(p, rays, base);
            query_packet(scene, ctx, p);
            for (int i = 0; i < N && base + i < rays.size(); ++i) {
                if (p.valid[i] == -1) {
                    take(base + i, p.rh.ray, p.rh.hit, i);
                    continue;
                }
                CHECK(p.rh.ray.tfar[i] == -12345.0f);
                CHECK(p.rh.hit.geomID[i] == RTC_INVALID_GEOMETRY_ID);
                out[base + i] = embree_closest<1>(scene, {rays[base + i]}, ctx)[0];
            }
        }
    }
    return out;
}

template <int N>
std::vector<std::uint8_t> embree_occluded(RTCScene scene, const std::vector<lsnif_ray>& rays,
                                          RTCIntersectContext* context = nullptr) {
    std::vector<std::uint8_t> out(rays.size());
    RTCIntersectContext own;
    rtcInitIntersectContext(&own);
    RTCIntersectContext* ctx = context ? context : &own;
    for (std::size_t base = 0; base < rays.size(); base += N) {
        Packet<N> p;
        load(p, rays, base);
        if constexpr (N == 1) {
            rtcOccluded1(scene, ctx, reinterpret_cast<RTCRay*>(&p.rh.ray));
            out[base] = p.rh.ray.tfar[0] == -kInf;
        } else {
            occlusion_packet(scene, ctx, p);
            for (int i = 0; i < N && base + i < rays.size(); ++i) {
                if (p.valid[i] == -1) {
                    out[base + i] = p.rh.ray.tfar[i] == -kInf;
                    continue;
                }
                CHECK(p.rh.ray.tfar[i] == -12345.0f);
                out[base + i] = embree_occluded<1>(scene, {rays[base + i]}, ctx)[0];
            }
        }
    }
    return out;
}

// A scene holding the asset's user geometry (and the caller's release of it).
struct AssetScene {
    RTCScene scene;
    RTCGeometry geometry = nullptr;
    unsigned id = 0;
    AssetScene(const Device& dev, const Model& model, const float* m) : scene(rtcNewScene(dev.d)) {
        REQUIRE(lsnif_embree_new_geometry(dev.d, model.m, m, &geometry) == LSNIF_OK);
        id = rtcAttachGeometry(scene, geometry);
        rtcCommitScene(scene);
    }
    ~AssetScene() {
        rtcReleaseScene(scene);
        lsnif_embree_release_geometry(geometry);
    }
    AssetScene(const AssetScene&) = delete;
    AssetScene& operator=(const AssetScene&) = delete;
};

// Every ray's closest hit through Embree equals the reader's, bit for bit.
void expect_same_hits(const std::vector<EmbreeHit>& got, const std::vector<lsnif_hit>& want, unsigned geom) {
    std::size_t hits = 0, differ = 0;
    for (std::size_t i = 0; i < got.size(); ++i) {
        const EmbreeHit& g = got[i];
        const lsnif_hit& w = want[i];
        hits += w.hit;
        const bool same = g.hit == bool(w.hit) &&
                          (!w.hit || (g.t == w.t && g.ng[0] == w.normal[0] && g.ng[1] == w.normal[1] &&
                                      g.ng[2] == w.normal[2] && g.prim == w.material && g.geom == geom &&
                                      g.inst == RTC_INVALID_GEOMETRY_ID));
        differ += !same;
    }
    CHECK(differ == 0);
    // The rays are not all hits or all misses: the comparison decides something.
    CHECK(hits > got.size() / 10);
    CHECK(hits < got.size() * 9 / 10);
}

void expect_same_occlusion(const std::vector<std::uint8_t>& got, const std::vector<std::uint8_t>& want) {
    std::size_t occluded = 0, differ = 0;
    for (std::size_t i = 0; i < got.size(); ++i) occluded += want[i], differ += got[i] != want[i];
    CHECK(differ == 0);
    CHECK(occluded > got.size() / 20);
    CHECK(occluded < got.size() * 19 / 20);
}

}  // namespace

TEST_CASE("the user geometry gives lsnif_intersect_instance's hits for single rays and 4/8/16-wide packets") {
    const Model model;
    const Device dev;
    const std::array<float, 12> xf = rotated_scaled();
    for (const float* m : {static_cast<const float*>(nullptr), xf.data()}) {
        CAPTURE(m != nullptr);
        const AssetScene s(dev, model, m);
        const std::vector<lsnif_ray> rays = rays_at(model.info, m, 3000, false);
        const std::vector<lsnif_hit> want = batched_hits(model, m, rays);
        expect_same_hits(embree_closest<1>(s.scene, rays), want, s.id);
        expect_same_hits(embree_closest<4>(s.scene, rays), want, s.id);
        expect_same_hits(embree_closest<8>(s.scene, rays), want, s.id);
        expect_same_hits(embree_closest<16>(s.scene, rays), want, s.id);
    }
}

TEST_CASE(
    "the user geometry gives lsnif_occluded_instance's decisions on segments, single rays and packets") {
    const Model model;
    const Device dev;
    const std::array<float, 12> xf = rotated_scaled();
    for (const float* m : {static_cast<const float*>(nullptr), xf.data()}) {
        CAPTURE(m != nullptr);
        const AssetScene s(dev, model, m);
        const std::vector<lsnif_ray> rays = rays_at(model.info, m, 3000, true);
        const std::vector<std::uint8_t> want = batched_occluded(model, m, rays);
        expect_same_occlusion(embree_occluded<1>(s.scene, rays), want);
        expect_same_occlusion(embree_occluded<4>(s.scene, rays), want);
        expect_same_occlusion(embree_occluded<8>(s.scene, rays), want);
        expect_same_occlusion(embree_occluded<16>(s.scene, rays), want);
    }
}

namespace {

// Calls of the occlusion filter below, which accepts every candidate.
std::atomic<std::size_t> occlusion_filter_calls{0};
extern "C" void count_occlusion_filter(const RTCFilterFunctionNArguments*) {
    ++occlusion_filter_calls;
}

}  // namespace

TEST_CASE(
    "with the model's enclosed rule on, the occluded callback decides as lsnif_occluded_instance under the "
    "rule, without occlusion filters") {
    const Model model;
    const Device dev;
    std::vector<lsnif_ray> outside, leaving;
    lsnif_test::make_rays(model.m, outside, leaving);
    leaving.resize(std::min<std::size_t>(leaving.size(), 8000));
    const std::vector<std::uint8_t> off = batched_occluded(model, nullptr, leaving);
    REQUIRE(lsnif_set_enclosed_rule(model.m, 1) == LSNIF_OK);
    const std::vector<std::uint8_t> on = batched_occluded(model, nullptr, leaving);
    std::size_t turned = 0;
    for (std::size_t i = 0; i < leaving.size(); ++i) turned += on[i] != off[i];
    CHECK(turned > 0);  // the rule answers some of these rays otherwise: the comparison sees it
    const AssetScene s(dev, model, nullptr);
    expect_same_occlusion(embree_occluded<1>(s.scene, leaving), on);
    expect_same_occlusion(embree_occluded<4>(s.scene, leaving), on);
    expect_same_occlusion(embree_occluded<8>(s.scene, leaving), on);
    expect_same_occlusion(embree_occluded<16>(s.scene, leaving), on);
    const std::array<float, 12> xf = rotated_scaled();
    const AssetScene placed(dev, model, xf.data());
    const std::vector<lsnif_ray> segments = rays_at(model.info, xf.data(), 3000, true);
    expect_same_occlusion(embree_occluded<16>(placed.scene, segments),
                          batched_occluded(model, xf.data(), segments));

    // An occlusion filter on the geometry is not called while the rule is on, and is again
    // once it is off.
    rtcSetGeometryOccludedFilterFunction(s.geometry, count_occlusion_filter);
    rtcCommitGeometry(s.geometry);
    rtcCommitScene(s.scene);
    occlusion_filter_calls = 0;
    CHECK(embree_occluded<16>(s.scene, leaving) == on);
    CHECK(occlusion_filter_calls == 0);
    REQUIRE(lsnif_set_enclosed_rule(model.m, 0) == LSNIF_OK);
    CHECK(embree_occluded<16>(s.scene, leaving) == off);
    CHECK(occlusion_filter_calls > 0);
}

namespace {

// A quad through the middle of the placed asset's box, facing +z in object space: some rays
// meet it before the dragon, some after.
RTCGeometry quad_through(const Device& dev, const lsnif_info& info, const float* m) {
    RTCGeometry g = rtcNewGeometry(dev.d, RTC_GEOMETRY_TYPE_TRIANGLE);
    auto* v =
        static_cast<float*>(rtcSetNewGeometryBuffer(g, RTC_BUFFER_TYPE_VERTEX, 0, RTC_FORMAT_FLOAT3, 12, 4));
    auto* idx =
        static_cast<unsigned*>(rtcSetNewGeometryBuffer(g, RTC_BUFFER_TYPE_INDEX, 0, RTC_FORMAT_UINT3, 12, 2));
    const float z = 0.5f * (info.box_min[2] + info.box_max[2]);
    const float corners[4][3] = {{info.box_min[0], info.box_min[1], z},
                                 {info.box_max[0], info.box_min[1], z},
                                 {info.box_max[0], info.box_max[1], z},
                                 {info.box_min[0], info.box_max[1], z}};
    for (int c = 0; c < 4; ++c) {
        const auto w = apply(m, corners[c]);
        std::memcpy(v + 3 * c, w.data(), sizeof w);
    }
    const unsigned tris[6] = {0, 1, 2, 0, 2, 3};
    std::memcpy(idx, tris, sizeof tris);
    rtcCommitGeometry(g);
    return g;
}

}  // namespace

TEST_CASE("next to a triangle mesh, the nearer of the mesh's and the asset's hits wins") {
    const Model model;
    const Device dev;
    const std::array<float, 12> xf = rotated_scaled();
    const std::vector<lsnif_ray> rays = rays_at(model.info, xf.data(), 2000, false);
    const std::vector<lsnif_hit> asset = batched_hits(model, xf.data(), rays);

    RTCScene mesh_only = rtcNewScene(dev.d);
    RTCGeometry quad = quad_through(dev, model.info, xf.data());
    rtcAttachGeometry(mesh_only, quad);
    rtcCommitScene(mesh_only);
    const std::vector<EmbreeHit> mesh = embree_closest<1>(mesh_only, rays);

    RTCScene both = rtcNewScene(dev.d);
    const unsigned quad_id = rtcAttachGeometry(both, quad);
    RTCGeometry g = nullptr;
    REQUIRE(lsnif_embree_new_geometry(dev.d, model.m, xf.data(), &g) == LSNIF_OK);
    const unsigned asset_id = rtcAttachGeometry(both, g);
    rtcCommitScene(both);
    const std::vector<EmbreeHit> got = embree_closest<8>(both, rays);

    std::size_t asset_wins = 0, mesh_wins = 0, differ = 0;
    for (std::size_t i = 0; i < rays.size(); ++i) {
        const float ta = asset[i].hit ? asset[i].t : kInf;
        const float tm = mesh[i].hit ? mesh[i].t : kInf;
        if (ta == kInf && tm == kInf) {
            differ += got[i].hit;
        } else if (ta < tm) {
            ++asset_wins;
            differ += !(got[i].geom == asset_id && got[i].t == ta);
        } else {
            ++mesh_wins;
            differ += !(got[i].geom == quad_id && got[i].t == tm);
        }
    }
    CHECK(differ == 0);
    CHECK(asset_wins > rays.size() / 20);
    CHECK(mesh_wins > rays.size() / 20);
    rtcReleaseScene(both);
    rtcReleaseScene(mesh_only);
    rtcReleaseGeometry(quad);
    lsnif_embree_release_geometry(g);
}

namespace {

// A context filter that rejects every hit of one geometry and counts what it saw.
struct RejectingContext {
    RTCIntersectContext base;  // first: Embree hands the filter this pointer
    unsigned reject_geom;
    std::size_t calls = 0, lanes = 0, wrong_fields = 0;
};

extern "C" void reject_geometry(const RTCFilterFunctionNArguments* args) {
    auto* ctx = reinterpret_cast<RejectingContext*>(args->context);
    ++ctx->calls;
    for (unsigned i = 0; i < args->N; ++i) {
        if (args->valid[i] != -1) continue;
        ++ctx->lanes;
        const unsigned geom = RTCHitN_geomID(args->hit, args->N, i);
        // The candidate's fields as lsnif_embree.h states them: a unit normal, u = v = 0,
        // and the ray's tfar set to the candidate's distance.
        const float nx = RTCHitN_Ng_x(args->hit, args->N, i), ny = RTCHitN_Ng_y(args->hit, args->N, i),
                    nz = RTCHitN_Ng_z(args->hit, args->N, i);
        if (geom == ctx->reject_geom &&
            (std::fabs(nx * nx + ny * ny + nz * nz - 1.0f) > 1e-4f ||
             RTCHitN_u(args->hit, args->N, i) != 0.0f || !(RTCRayN_tfar(args->ray, args->N, i) > 0.0f)))
            ++ctx->wrong_fields;
        if (geom == ctx->reject_geom) args->valid[i] = 0;
    }
}

}  // namespace

TEST_CASE("filter functions judge the asset's hits: a rejected hit lets the ray go on to the mesh") {
    const Model model;
    const Device dev;
    const std::array<float, 12> xf = rotated_scaled();
    const std::vector<lsnif_ray> rays = rays_at(model.info, xf.data(), 1500, false);

    RTCScene both = rtcNewScene(dev.d);
    rtcSetSceneFlags(both,
                     RTC_SCENE_FLAG_CONTEXT_FILTER_FUNCTION);  // Embree calls a context's filter only then
    RTCGeometry quad = quad_through(dev, model.info, xf.data());
    rtcAttachGeometry(both, quad);
    RTCGeometry g = nullptr;
    REQUIRE(lsnif_embree_new_geometry(dev.d, model.m, xf.data(), &g) == LSNIF_OK);
    const unsigned asset_id = rtcAttachGeometry(both, g);
    rtcCommitScene(both);

    RTCScene mesh_only = rtcNewScene(dev.d);
    rtcAttachGeometry(mesh_only, quad);
    rtcCommitScene(mesh_only);
    const std::vector<EmbreeHit> mesh = embree_closest<1>(mesh_only, rays);

    RejectingContext ctx;
    rtcInitIntersectContext(&ctx.base);
    ctx.base.filter = reject_geometry;
    ctx.reject_geom = asset_id;
    const std::vector<EmbreeHit> got = embree_closest<16>(both, rays, &ctx.base);
    std::size_t differ = 0;
    for (std::size_t i = 0; i < rays.size(); ++i)
        differ += got[i].hit != mesh[i].hit || (got[i].hit && got[i].t != mesh[i].t);
    CHECK(differ == 0);  // with the asset's hits rejected, exactly the mesh's hits remain
    CHECK(ctx.lanes > rays.size() / 10);
    CHECK(ctx.wrong_fields == 0);

    // Occlusion: the asset's hits rejected, a ray is occluded exactly when the mesh occludes it.
    const std::vector<lsnif_ray> segments = rays_at(model.info, xf.data(), 1500, true);
    const std::vector<std::uint8_t> mesh_occ = embree_occluded<1>(mesh_only, segments);
    RejectingContext occ_ctx;
    rtcInitIntersectContext(&occ_ctx.base);
    occ_ctx.base.filter = reject_geometry;
    occ_ctx.reject_geom = asset_id;
    CHECK(embree_occluded<16>(both, segments, &occ_ctx.base) == mesh_occ);
    CHECK(occ_ctx.lanes > 0);
    CHECK(occ_ctx.wrong_fields == 0);

    // The same filter set on the asset's geometry instead of the context.
    rtcSetGeometryIntersectFilterFunction(g, reject_geometry);
    rtcSetGeometryOccludedFilterFunction(g, reject_geometry);
    rtcCommitGeometry(g);
    rtcCommitScene(both);
    RejectingContext geom_ctx;
    rtcInitIntersectContext(&geom_ctx.base);
    geom_ctx.reject_geom = asset_id;
    const std::vector<EmbreeHit> filtered = embree_closest<1>(both, rays, &geom_ctx.base);
    differ = 0;
    for (std::size_t i = 0; i < rays.size(); ++i)
        differ += filtered[i].hit != mesh[i].hit || (filtered[i].hit && filtered[i].t != mesh[i].t);
    CHECK(differ == 0);
    CHECK(geom_ctx.lanes > rays.size() / 10);
    CHECK(embree_occluded<8>(both, segments, &geom_ctx.base) == mesh_occ);
    CHECK(geom_ctx.wrong_fields == 0);

    rtcReleaseScene(both);
    rtcReleaseScene(mesh_only);
    rtcReleaseGeometry(quad);
    lsnif_embree_release_geometry(g);
}

TEST_CASE("inside an Embree instance the asset is traced in the instance's space") {
    const Model model;
    const Device dev;
    const std::array<float, 12> xf = rotated_scaled();
    const AssetScene object(dev, model, nullptr);
    RTCScene world = rtcNewScene(dev.d);
    RTCGeometry inst = rtcNewGeometry(dev.d, RTC_GEOMETRY_TYPE_INSTANCE);
    rtcSetGeometryInstancedScene(inst, object.scene);
    rtcSetGeometryTransform(inst, 0, RTC_FORMAT_FLOAT3X4_ROW_MAJOR, xf.data());
    rtcCommitGeometry(inst);
    const unsigned inst_id = rtcAttachGeometry(world, inst);
    rtcCommitScene(world);

    const std::vector<lsnif_ray> rays = rays_at(model.info, xf.data(), 3000, false);
    const std::vector<lsnif_hit> want = batched_hits(model, xf.data(), rays);
    const std::vector<EmbreeHit> got = embree_closest<4>(world, rays);
    // Embree maps the rays into the instance with its own arithmetic, the reader with its
    // own: the network's inputs differ in the last bits, so decisions near the surface's
    // edge may differ on a few rays and distances agree to float precision.
    std::size_t hits = 0, decided_alike = 0, far = 0;
    for (std::size_t i = 0; i < rays.size(); ++i) {
        hits += want[i].hit;
        if (got[i].hit != bool(want[i].hit)) continue;
        ++decided_alike;
        if (!got[i].hit) continue;
        CHECK(got[i].inst == inst_id);
        CHECK(got[i].geom == object.id);
        far += std::fabs(got[i].t - want[i].t) > 1e-3f * want[i].t;
    }
    CHECK(hits > rays.size() / 10);
    CHECK(decided_alike >= rays.size() * 998 / 1000);
    CHECK(far <= rays.size() / 1000);
    rtcReleaseScene(world);
    rtcReleaseGeometry(inst);
}

TEST_CASE("bad arguments are refused and leave no geometry") {
    const Model model;
    const Device dev;
    RTCGeometry g = reinterpret_cast<RTCGeometry>(&g);  // must be reset to NULL on failure
    CHECK(lsnif_embree_new_geometry(nullptr, model.m, nullptr, &g) == LSNIF_ERR_INVALID_ARGUMENT);
    CHECK(g == nullptr);
    CHECK(lsnif_embree_new_geometry(dev.d, nullptr, nullptr, &g) == LSNIF_ERR_INVALID_ARGUMENT);
    CHECK(lsnif_embree_new_geometry(dev.d, model.m, nullptr, nullptr) == LSNIF_ERR_INVALID_ARGUMENT);
    const float flat[12] = {1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 0, 0};  // z flattened: singular
    g = reinterpret_cast<RTCGeometry>(&g);
    CHECK(lsnif_embree_new_geometry(dev.d, model.m, flat, &g) == LSNIF_ERR_INVALID_ARGUMENT);
    CHECK(g == nullptr);
    const float nan[12] = {1, 0, 0, NAN, 0, 1, 0, 0, 0, 0, 1, 0};
    CHECK(lsnif_embree_new_geometry(dev.d, model.m, nan, &g) == LSNIF_ERR_INVALID_ARGUMENT);
    const float huge[12] = {1e38f, 0, 0, 0, 0, 1e38f, 0, 0, 0, 0, 1e38f, 0};  // the box overflows float
    CHECK(lsnif_embree_new_geometry(dev.d, model.m, huge, &g) == LSNIF_ERR_INVALID_ARGUMENT);
    lsnif_embree_release_geometry(nullptr);  // allowed
    CHECK(rtcGetDeviceError(dev.d) == RTC_ERROR_NONE);
}
