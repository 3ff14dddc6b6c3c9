// `lsnif bench memory|rays|convert`: a converted scene measured against Embree on the same
// machine in the same run (docs/architecture.md §5 "Speed"; docs/investigations/ has the figures).
#include <lsnif/lsnif.h>
#include <lsnif/base/clock.hpp>
#include <lsnif/converter/bench.hpp>
#include <lsnif/converter/convert.hpp>
#include <lsnif/converter/manifest.hpp>

#include <lsnif/sampling/sampling.hpp>
#include <lsnif/scene/scene.hpp>
#include <map>

#include <embree3/rtcore.h>

#include <algorithm>
#include <atomic>
#include <chrono>
#include <filesystem>
#include <lsnif/base/parallel.hpp>

namespace lsnif::converter {
namespace fs = std::filesystem;
using nlohmann::json;
using Clock = std::chrono::steady_clock;

namespace {

using base::seconds_since;

// One complex mesh of a conversion: its source geometry and its opened asset.
struct Object {
    std::string name;
    scene::Mesh mesh;
    mesh::Box box;
    lsnif_model* model = nullptr;
    std::uint64_t lsnif_bytes = 0;
    std::uint32_t instances = 0;
};

struct Loaded {
    std::vector<Object> objects;
    ~Loaded() {
        for (auto& o : objects)
            if (o.model) lsnif_close(o.model);
    }
};

bool load_objects(const SceneBenchOptions& opt, Loaded& out, std::string& error) {
    LoadedManifest loaded;
    if (!load_manifest(opt.outdir, opt.sources, loaded, error)) return false;
    const fs::path& mp = loaded.path;
    const std::vector<std::string>& sources = loaded.sources;
    std::vector<std::optional<scene::Scene>> scenes(sources.size());
    for (const MeshOutcome& m : loaded.meshes) {
        if (m.cls() != MeshClass::complex || !m.asset || !m.stats) continue;
        const std::size_t input = m.input, src = m.source_mesh;
        if (!scenes[input]) {
            auto r = scene::import_scene(sources[input]);
            if (!r.ok()) {
                error = mp.string() + ": input " + std::to_string(input) + ": " + r.error;
                return false;
            }
            scenes[input] = std::move(r.scene);
        }
        if (src >= scenes[input]->meshes.size() ||
            scene::geometry_hash(scenes[input]->meshes[src]) != m.geometry_hash) {
            error = sources[input] + ": mesh '" + m.name +
                    "' differs from the converted geometry (geometry hash mismatch)";
            return false;
        }
        Object o;
        o.name = m.name;
        o.mesh = scenes[input]->meshes[src];
        o.box.min = m.stats->box_min;
        o.box.max = m.stats->box_max;
        o.instances = std::uint32_t(m.instances);
        const fs::path asset = fs::path(opt.outdir) / m.asset->file;
        lsnif_error e{};
        if (lsnif_open_file(asset.c_str(), &o.model, &e) != LSNIF_OK) {
            error = asset.string() + ": " + lsnif_status_string(e.status) + " (" + e.message + ")";
            return false;
        }
        if (lsnif_set_arithmetic(o.model, opt.arithmetic, nullptr) != LSNIF_OK) {
            error = asset.string() + ": cannot set the arithmetic " + lsnif_arithmetic_string(opt.arithmetic);
            return false;
        }
        std::error_code ec;
        o.lsnif_bytes = fs::file_size(asset, ec);
        out.objects.push_back(std::move(o));
    }
    if (out.objects.empty()) {
        error = mp.string() + ": no complex mesh with an asset to measure";
        return false;
    }
    return true;
}

// Node counts of an 8-wide BVH over the triangles, built by Embree's own BVH builder
// (rtcBuildBVH, SAH, medium quality) with leaves of at most 3 triangles — the layout of
// compressed wide BVHs (Ylitie et al. 2017) that the paper's 80-bytes-per-node estimate
// assumes. Embree 3 does not expose the node count of its internal scene BVH.
struct Bvh8Counts {
    std::uint64_t inner = 0, leaves = 0;
};

Bvh8Counts count_bvh8_nodes(RTCDevice device, const scene::Mesh& m) {
    std::vector<RTCBuildPrimitive> prims(m.triangle_count());
    for (std::size_t t = 0; t < prims.size(); ++t) {
        float lo[3] = {INFINITY, INFINITY, INFINITY}, hi[3] = {-INFINITY, -INFINITY, -INFINITY};
        for (int c = 0; c < 3; ++c)
            for (int a = 0; a < 3; ++a) {
                const float v = m.positions[std::size_t(m.indices[t * 3 + c]) * 3 + a];
                lo[a] = std::min(lo[a], v);
                hi[a] = std::max(hi[a], v);
            }
        prims[t] = {lo[0], lo[1], lo[2], 0u, hi[0], hi[1], hi[2], std::uint32_t(t)};
    }
    struct Counters {
        std::atomic<std::uint64_t> inner{0}, leaves{0};
    } counters;
    RTCBVH bvh = rtcNewBVH(device);
    RTCBuildArguments args = rtcDefaultBuildArguments();
    args.byteSize = sizeof(args);
    args.buildQuality = RTC_BUILD_QUALITY_MEDIUM;
    args.maxBranchingFactor = 8;
    args.maxDepth = 1024;
    args.sahBlockSize = 1;
    args.minLeafSize = 1;
    args.maxLeafSize = 3;
    args.traversalCost = 1.0f;
    args.intersectionCost = 1.0f;
    args.bvh = bvh;
    args.primitives = prims.data();
    args.primitiveCount = prims.size();
    args.primitiveArrayCapacity = prims.size();
    args.userPtr = &counters;
    args.createNode = [](RTCThreadLocalAllocator alloc, unsigned, void* user) -> void* {
        static_cast<Counters*>(user)->inner++;
        return rtcThreadLocalAlloc(alloc, 8, 8);
    };
    args.setNodeChildren = [](void*, void**, unsigned, void*) {};
    args.setNodeBounds = [](void*, const RTCBounds**, unsigned, void*) {};
    args.createLeaf = [](RTCThreadLocalAllocator alloc, const RTCBuildPrimitive*, size_t,
                         void* user) -> void* {
        static_cast<Counters*>(user)->leaves++;
        return rtcThreadLocalAlloc(alloc, 8, 8);
    };
    rtcBuildBVH(&args);
    rtcReleaseBVH(bvh);
    return {counters.inner.load(), counters.leaves.load()};
}

std::unique_ptr<sampling::EmbreeSource> make_source(const Object& o, std::uint32_t threads,
                                                    std::string& error) {
    sampling::MeshView v{o.mesh.positions, o.mesh.indices, o.mesh.normals, o.mesh.triangle_materials};
    sampling::SamplingConfig cfg;
    cfg.threads = threads;
    return sampling::EmbreeSource::create(v, o.box, cfg, error);
}

}  // namespace

json bench_memory(const SceneBenchOptions& opt, std::string& error) {
    Loaded l;
    if (!load_objects(opt, l, error)) return {};
    // One thread, as the sources' own devices: Embree's thread count is process-wide, so a
    // device with every core here would make the sources' BVH builds multi-threaded too, and
    // their byte counts would change from run to run (per-thread allocation blocks).
    RTCDevice device = rtcNewDevice("threads=1");
    json objects = json::array();
    std::uint64_t total_lsnif = 0, total_bvh = 0, total_bvh8 = 0;
    for (const Object& o : l.objects) {
        auto src = make_source(o, opt.threads, error);
        if (!src) {
            rtcReleaseDevice(device);
            error = o.name + ": " + error;
            return {};
        }
        const Bvh8Counts c = count_bvh8_nodes(device, o.mesh);
        const std::uint64_t bvh8 = 80 * c.inner;
        total_lsnif += o.lsnif_bytes;
        total_bvh += src->bvh_bytes();
        total_bvh8 += bvh8;
        objects.push_back({{"name", o.name},
                           {"triangles", o.mesh.triangle_count()},
                           {"instances", o.instances},
                           {"lsnif_bytes", o.lsnif_bytes},
                           {"embree_bvh_bytes", src->bvh_bytes()},
                           {"embree_device_bytes", src->device_bytes()},
                           {"bvh8_inner_nodes", c.inner},
                           {"bvh8_leaves", c.leaves},
                           {"bvh8_compressed_bytes_estimate", bvh8},
                           {"ratio_embree_over_lsnif", double(src->bvh_bytes()) / double(o.lsnif_bytes)},
                           {"ratio_bvh8_over_lsnif", double(bvh8) / double(o.lsnif_bytes)}});
    }
    rtcReleaseDevice(device);
    return {
        {"benchmark", "memory"},
        {"outdir", opt.outdir},
        {"objects", objects},
        {"total",
         {{"lsnif_bytes", total_lsnif},
          {"embree_bvh_bytes", total_bvh},
          {"bvh8_compressed_bytes_estimate", total_bvh8},
          {"ratio_embree_over_lsnif", double(total_bvh) / double(std::max<std::uint64_t>(1, total_lsnif))}}}};
}

json bench_rays(const SceneBenchOptions& opt, std::string& error) {
    Loaded l;
    if (!load_objects(opt, l, error)) return {};
    json objects = json::array();
    for (const Object& o : l.objects) {
        auto src = make_source(o, opt.threads, error);
        if (!src) {
            error = o.name + ": " + error;
            return {};
        }
        // Embree: rtcIntersect1 loop and rtcIntersect16 packets over the rays generate()
        // makes (all three families, a quarter shadow rays), best of `repeats`.
        const sampling::GenerationStats g =
            sampling::measure_throughput(*src, opt.seed, opt.rays, opt.repeats);
        std::vector<samples::Sample> samples;
        src->generate(opt.seed, opt.rays, samples);
        std::vector<lsnif_ray> rays(samples.size());
        for (std::size_t i = 0; i < samples.size(); ++i) {
            const auto& r = samples[i].ray;
            rays[i] = {{r.org[0], r.org[1], r.org[2]}, r.tmin, {r.dir[0], r.dir[1], r.dir[2]}, r.tmax};
        }
        // The reader on the same rays: each thread takes 256-ray batches from a shared
        // counter (lsnif.h's advice), same thread count.
        std::vector<lsnif_hit> hits(rays.size());
        double best = INFINITY;
        for (std::uint32_t rep = 0; rep < opt.repeats; ++rep) {
            const auto t0 = Clock::now();
            base::parallel_chunks(rays.size(), opt.threads, 256,
                                  [&](std::uint32_t, std::size_t b, std::size_t e) {
                                      lsnif_intersect(o.model, rays.data() + b, e - b, hits.data() + b);
                                  });
            best = std::min(best, seconds_since(t0));
        }
        std::size_t agree = 0;
        for (std::size_t i = 0; i < rays.size(); ++i) agree += (hits[i].hit != 0) == (samples[i].hit != 0);
        const double lsnif_rps = double(rays.size()) / best;
        objects.push_back(
            {{"name", o.name},
             {"triangles", o.mesh.triangle_count()},
             {"rays", rays.size()},
             {"threads", opt.threads},
             {"lsnif_rays_per_second", lsnif_rps},
             {"rtcintersect1_rays_per_second", g.plain_rtcintersect_rays_per_second},
             {"rtcintersect16_rays_per_second", g.packet_rays_per_second},
             {"ratio_lsnif_over_rtcintersect1", lsnif_rps / g.plain_rtcintersect_rays_per_second},
             {"ratio_lsnif_over_rtcintersect16", lsnif_rps / g.packet_rays_per_second},
             {"time_ratio_lsnif_over_rtcintersect1", g.plain_rtcintersect_rays_per_second / lsnif_rps},
             {"hit_agreement", double(agree) / double(rays.size())},
             {"lsnif_arithmetic", lsnif_arithmetic_string(lsnif_get_arithmetic(o.model))}});
    }
    return {{"benchmark", "rays"}, {"outdir", opt.outdir}, {"objects", objects}};
}

json bench_convert(const ConvertOptions& copt, std::string& error) {
    ConvertOptions o = copt;
    const auto t0 = Clock::now();
    const ConvertResult r = convert(o);
    const double wall = seconds_since(t0);
    if (!r.ok()) {
        error = r.errors.empty() ? "conversion failed" : r.errors[0];
        return {};
    }
    json objects = json::array();
    std::map<std::string, double> totals;
    for (const MeshOutcome& m : r.meshes) {
        json t = json::object();
        for (std::size_t k = 0; k < kStageCount; ++k) {
            const std::optional<double>& seconds = m.timings.seconds[k];
            if (!seconds) continue;
            const std::string stage(stage_name(Stage(k)));
            t[stage] = *seconds;
            totals[stage] += *seconds;
        }
        objects.push_back(
            {{"name", m.name}, {"class", class_name(m.cls())}, {"triangles", m.triangles}, {"timings", t}});
    }
    json out = {{"benchmark", "convert"}, {"preset", o.preset}, {"threads", o.threads},
                {"wall_seconds", wall},   {"objects", objects}, {"stage_totals", totals}};
    out["run_timings"] = {{"import", r.import_seconds}};
    return out;
}

std::string bench_scene_text(const json& r) {
    char buf[640];
    std::string s;
    if (r["benchmark"] == "memory") {
        s += "object                      triangles  .lsnif bytes  Embree BVH bytes (ratio)  BVH8 est. bytes "
             "(ratio)\n";
        for (const json& o : r["objects"]) {
            std::snprintf(buf, sizeof buf, "%-26s %10llu %13llu %17llu (%5.2fx) %16llu (%5.2fx)\n",
                          o["name"].get<std::string>().c_str(), o["triangles"].get<unsigned long long>(),
                          o["lsnif_bytes"].get<unsigned long long>(),
                          o["embree_bvh_bytes"].get<unsigned long long>(),
                          o["ratio_embree_over_lsnif"].get<double>(),
                          o["bvh8_compressed_bytes_estimate"].get<unsigned long long>(),
                          o["ratio_bvh8_over_lsnif"].get<double>());
            s += buf;
        }
    } else if (r["benchmark"] == "rays") {
        s += "object                      rays     LSNIF rays/s  rtcIntersect1 rays/s (LSNIF ratio)  "
             "rtcIntersect16 (ratio)  hit agreement\n";
        for (const json& o : r["objects"]) {
            std::snprintf(
                buf, sizeof buf, "%-26s %8llu %12.0f %20.0f (%5.2fx) %16.0f (%5.2fx) %8.2f%%\n",
                o["name"].get<std::string>().c_str(), o["rays"].get<unsigned long long>(),
                o["lsnif_rays_per_second"].get<double>(), o["rtcintersect1_rays_per_second"].get<double>(),
                o["ratio_lsnif_over_rtcintersect1"].get<double>(),
                o["rtcintersect16_rays_per_second"].get<double>(),
                o["ratio_lsnif_over_rtcintersect16"].get<double>(), 100 * o["hit_agreement"].get<double>());
            s += buf;
        }
    } else {
        std::snprintf(buf, sizeof buf, "preset %s, wall %.2f s\n", r["preset"].get<std::string>().c_str(),
                      r["wall_seconds"].get<double>());
        s += buf;
        if (r.contains("run_timings"))
            for (const auto& [k, v] : r["run_timings"].items()) {
                std::snprintf(buf, sizeof buf, "  %-10s %8.3f s\n", k.c_str(), v.get<double>());
                s += buf;
            }
        for (const auto& [k, v] : r["stage_totals"].items()) {
            std::snprintf(buf, sizeof buf, "  %-10s %8.3f s (all objects)\n", k.c_str(), v.get<double>());
            s += buf;
        }
    }
    return s;
}

}  // namespace lsnif::converter
