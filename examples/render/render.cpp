// The reference integration for a renderer author: load a `lsnif convert` output
// directory and render the hybrid scene — Embree's BVH for simple meshes, the LSNIF reader
// for complex ones — with a point light and hard shadows, into a binary PPM.
//
//   lsnif_render OUTDIR OUT.ppm [WIDTH HEIGHT]
//
// What a renderer needs from the conversion is all in OUTDIR/manifest.json:
//   meshes[i].class      "complex" (trace its .lsnif) or "simple" (trace the source mesh)
//   meshes[i].lsnif.file the asset, shared by all instances of the mesh
//   meshes[i].input / source_mesh   where the simple geometry is (the renderer's importer
//                                   reads it; here lsnif::scene stands in for that importer)
//   instances[j]         mesh index and object-to-world 3x4 row-major transform
// The reader is thread-safe for concurrent lsnif_intersect_instance calls on one model
// and works best on batches of >= 256 rays, so rays are traced a row at a time.
#include <lsnif/lsnif.h>
#include <lsnif/scene/scene.hpp>

#include <embree3/rtcore.h>
#include <nlohmann/json.hpp>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <fstream>
#include <string>
#include <vector>

namespace {

struct Instance {
    int mesh;
    float xf[12];            // object -> world, the layout lsnif_intersect_instance takes
    lsnif_model* model;      // non-null: traced through the reader
    float box[6];            // world bounds, to skip rays that cannot reach the instance
    float nmat[9];           // cofactor matrix of A: object -> world normals (up to scale)
};

float dot3(const float* a, const float* b) { return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]; }

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

}  // namespace

int main(int argc, char** argv) {
    if (argc != 3 && argc != 5) {
        std::fprintf(stderr, "usage: %s OUTDIR OUT.ppm [WIDTH HEIGHT]\n", argv[0]);
        return 2;
    }
    const std::string dir = argv[1];
    const int W = argc == 5 ? std::atoi(argv[3]) : 320, H = argc == 5 ? std::atoi(argv[4]) : 240;
    if (W < 1 || H < 1 || W > 8192 || H > 8192) {
        std::fprintf(stderr, "error: image size out of range\n");
        return 2;
    }
    std::ifstream mf(dir + "/manifest.json");
    const nlohmann::json manifest = nlohmann::json::parse(mf, nullptr, false);
    if (!mf || manifest.is_discarded()) {
        std::fprintf(stderr, "error: %s/manifest.json: cannot read\n", dir.c_str());
        return 1;
    }

    // 1. Geometry: simple meshes become Embree scenes, complex meshes open their asset.
    RTCDevice device = rtcNewDevice(nullptr);
    std::vector<lsnif::scene::Scene> inputs;
    for (const auto& in : manifest["inputs"]) {
        auto r = lsnif::scene::import_scene(in["path"].get<std::string>());
        inputs.push_back(std::move(r.scene));  // a failed input has no meshes in the manifest
    }
    struct Mesh {
        RTCScene scene = nullptr;
        lsnif_model* model = nullptr;
        float box[6] = {INFINITY, INFINITY, INFINITY, -INFINITY, -INFINITY, -INFINITY};
    };
    std::vector<Mesh> meshes;
    for (const auto& m : manifest["meshes"]) {
        Mesh out;
        const auto& src = inputs.at(m["input"]).meshes.at(m["source_mesh"]);
        for (std::size_t v = 0; v < src.positions.size(); ++v)
            out.box[v % 3] = std::min(out.box[v % 3], src.positions[v]),
            out.box[v % 3 + 3] = std::max(out.box[v % 3 + 3], src.positions[v]);
        if (m["class"] == "complex") {
            const std::string file = dir + "/" + m["lsnif"]["file"].get<std::string>();
            lsnif_error err;
            if (lsnif_open_file(file.c_str(), &out.model, &err) != LSNIF_OK) {
                std::fprintf(stderr, "error: %s: %s\n", file.c_str(), err.message);
                return 1;
            }
        } else {
            out.scene = rtcNewScene(device);
            RTCGeometry g = rtcNewGeometry(device, RTC_GEOMETRY_TYPE_TRIANGLE);
            // Embree-owned copies: Embree may read 16 bytes past the last vertex, which a
            // shared buffer would have to guarantee.
            void* vb = rtcSetNewGeometryBuffer(g, RTC_BUFFER_TYPE_VERTEX, 0, RTC_FORMAT_FLOAT3, 12, src.vertex_count());
            void* ib = rtcSetNewGeometryBuffer(g, RTC_BUFFER_TYPE_INDEX, 0, RTC_FORMAT_UINT3, 12, src.triangle_count());
            std::memcpy(vb, src.positions.data(), src.positions.size() * sizeof(float));
            std::memcpy(ib, src.indices.data(), src.indices.size() * sizeof(std::uint32_t));
            rtcCommitGeometry(g);
            rtcAttachGeometry(out.scene, g);
            rtcReleaseGeometry(g);
            rtcCommitScene(out.scene);
        }
        meshes.push_back(out);
    }

    // 2. Instances: simple ones go into one top-level Embree scene, complex ones are kept
    //    with their transform and world box for the reader.
    RTCScene top = rtcNewScene(device);
    std::vector<Instance> instances;
    float world[6] = {INFINITY, INFINITY, INFINITY, -INFINITY, -INFINITY, -INFINITY};
    for (const auto& j : manifest["instances"]) {
        Instance in{j["mesh"].get<int>(), {}, nullptr, {INFINITY, INFINITY, INFINITY, -INFINITY, -INFINITY, -INFINITY}, {}};
        for (int k = 0; k < 12; ++k) in.xf[k] = j["transform"][k].get<float>();
        // Normals transform by the inverse transpose of A = cofactor(A) / det(A); the sign
        // of det keeps mirrored instances' normals outward.
        const float* a = in.xf;
        const float co[9] = {a[5] * a[10] - a[6] * a[9], a[6] * a[8] - a[4] * a[10], a[4] * a[9] - a[5] * a[8],
                             a[2] * a[9] - a[1] * a[10], a[0] * a[10] - a[2] * a[8], a[1] * a[8] - a[0] * a[9],
                             a[1] * a[6] - a[2] * a[5], a[2] * a[4] - a[0] * a[6], a[0] * a[5] - a[1] * a[4]};
        const float det = a[0] * co[0] + a[1] * co[1] + a[2] * co[2];
        for (int k = 0; k < 9; ++k) in.nmat[k] = det < 0 ? -co[k] : co[k];
        const Mesh& m = meshes[in.mesh];
        for (int c = 0; c < 8; ++c) {  // world box = transformed object-box corners
            const float p[3] = {m.box[c & 1 ? 3 : 0], m.box[c & 2 ? 4 : 1], m.box[c & 4 ? 5 : 2]};
            for (int a = 0; a < 3; ++a) {
                const float w = in.xf[4 * a] * p[0] + in.xf[4 * a + 1] * p[1] + in.xf[4 * a + 2] * p[2] + in.xf[4 * a + 3];
                in.box[a] = std::min(in.box[a], w), in.box[a + 3] = std::max(in.box[a + 3], w);
                world[a] = std::min(world[a], w), world[a + 3] = std::max(world[a + 3], w);
            }
        }
        if (m.model) {
            in.model = m.model;
        } else {
            RTCGeometry g = rtcNewGeometry(device, RTC_GEOMETRY_TYPE_INSTANCE);
            rtcSetGeometryInstancedScene(g, m.scene);
            rtcSetGeometryTransform(g, 0, RTC_FORMAT_FLOAT3X4_ROW_MAJOR, in.xf);
            rtcCommitGeometry(g);
            rtcAttachGeometryByID(top, g, unsigned(instances.size()));  // instID = our index
            rtcReleaseGeometry(g);
        }
        instances.push_back(in);
    }
    rtcCommitScene(top);

    // 3. The hybrid trace of a batch: Embree for the simple part, then every LSNIF instance
    //    whose box the ray reaches; the nearest hit wins. Normals: Embree's geometric
    //    normal (object space, so transformed here) or the network's world-space normal.
    auto trace = [&](std::vector<lsnif_ray>& rays, std::vector<lsnif_hit>& hits) {
        for (std::size_t i = 0; i < rays.size(); ++i) {
            RTCIntersectContext ctx;
            rtcInitIntersectContext(&ctx);
            RTCRayHit rh{};
            rh.ray = {rays[i].org[0], rays[i].org[1], rays[i].org[2], rays[i].tmin,
                      rays[i].dir[0], rays[i].dir[1], rays[i].dir[2], 0.0f, rays[i].tmax, 0xFFFFFFFFu, 0, 0};
            rh.hit.geomID = RTC_INVALID_GEOMETRY_ID;
            rtcIntersect1(top, &ctx, &rh);
            hits[i] = {INFINITY, {0, 0, 0}, 0, 0};
            if (rh.hit.geomID != RTC_INVALID_GEOMETRY_ID) {
                const float* n = instances[rh.hit.instID[0]].nmat;
                const float g[3] = {rh.hit.Ng_x, rh.hit.Ng_y, rh.hit.Ng_z};
                hits[i] = {rh.ray.tfar, {dot3(n, g), dot3(n + 3, g), dot3(n + 6, g)}, 1, 0};
            }
        }
        std::vector<lsnif_ray> batch;
        std::vector<std::size_t> index;
        std::vector<lsnif_hit> out;
        for (const Instance& in : instances) {
            if (!in.model) continue;
            batch.clear();
            index.clear();
            for (std::size_t i = 0; i < rays.size(); ++i) {
                lsnif_ray r = rays[i];
                r.tmax = std::min(r.tmax, hits[i].t);  // only a nearer hit matters
                if (ray_hits_box(r, in.box)) batch.push_back(r), index.push_back(i);
            }
            out.resize(batch.size());
            if (!batch.empty() && lsnif_intersect_instance(in.model, in.xf, batch.data(), batch.size(), out.data()) == LSNIF_OK)
                for (std::size_t k = 0; k < batch.size(); ++k)
                    if (out[k].hit && out[k].t < hits[index[k]].t) hits[index[k]] = out[k];
        }
    };

    // 4. Camera framing the scene, light above it; primary rays, then shadow rays.
    const float c[3] = {0.5f * (world[0] + world[3]), 0.5f * (world[1] + world[4]), 0.5f * (world[2] + world[5])};
    const float diag = std::sqrt((world[3] - world[0]) * (world[3] - world[0]) + (world[4] - world[1]) * (world[4] - world[1]) +
                                 (world[5] - world[2]) * (world[5] - world[2]));
    const float eye[3] = {c[0] + 0.5f * diag, c[1] + 0.37f * diag, c[2] + 0.92f * diag};
    const float light[3] = {c[0] + 0.5f * diag, c[1] + 1.2f * diag, c[2] + 0.7f * diag};
    float f[3] = {c[0] - eye[0], c[1] - eye[1], c[2] - eye[2]};
    const float fl = std::sqrt(dot3(f, f));
    for (float& x : f) x /= fl;
    float r[3] = {-f[2], 0.0f, f[0]};  // f x (0,1,0)
    const float rl = std::sqrt(dot3(r, r));
    for (float& x : r) x /= rl;
    const float u[3] = {r[1] * f[2] - r[2] * f[1], r[2] * f[0] - r[0] * f[2], r[0] * f[1] - r[1] * f[0]};
    const float th = std::tan(20.0f * 3.14159265f / 180.0f);

    std::vector<unsigned char> image(std::size_t(W) * H * 3);
    std::vector<lsnif_ray> prim(W), shadow(W);
    std::vector<lsnif_hit> ph(W), sh(W);
    for (int y = 0; y < H; ++y) {
        for (int x = 0; x < W; ++x) {
            const float sx = (2.0f * (x + 0.5f) / W - 1.0f) * th * W / H, sy = (1.0f - 2.0f * (y + 0.5f) / H) * th;
            prim[x] = {{eye[0], eye[1], eye[2]}, 0.0f, {f[0] + sx * r[0] + sy * u[0], f[1] + sx * r[1] + sy * u[1], f[2] + sx * r[2] + sy * u[2]}, INFINITY};
        }
        trace(prim, ph);
        for (int x = 0; x < W; ++x) {
            float p[3], n[3] = {ph[x].normal[0], ph[x].normal[1], ph[x].normal[2]};
            const float nl = std::sqrt(dot3(n, n)) + 1e-30f;
            for (int a = 0; a < 3; ++a) p[a] = prim[x].org[a] + ph[x].t * prim[x].dir[a], n[a] /= nl;
            if (dot3(n, prim[x].dir) > 0) for (float& v : n) v = -v;  // face the camera
            const float eps = 1e-4f * diag;  // leave the surface before tracing on
            float l[3] = {light[0] - p[0], light[1] - p[1], light[2] - p[2]};
            shadow[x] = {{p[0] + eps * n[0], p[1] + eps * n[1], p[2] + eps * n[2]}, 0.0f, {l[0], l[1], l[2]}, ph[x].hit ? 1.0f : -1.0f};
        }
        trace(shadow, sh);
        for (int x = 0; x < W; ++x) {
            float v = 0.05f;  // background
            if (ph[x].hit) {
                float n[3] = {ph[x].normal[0], ph[x].normal[1], ph[x].normal[2]};
                if (dot3(n, prim[x].dir) > 0) for (float& q : n) q = -q;
                const float ll = std::sqrt(dot3(shadow[x].dir, shadow[x].dir)), nl = std::sqrt(dot3(n, n)) + 1e-30f;
                const float lambert = std::max(0.0f, dot3(n, shadow[x].dir) / (ll * nl));
                v = 0.1f + 0.9f * lambert * (sh[x].hit ? 0.0f : 1.0f);
            }
            const unsigned char g = (unsigned char)std::lround(255.0f * std::pow(std::min(v, 1.0f), 1.0f / 2.2f));
            image[(std::size_t(y) * W + x) * 3 + 0] = image[(std::size_t(y) * W + x) * 3 + 1] = image[(std::size_t(y) * W + x) * 3 + 2] = g;
        }
    }

    std::FILE* out = std::fopen(argv[2], "wb");
    if (!out) {
        std::fprintf(stderr, "error: %s: cannot open for writing\n", argv[2]);
        return 1;
    }
    std::fprintf(out, "P6\n%d %d\n255\n", W, H);
    const bool ok = std::fwrite(image.data(), 1, image.size(), out) == image.size();
    if (std::fclose(out) != 0 || !ok) {
        std::fprintf(stderr, "error: %s: write failed\n", argv[2]);
        return 1;
    }
    for (auto& m : meshes) {
        if (m.model) lsnif_close(m.model);
        if (m.scene) rtcReleaseScene(m.scene);
    }
    rtcReleaseScene(top);
    rtcReleaseDevice(device);
    std::printf("wrote %s (%dx%d, %zu instances)\n", argv[2], W, H, instances.size());
    return 0;
}
