// The reference integration for a renderer author: load a `lsnif convert` output
// directory and render the hybrid scene — Embree's BVH for simple meshes, the LSNIF reader
// for complex ones — with a point light and hard shadows, into a binary PPM.
//
//   lsnif_render OUTDIR|OUTDIR/scene.gltf OUT.ppm [WIDTH HEIGHT] [--camera ex,ey,ez,tx,ty,tz]
//                [--user-geometry [--packet 1|4|8|16]]
//
// Two ways to trace the assets, the same image from both:
//   batched (default)  Embree traces the simple meshes in packets of 16 rays, then the reader
//                      answers each asset instance's rays a row at a time
//                      (lsnif_intersect_instance, lsnif_occluded_instance): what each is
//                      fastest at.
//   --user-geometry    every asset instance is an Embree user geometry (lsnif_embree.h) in the
//                      same scene as the meshes, and Embree alone is called, with single rays
//                      or with packets of --packet rays: what a renderer that already traces
//                      through Embree changes least to adopt.
//
// Every asset is opened with the escape rule its metadata names (metrics.escape_points,
// lsnif_set_escape_points): shadow rays that leave its surface and stay within a run of that
// many occupied voxels skip the network. And with the enclosed rule (lsnif_set_enclosed_rule):
// shadow rays that cross into the space its shell of voxels shuts in are occluded without
// the network. Both routes apply them alike (the user geometry's occluded callback then
// calls no occlusion filter; this renderer sets none).
//
// OUTDIR/scene.gltf is the same scene as a glTF whose converted meshes carry the
// LSNIF_neural_geometry extension (schema/LSNIF_neural_geometry.md): a renderer that already
// loads glTF needs only that extension. Read from here on, the manifest route:
//
// What a renderer needs from the conversion is all in OUTDIR/manifest.json
// (schema/manifest.schema.json):
//   inputs[i].path       the source file, relative to OUTDIR (resolve it as OUTDIR/path: the
//                        converted scene works from any working directory and can be moved
//                        together with its sources)
//   meshes[i].class      "complex" (trace its .lsnif), else "simple" or "failed" (trace the source mesh)
//   meshes[i].lsnif.file the asset, relative to OUTDIR, shared by all instances of the mesh
//   meshes[i].input / source_mesh   where the simple geometry is (the renderer's importer
//                                   reads it; here lsnif::scene stands in for that importer)
//   instances[j]         mesh index and object-to-world 3x4 row-major transform
// The reader is thread-safe for concurrent lsnif_intersect_instance calls on one model
// and works best on batches of >= 256 rays, so the batched route traces a row at a time.
//
// Embree (and the reader) are only given rays whose origin and direction are finite: a
// pixel whose primary ray missed has no shadow ray at all.
#include <lsnif/lsnif.h>
#include <lsnif/lsnif_embree.h>
#include <lsnif/base/affine.hpp>
#include <lsnif/scene/scene.hpp>

#include <embree3/rtcore.h>
#include <nlohmann/json.hpp>

#include <algorithm>
#include <array>
#include <chrono>
#include <cmath>
#include <cstdint>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <exception>
#include <filesystem>
#include <fstream>
#include <optional>
#include <stdexcept>
#include <string>
#include <vector>

namespace {

namespace fs = std::filesystem;
using nlohmann::json;
using Vec3 = std::array<float, 3>;

// Every failure below main() is one of these; main prints "error: <message>" and exits 1.
struct Failure : std::runtime_error {
    using std::runtime_error::runtime_error;
};

float dot3(const float* a, const float* b) {
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
}

Vec3 normalized(Vec3 v) {
    const float l = std::sqrt(dot3(v.data(), v.data()));
    return {v[0] / l, v[1] / l, v[2] / l};
}

bool finite_ray(const lsnif_ray& r) {
    for (int a = 0; a < 3; ++a)
        if (!std::isfinite(r.org[a]) || !std::isfinite(r.dir[a])) return false;
    return !std::isnan(r.tmin) && !std::isnan(r.tmax);
}

bool ray_hits_box(const lsnif_ray& r, const float* b) {
    float t0 = r.tmin, t1 = r.tmax;
    for (int a = 0; a < 3; ++a) {
        float tn = (b[a] - r.org[a]) / r.dir[a], tf = (b[a + 3] - r.org[a]) / r.dir[a];
        if (tn > tf) std::swap(tn, tf);
        if (tn == tn) t0 = std::max(t0, tn);  // NaN (0/0) leaves the slab unconstrained
        if (tf == tf) t1 = std::min(t1, tf);
    }
    return t0 <= t1;
}

void grow(float* box, const float* p) {
    for (int a = 0; a < 3; ++a) box[a] = std::min(box[a], p[a]), box[a + 3] = std::max(box[a + 3], p[a]);
}

// How the assets are traced (the header comment says what each does).
struct Tracing {
    bool user_geometry = false;
    int packet = 1;  // rays per Embree call with user_geometry: 1, 4, 8 or 16
};

struct Options {
    fs::path outdir, image;
    int width = 320, height = 240;
    std::optional<std::array<float, 6>> camera;  // eye, target
    Tracing tracing;
    bool packet_given = false;
};

// Returns nothing on a usage error (after printing usage).
std::optional<Options> parse_args(int argc, char** argv) {
    Options o;
    std::vector<std::string> pos;
    for (int i = 1; i < argc; ++i) {
        const std::string a = argv[i];
        if (a == "--camera" && i + 1 < argc) {
            std::array<float, 6> c{};
            if (std::sscanf(argv[++i], "%f,%f,%f,%f,%f,%f", &c[0], &c[1], &c[2], &c[3], &c[4], &c[5]) != 6 ||
                !std::all_of(c.begin(), c.end(), [](float v) { return std::isfinite(v); }))
                return std::nullopt;
            o.camera = c;
        } else if (a == "--user-geometry") {
            o.tracing.user_geometry = true;
        } else if (a == "--packet" && i + 1 < argc) {
            const std::string w = argv[++i];
            if (w != "1" && w != "4" && w != "8" && w != "16") return std::nullopt;
            o.tracing.packet = std::stoi(w);
            o.packet_given = true;
        } else {
            pos.push_back(a);
        }
    }
    if (pos.size() != 2 && pos.size() != 4) return std::nullopt;
    if (o.packet_given && !o.tracing.user_geometry) return std::nullopt;  // packets are Embree's calls
    o.outdir = pos[0];
    o.image = pos[1];
    if (pos.size() == 4) {
        o.width = std::atoi(pos[2].c_str());
        o.height = std::atoi(pos[3].c_str());
        if (o.width < 1 || o.height < 1 || o.width > 8192 || o.height > 8192) return std::nullopt;
    }
    return o;
}

// The converted scene: simple meshes as Embree scenes instanced into one top-level scene,
// complex meshes as open LSNIF models with their instances' transforms. Owns every handle.
class HybridScene {
public:
    // `input`: an OUTDIR (its manifest) or a scene.gltf.
    HybridScene(const fs::path& input, const Tracing& tracing);
    ~HybridScene();
    HybridScene(const HybridScene&) = delete;
    HybridScene& operator=(const HybridScene&) = delete;

    const float* world_box() const { return world_; }
    std::size_t instance_count() const { return instances_.size(); }
    // The assets opened, and how many of them with the escape rule on.
    std::size_t asset_count() const {
        return std::size_t(
            std::count_if(meshes_.begin(), meshes_.end(), [](const Mesh& m) { return m.model; }));
    }
    std::size_t escaping_asset_count() const {
        return std::size_t(std::count_if(meshes_.begin(), meshes_.end(), [](const Mesh& m) {
            return m.model && lsnif_get_escape_points(m.model) != 0;
        }));
    }

    // Closest hit of every ray (all finite) on [tmin, tmax]; the nearest of the meshes' and
    // the assets' hits wins, each asset answering for the ray from tmin on (lsnif_embree.h's
    // rule, which the batched route follows too). Normals are world-space: Embree's geometric
    // normal (transformed here) or the network's.
    void trace(const std::vector<lsnif_ray>& rays, std::vector<lsnif_hit>& hits) const;
    // Whether anything lies on each ray's [tmin, tmax] (all finite rays).
    void occluded(const std::vector<lsnif_ray>& rays, std::vector<char>& occluded) const;

private:
    struct Mesh {
        RTCScene scene = nullptr;
        lsnif_model* model = nullptr;
        float box[6] = {INFINITY, INFINITY, INFINITY, -INFINITY, -INFINITY, -INFINITY};
    };
    struct Instance {
        float xf[12];               // object -> world, the layout lsnif_intersect_instance takes
        lsnif_model* model;         // non-null: traced through the reader
        float box[6];               // world bounds, to skip rays that cannot reach the instance
        std::array<float, 9> nmat;  // A^-T: object -> world normals (before normalizing)
    };

    void release();  // every handle, once
    // The two routes of trace() and occluded() (the file's header comment).
    void trace_batched(const std::vector<lsnif_ray>& rays, std::vector<lsnif_hit>& hits) const;
    void occluded_batched(const std::vector<lsnif_ray>& rays, std::vector<char>& occluded) const;
    void load_manifest(const fs::path& outdir);
    void load_gltf(const fs::path& gltf);
    std::vector<lsnif::scene::Scene> load_inputs(const json& manifest, const fs::path& outdir) const;
    // `asset`: the mesh's .lsnif, or empty to trace its triangles through Embree.
    void add_mesh(const lsnif::scene::Mesh& src, const fs::path& asset);
    void add_instance(std::size_t mesh, const float (&xf)[12]);

    fs::path manifest_path_;  // or the glTF file: what error messages name
    Tracing tracing_;
    RTCDevice device_ = nullptr;
    RTCScene top_ = nullptr;
    std::vector<RTCGeometry>
        asset_geometries_;  // with --user-geometry: lsnif_embree's, one per asset instance
    std::vector<Mesh> meshes_;
    std::vector<Instance> instances_;
    float world_[6] = {INFINITY, INFINITY, INFINITY, -INFINITY, -INFINITY, -INFINITY};
};

HybridScene::HybridScene(const fs::path& input, const Tracing& tracing) : tracing_(tracing) {
    try {  // a constructor that throws runs no destructor: release what was made so far
        device_ = rtcNewDevice(nullptr);
        top_ = rtcNewScene(device_);
        if (!device_ || !top_) throw Failure("embree: cannot create a device");
        std::error_code ec;
        if (fs::is_directory(input, ec))
            load_manifest(input);
        else
            load_gltf(input);
        if (instances_.empty()) throw Failure(manifest_path_.string() + ": the scene has no instances");
        rtcCommitScene(top_);
    } catch (...) {
        release();
        throw;
    }
}

void HybridScene::load_manifest(const fs::path& outdir) {
    manifest_path_ = outdir / "manifest.json";
    std::ifstream mf(manifest_path_);
    const json manifest = json::parse(mf, nullptr, false);
    if (!mf || !manifest.is_object()) throw Failure(manifest_path_.string() + ": cannot read");
    // Formats 2 to 4 agree on everything read here (3 adds each mesh's decision, 4 counts
    // memory as a renderer holds it).
    const std::string format = manifest.value("format", "");
    if (format != "lsnif-manifest/2" && format != "lsnif-manifest/3" && format != "lsnif-manifest/4")
        throw Failure(manifest_path_.string() +
                      ": not a lsnif-manifest/2, /3 or /4 manifest (re-run lsnif convert)");
    const std::vector<lsnif::scene::Scene> inputs = load_inputs(manifest, outdir);
    for (const json& m : manifest.at("meshes")) {
        const std::size_t input = m.at("input").get<std::size_t>(),
                          index = m.at("source_mesh").get<std::size_t>();
        if (input >= inputs.size() || index >= inputs[input].meshes.size())
            throw Failure(manifest_path_.string() + ": mesh '" + m.value("name", "") + "' refers to input " +
                          std::to_string(input) + " mesh " + std::to_string(index) +
                          ", which the source does not have");
        add_mesh(inputs[input].meshes[index], m.at("class") == "complex"
                                                  ? outdir / m.at("lsnif").at("file").get<std::string>()
                                                  : fs::path());
    }
    for (const json& j : manifest.at("instances")) {
        const json& t = j.at("transform");
        if (!t.is_array() || t.size() != 12)
            throw Failure(manifest_path_.string() + ": instance " + std::to_string(instances_.size()) +
                          " is malformed");
        float xf[12];
        for (int k = 0; k < 12; ++k) xf[k] = t[k].get<float>();
        add_instance(j.at("mesh").get<std::size_t>(), xf);
    }
}

// glTF URIs are percent-encoded (RFC 3986); lsnif writes relative file references only.
std::string percent_decoded(const std::string& uri) {
    std::string out;
    for (std::size_t i = 0; i < uri.size(); ++i)
        if (uri[i] == '%' && i + 2 < uri.size()) {
            out += char(std::strtol(uri.substr(i + 1, 2).c_str(), nullptr, 16));
            i += 2;
        } else {
            out += uri[i];
        }
    return out;
}

// OUTDIR/scene.gltf (schema/LSNIF_neural_geometry.md): every mesh's triangles from the glTF,
// traced through the asset its LSNIF_neural_geometry extension names when the geometry hash
// matches (the mesh was not edited since it was converted).
void HybridScene::load_gltf(const fs::path& gltf) {
    manifest_path_ = gltf;
    std::ifstream f(gltf);
    const json doc = json::parse(f, nullptr, false);
    if (!f || !doc.is_object()) throw Failure(gltf.string() + ": cannot read (a .gltf file or an OUTDIR)");
    auto r = lsnif::scene::import_scene(gltf);
    if (!r.ok()) throw Failure(r.error);
    for (const lsnif::scene::Mesh& mesh : r.scene.meshes) {
        fs::path asset;
        const json& gm = doc.at("meshes").at(std::size_t(mesh.source_index));
        if (gm.contains("extensions") && gm["extensions"].contains("LSNIF_neural_geometry")) {
            const json& ext = gm["extensions"]["LSNIF_neural_geometry"];
            if (ext.value("geometryHash", "") == lsnif::scene::geometry_hash(mesh))
                asset = gltf.parent_path() / percent_decoded(ext.at("uri").get<std::string>());
            else
                std::fprintf(stderr,
                             "warning: %s: mesh '%s' changed since it was converted: tracing its triangles\n",
                             gltf.string().c_str(), mesh.name.c_str());
        }
        add_mesh(mesh, asset);
    }
    for (const lsnif::scene::Instance& in : r.scene.instances) {
        float xf[12];
        std::copy(in.transform.begin(), in.transform.end(), xf);
        add_instance(in.mesh, xf);
    }
}

HybridScene::~HybridScene() {
    release();
}

void HybridScene::release() {
    // The scene first, then the user geometries it held, then the models they borrow.
    if (top_) rtcReleaseScene(top_);
    for (RTCGeometry g : asset_geometries_) lsnif_embree_release_geometry(g);
    asset_geometries_.clear();
    for (Mesh& m : meshes_) {
        if (m.model) lsnif_close(m.model);
        if (m.scene) rtcReleaseScene(m.scene);
    }
    meshes_.clear();
    if (device_) rtcReleaseDevice(device_);
    top_ = nullptr;
    device_ = nullptr;
}

std::vector<lsnif::scene::Scene> HybridScene::load_inputs(const json& manifest,
                                                          const fs::path& outdir) const {
    std::vector<lsnif::scene::Scene> inputs;
    const json& list = manifest.at("inputs");
    for (std::size_t i = 0; i < list.size(); ++i) {
        inputs.emplace_back();
        if (list[i].value("status", "") != "ok") continue;  // failed in convert: no meshes refer to it
        // The manifest's path rule: relative to the manifest's own directory.
        const fs::path source = outdir / list[i].at("path").get<std::string>();
        auto r = lsnif::scene::import_scene(source.string());
        if (!r.ok()) throw Failure(manifest_path_.string() + ": input " + std::to_string(i) + ": " + r.error);
        inputs.back() = std::move(r.scene);
    }
    return inputs;
}

void HybridScene::add_mesh(const lsnif::scene::Mesh& src, const fs::path& asset) {
    Mesh& out = meshes_.emplace_back();
    for (std::size_t v = 0; v + 2 < src.positions.size(); v += 3) grow(out.box, &src.positions[v]);
    if (!asset.empty()) {
        lsnif_error err;
        if (lsnif_open_file(asset.c_str(), &out.model, &err) != LSNIF_OK)
            throw Failure(asset.string() + ": " + err.message);
        // The escape rule conversion chose for the asset (its metadata's
        // metrics.escape_points, absent in older assets: off; docs/model.md "The escape
        // rule"): shadow rays leaving its surface within a run of that many occupied voxels
        // skip the network. It applies to both routes alike.
        std::size_t length = 0;
        const char* text = lsnif_metadata(out.model, &length);
        const json meta = json::parse(text, text + length, nullptr, false);
        const json::json_pointer where("/metrics/escape_points");
        const auto escape = meta.is_object() && meta.contains(where) && meta[where].is_number_unsigned()
                                ? meta[where].get<std::uint32_t>()
                                : 0u;
        if (lsnif_set_escape_points(out.model, escape) != LSNIF_OK)
            throw Failure(asset.string() + ": metrics.escape_points " + std::to_string(escape) +
                          " exceeds the asset's entry points per ray");
        // The enclosed rule (docs/model.md "The enclosed rule"): shadow rays that cross the
        // asset's shell into the inside are occluded without the network, on both routes.
        if (lsnif_set_enclosed_rule(out.model, 1) != LSNIF_OK)
            throw Failure(asset.string() + ": out of memory turning the enclosed rule on");
        // The box the asset answers in (it may reach past the vertices): what Embree is given
        // for its user geometry, and what the batched route culls rays with.
        lsnif_info info;
        lsnif_get_info(out.model, &info);
        grow(out.box, info.box_min);
        grow(out.box, info.box_max);
        return;
    }
    out.scene = rtcNewScene(device_);
    RTCGeometry g = rtcNewGeometry(device_, RTC_GEOMETRY_TYPE_TRIANGLE);
    // Embree-owned copies: Embree may read 16 bytes past the last vertex, which a shared
    // buffer would have to guarantee.
    void* vb =
        rtcSetNewGeometryBuffer(g, RTC_BUFFER_TYPE_VERTEX, 0, RTC_FORMAT_FLOAT3, 12, src.vertex_count());
    void* ib =
        rtcSetNewGeometryBuffer(g, RTC_BUFFER_TYPE_INDEX, 0, RTC_FORMAT_UINT3, 12, src.triangle_count());
    if (!vb || !ib) {
        rtcReleaseGeometry(g);
        throw Failure("embree: cannot allocate mesh '" + src.name + "'");
    }
    std::memcpy(vb, src.positions.data(), src.positions.size() * sizeof(float));
    std::memcpy(ib, src.indices.data(), src.indices.size() * sizeof(std::uint32_t));
    rtcCommitGeometry(g);
    rtcAttachGeometry(out.scene, g);
    rtcReleaseGeometry(g);
    rtcCommitScene(out.scene);
}

void HybridScene::add_instance(std::size_t mesh, const float (&xf)[12]) {
    if (mesh >= meshes_.size())
        throw Failure(manifest_path_.string() + ": instance " + std::to_string(instances_.size()) +
                      " refers to a mesh that does not exist");
    Instance in{{}, meshes_[mesh].model, {INFINITY, INFINITY, INFINITY, -INFINITY, -INFINITY, -INFINITY}, {}};
    std::copy(std::begin(xf), std::end(xf), in.xf);
    const auto inverse = lsnif::base::invert_linear(in.xf);  // the C API's own rule
    if (!inverse)
        throw Failure(manifest_path_.string() + ": instance " + std::to_string(instances_.size()) +
                      " has a singular or non-finite transform");
    in.nmat = lsnif::base::normal_matrix(*inverse);
    const Mesh& m = meshes_[mesh];
    for (int c = 0; c < 8 && m.box[0] <= m.box[3]; ++c) {  // world box = transformed object-box corners
        const float p[3] = {m.box[c & 1 ? 3 : 0], m.box[c & 2 ? 4 : 1], m.box[c & 4 ? 5 : 2]};
        float w[3];
        for (int r = 0; r < 3; ++r)
            w[r] = in.xf[4 * r] * p[0] + in.xf[4 * r + 1] * p[1] + in.xf[4 * r + 2] * p[2] + in.xf[4 * r + 3];
        grow(in.box, w);
        grow(world_, w);
    }
    if (m.model && tracing_.user_geometry) {
        RTCGeometry g = nullptr;
        const lsnif_status st = lsnif_embree_new_geometry(device_, m.model, in.xf, &g);
        if (st != LSNIF_OK)
            throw Failure(manifest_path_.string() + ": instance " + std::to_string(instances_.size()) +
                          ": cannot make an Embree user geometry (" + lsnif_status_string(st) + ")");
        asset_geometries_.push_back(g);
        rtcAttachGeometryByID(top_, g, unsigned(instances_.size()));  // geomID = our index
    } else if (!m.model) {
        RTCGeometry g = rtcNewGeometry(device_, RTC_GEOMETRY_TYPE_INSTANCE);
        rtcSetGeometryInstancedScene(g, m.scene);
        rtcSetGeometryTransform(g, 0, RTC_FORMAT_FLOAT3X4_ROW_MAJOR, in.xf);
        rtcCommitGeometry(g);
        rtcAttachGeometryByID(top_, g, unsigned(instances_.size()));  // instID = our index
        rtcReleaseGeometry(g);
    }
    instances_.push_back(in);
}

// What Embree reports for one ray: the hit's distance, geometric normal and IDs.
struct EmbreeHit {
    float t;
    float ng[3];
    unsigned geom, inst;
};

// A packet of N rays in Embree's SOA layout: RTCRayHit for N = 1, RTCRayHit4/8/16 otherwise.
template <int N>
struct alignas(64) Packet {
    RTCRayHitNt<N> rh;
    int valid[N];
};

template <int N>
void load_packet(Packet<N>& p, const lsnif_ray* rays, std::size_t n) {
    for (int i = 0; i < N; ++i) {
        const bool on = std::size_t(i) < n;
        const lsnif_ray& r = rays[on ? i : 0];
        p.valid[i] = on ? -1 : 0;
        p.rh.ray.org_x[i] = r.org[0], p.rh.ray.org_y[i] = r.org[1], p.rh.ray.org_z[i] = r.org[2];
        p.rh.ray.dir_x[i] = r.dir[0], p.rh.ray.dir_y[i] = r.dir[1], p.rh.ray.dir_z[i] = r.dir[2];
        p.rh.ray.tnear[i] = r.tmin, p.rh.ray.tfar[i] = r.tmax, p.rh.ray.time[i] = 0.0f;
        p.rh.ray.mask[i] = 0xFFFFFFFFu, p.rh.ray.id[i] = 0, p.rh.ray.flags[i] = 0;
        p.rh.hit.geomID[i] = RTC_INVALID_GEOMETRY_ID;
        p.rh.hit.instID[0][i] = RTC_INVALID_GEOMETRY_ID;
    }
}

// Closest hits of `rays` through Embree alone, N rays per call.
template <int N>
void embree_closest(RTCScene scene, const std::vector<lsnif_ray>& rays, std::vector<EmbreeHit>& out) {
    out.resize(rays.size());
    Packet<N> p;
    RTCIntersectContext ctx;
    for (std::size_t base = 0; base < rays.size(); base += N) {
        const std::size_t n = std::min<std::size_t>(N, rays.size() - base);
        load_packet(p, &rays[base], n);
        rtcInitIntersectContext(&ctx);
        if constexpr (N == 1) rtcIntersect1(scene, &ctx, reinterpret_cast<RTCRayHit*>(&p.rh));
        if constexpr (N == 4) rtcIntersect4(p.valid, scene, &ctx, reinterpret_cast<RTCRayHit4*>(&p.rh));
        if constexpr (N == 8) rtcIntersect8(p.valid, scene, &ctx, reinterpret_cast<RTCRayHit8*>(&p.rh));
        if constexpr (N == 16) rtcIntersect16(p.valid, scene, &ctx, reinterpret_cast<RTCRayHit16*>(&p.rh));
        for (std::size_t i = 0; i < n; ++i)
            out[base + i] = {p.rh.ray.tfar[i],
                             {p.rh.hit.Ng_x[i], p.rh.hit.Ng_y[i], p.rh.hit.Ng_z[i]},
                             p.rh.hit.geomID[i],
                             p.rh.hit.instID[0][i]};
    }
}

// Occlusion of `rays` through Embree alone, N rays per call.
template <int N>
void embree_occluded(RTCScene scene, const std::vector<lsnif_ray>& rays, std::vector<char>& out) {
    out.assign(rays.size(), 0);
    Packet<N> p;
    RTCIntersectContext ctx;
    for (std::size_t base = 0; base < rays.size(); base += N) {
        const std::size_t n = std::min<std::size_t>(N, rays.size() - base);
        load_packet(p, &rays[base], n);
        rtcInitIntersectContext(&ctx);
        if constexpr (N == 1) rtcOccluded1(scene, &ctx, reinterpret_cast<RTCRay*>(&p.rh.ray));
        if constexpr (N == 4) rtcOccluded4(p.valid, scene, &ctx, reinterpret_cast<RTCRay4*>(&p.rh.ray));
        if constexpr (N == 8) rtcOccluded8(p.valid, scene, &ctx, reinterpret_cast<RTCRay8*>(&p.rh.ray));
        if constexpr (N == 16) rtcOccluded16(p.valid, scene, &ctx, reinterpret_cast<RTCRay16*>(&p.rh.ray));
        for (std::size_t i = 0; i < n; ++i) out[base + i] = p.rh.ray.tfar[i] < 0.0f;  // Embree's mark: -inf
    }
}

void HybridScene::trace(const std::vector<lsnif_ray>& rays, std::vector<lsnif_hit>& hits) const {
    if (!tracing_.user_geometry) return trace_batched(rays, hits);
    std::vector<EmbreeHit> eh;
    switch (tracing_.packet) {
        case 4: embree_closest<4>(top_, rays, eh); break;
        case 8: embree_closest<8>(top_, rays, eh); break;
        case 16: embree_closest<16>(top_, rays, eh); break;
        default: embree_closest<1>(top_, rays, eh); break;
    }
    hits.assign(rays.size(), lsnif_hit{INFINITY, {0, 0, 0}, 0, 0});
    for (std::size_t i = 0; i < rays.size(); ++i) {
        const EmbreeHit& h = eh[i];
        if (h.geom == RTC_INVALID_GEOMETRY_ID) continue;
        if (h.inst ==
            RTC_INVALID_GEOMETRY_ID) {  // an asset's user geometry: a world-space normal, a material
            hits[i] = {h.t, {h.ng[0], h.ng[1], h.ng[2]}, 1, 0};
            continue;
        }
        const float* n = instances_[h.inst].nmat.data();
        hits[i] = {h.t, {dot3(n, h.ng), dot3(n + 3, h.ng), dot3(n + 6, h.ng)}, 1, 0};
    }
}

void HybridScene::occluded(const std::vector<lsnif_ray>& rays, std::vector<char>& occluded) const {
    if (!tracing_.user_geometry) return occluded_batched(rays, occluded);
    switch (tracing_.packet) {
        case 4: return embree_occluded<4>(top_, rays, occluded);
        case 8: return embree_occluded<8>(top_, rays, occluded);
        case 16: return embree_occluded<16>(top_, rays, occluded);
        default: return embree_occluded<1>(top_, rays, occluded);
    }
}

void HybridScene::trace_batched(const std::vector<lsnif_ray>& rays, std::vector<lsnif_hit>& hits) const {
    std::vector<EmbreeHit> eh;
    embree_closest<16>(top_, rays, eh);
    hits.assign(rays.size(), lsnif_hit{INFINITY, {0, 0, 0}, 0, 0});
    for (std::size_t i = 0; i < rays.size(); ++i) {
        if (eh[i].geom == RTC_INVALID_GEOMETRY_ID) continue;
        const float* n = instances_[eh[i].inst].nmat.data();
        hits[i] = {eh[i].t, {dot3(n, eh[i].ng), dot3(n + 3, eh[i].ng), dot3(n + 6, eh[i].ng)}, 1, 0};
    }
    std::vector<lsnif_ray> batch;
    std::vector<std::size_t> index;
    std::vector<lsnif_hit> out;
    for (const Instance& in : instances_) {
        if (!in.model) continue;
        batch.clear();
        index.clear();
        for (std::size_t i = 0; i < rays.size(); ++i) {
            // Only a nearer hit matters, so a box beyond the hit so far is skipped; the reader
            // still gets the whole ray (its answer must not depend on what was met first).
            lsnif_ray r = rays[i];
            r.tmax = std::min(r.tmax, hits[i].t);
            if (ray_hits_box(r, in.box)) batch.push_back(rays[i]), index.push_back(i);
        }
        out.resize(batch.size());
        if (!batch.empty() &&
            lsnif_intersect_instance(in.model, in.xf, batch.data(), batch.size(), out.data()) == LSNIF_OK)
            for (std::size_t k = 0; k < batch.size(); ++k)
                if (out[k].hit && out[k].t <= hits[index[k]].t) hits[index[k]] = out[k];
    }
}

void HybridScene::occluded_batched(const std::vector<lsnif_ray>& rays, std::vector<char>& occluded) const {
    embree_occluded<16>(top_, rays, occluded);
    std::vector<lsnif_ray> batch;
    std::vector<std::size_t> index;
    std::vector<std::uint8_t> out;
    for (const Instance& in : instances_) {
        if (!in.model) continue;
        batch.clear();
        index.clear();
        for (std::size_t i = 0; i < rays.size(); ++i)
            if (!occluded[i] && ray_hits_box(rays[i], in.box)) batch.push_back(rays[i]), index.push_back(i);
        out.resize(batch.size());
        if (!batch.empty() &&
            lsnif_occluded_instance(in.model, in.xf, batch.data(), batch.size(), out.data()) == LSNIF_OK)
            for (std::size_t k = 0; k < batch.size(); ++k)
                if (out[k]) occluded[index[k]] = 1;
    }
}

struct Camera {
    Vec3 eye, forward, right, up;
    float tan_half = std::tan(20.0f * 3.14159265f / 180.0f);  // 40-degree vertical field of view
};

Camera make_camera(const Vec3& eye, const Vec3& target) {
    const Vec3 f{target[0] - eye[0], target[1] - eye[1], target[2] - eye[2]};
    if (!(dot3(f.data(), f.data()) > 0.0f)) throw Failure("--camera: the eye and the target coincide");
    Camera c{eye, normalized(f), {}, {}};
    Vec3 r{-c.forward[2], 0.0f, c.forward[0]};                         // forward x (0,1,0)
    if (!(dot3(r.data(), r.data()) > 1e-12f)) r = {1.0f, 0.0f, 0.0f};  // looking straight up or down
    c.right = normalized(r);
    c.up = {c.right[1] * c.forward[2] - c.right[2] * c.forward[1],
            c.right[2] * c.forward[0] - c.right[0] * c.forward[2],
            c.right[0] * c.forward[1] - c.right[1] * c.forward[0]};
    return c;
}

// One row: primary rays, then shadow rays from the pixels that hit, then shading.
void render_row(const HybridScene& scene, const Camera& cam, const Vec3& light, float eps, int y, int W,
                int H, unsigned char* row) {
    std::vector<lsnif_ray> prim(W), shadow;
    std::vector<lsnif_hit> ph;
    std::vector<int> lit;  // pixel of each shadow ray
    for (int x = 0; x < W; ++x) {
        const float sx = (2.0f * (x + 0.5f) / W - 1.0f) * cam.tan_half * W / H,
                    sy = (1.0f - 2.0f * (y + 0.5f) / H) * cam.tan_half;
        Vec3 d;
        for (int a = 0; a < 3; ++a) d[a] = cam.forward[a] + sx * cam.right[a] + sy * cam.up[a];
        prim[x] = {{cam.eye[0], cam.eye[1], cam.eye[2]}, 0.0f, {d[0], d[1], d[2]}, INFINITY};
    }
    scene.trace(prim, ph);
    std::vector<Vec3> normal(W);
    for (int x = 0; x < W; ++x) {
        if (!ph[x].hit) continue;
        Vec3 n{ph[x].normal[0], ph[x].normal[1], ph[x].normal[2]};
        const float nl = std::sqrt(dot3(n.data(), n.data())) + 1e-30f;
        for (float& v : n) v /= nl;
        if (dot3(n.data(), prim[x].dir) > 0)
            for (float& v : n) v = -v;  // face the camera
        normal[x] = n;
        lsnif_ray s;
        for (int a = 0; a < 3; ++a) {
            const float p = prim[x].org[a] + ph[x].t * prim[x].dir[a] + eps * n[a];  // leave the surface
            s.org[a] = p;
            s.dir[a] = light[a] - p;
        }
        s.tmin = 0.0f;
        s.tmax = 1.0f;                 // up to the light
        if (!finite_ray(s)) continue;  // a degenerate hit: shaded as lit, never traced
        shadow.push_back(s);
        lit.push_back(x);
    }
    std::vector<char> shadowed;
    scene.occluded(shadow, shadowed);
    std::vector<char> occluded(W, 0);
    for (std::size_t k = 0; k < lit.size(); ++k) occluded[lit[k]] = shadowed[k];
    for (int x = 0; x < W; ++x) {
        float v = 0.05f;  // background
        if (ph[x].hit) {
            Vec3 l;
            for (int a = 0; a < 3; ++a) l[a] = light[a] - (prim[x].org[a] + ph[x].t * prim[x].dir[a]);
            const float lambert = std::max(0.0f, dot3(normal[x].data(), normalized(l).data()));
            v = 0.1f + 0.9f * lambert * (occluded[x] ? 0.0f : 1.0f);
        }
        const auto g = (unsigned char)std::lround(255.0f * std::pow(std::clamp(v, 0.0f, 1.0f), 1.0f / 2.2f));
        row[3 * x] = row[3 * x + 1] = row[3 * x + 2] = g;
    }
}

// Binary PPM through a temporary file and a rename: no half-written image is ever left.
void write_ppm(const fs::path& path, int W, int H, const std::vector<unsigned char>& rgb) {
    const fs::path tmp = path.string() + ".tmp";
    std::FILE* out = std::fopen(tmp.c_str(), "wb");
    if (!out) throw Failure(path.string() + ": cannot open for writing");
    std::fprintf(out, "P6\n%d %d\n255\n", W, H);
    const bool ok = std::fwrite(rgb.data(), 1, rgb.size(), out) == rgb.size();
    std::error_code ec;
    if (std::fclose(out) != 0 || !ok) {
        fs::remove(tmp, ec);
        throw Failure(path.string() + ": write failed");
    }
    fs::rename(tmp, path, ec);
    if (ec) {
        fs::remove(tmp, ec);
        throw Failure(path.string() + ": cannot rename the finished image into place");
    }
}

int run(const Options& opt) {
    const HybridScene scene(opt.outdir, opt.tracing);
    const float* w = scene.world_box();
    const Vec3 c{0.5f * (w[0] + w[3]), 0.5f * (w[1] + w[4]), 0.5f * (w[2] + w[5])};
    const Vec3 ext{w[3] - w[0], w[4] - w[1], w[5] - w[2]};
    const float diag = std::max(std::sqrt(dot3(ext.data(), ext.data())), 1e-6f);
    if (!std::isfinite(diag) || !std::isfinite(c[0] + c[1] + c[2]))
        throw Failure(opt.outdir.string() + "/manifest.json: the scene's bounds are not finite");
    // Default view: the scene framed from above and in front; the light above it.
    const Camera cam = opt.camera
                           ? make_camera({(*opt.camera)[0], (*opt.camera)[1], (*opt.camera)[2]},
                                         {(*opt.camera)[3], (*opt.camera)[4], (*opt.camera)[5]})
                           : make_camera({c[0] + 0.5f * diag, c[1] + 0.37f * diag, c[2] + 0.92f * diag}, c);
    const Vec3 light{c[0] + 0.5f * diag, c[1] + 1.2f * diag, c[2] + 0.7f * diag};
    const float eps = 1e-4f * diag;

    std::vector<unsigned char> image(std::size_t(opt.width) * opt.height * 3);
    const auto start = std::chrono::steady_clock::now();
    for (int y = 0; y < opt.height; ++y)
        render_row(scene, cam, light, eps, y, opt.width, opt.height, &image[std::size_t(y) * opt.width * 3]);
    const double seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
    write_ppm(opt.image, opt.width, opt.height, image);
    const std::string route =
        opt.tracing.user_geometry
            ? "Embree user geometry, " + std::to_string(opt.tracing.packet) + "-ray calls"
            : std::string("batched");
    std::printf(
        "wrote %s (%dx%d, %zu instances; assets traced %s, %zu of %zu with the escape rule; rendered "
        "in %.3f s)\n",
        opt.image.c_str(), opt.width, opt.height, scene.instance_count(), route.c_str(),
        scene.escaping_asset_count(), scene.asset_count(), seconds);
    return 0;
}

}  // namespace

int main(int argc, char** argv) {
    const std::optional<Options> opt = parse_args(argc, argv);
    if (!opt) {
        std::fprintf(
            stderr,
            "usage: %s OUTDIR|OUTDIR/scene.gltf OUT.ppm [WIDTH HEIGHT] [--camera ex,ey,ez,tx,ty,tz]\n"
            "          [--user-geometry [--packet 1|4|8|16]]\n"
            "  WIDTH, HEIGHT in 1..8192 (default 320x240)\n",
            argc > 0 ? argv[0] : "lsnif_render");
        return 2;
    }
    try {
        return run(*opt);
    } catch (const Failure& e) {
        std::fprintf(stderr, "error: %s\n", e.what());
    } catch (const json::exception& e) {  // a manifest that parses but lacks a field or has the wrong type
        std::fprintf(stderr, "error: %s/manifest.json: malformed: %s\n", opt->outdir.c_str(), e.what());
    } catch (const std::exception& e) {
        std::fprintf(stderr, "error: %s\n", e.what());
    }
    return 1;
}
