// `lsnif bench memory|rays|convert`: a converted scene measured against Embree on the same
// machine in the same run (docs/architecture.md §5 "Speed"; docs/investigations/ has the figures).
#include <lsnif/lsnif.h>
#include <lsnif/base/clock.hpp>
#include <lsnif/converter/convert.hpp>
#include <lsnif/converter/manifest.hpp>
#include <lsnif/eval/bench.hpp>

#include <lsnif/sampling/sampling.hpp>
#include <lsnif/scene/scene.hpp>
#include <map>

#include <embree3/rtcore.h>

#include <algorithm>
#include <atomic>
#include <chrono>
#include <filesystem>
#include <lsnif/base/parallel.hpp>

namespace lsnif::eval {
namespace fs = std::filesystem;
using converter::ConvertOptions;
using converter::ConvertResult;
using converter::LoadedManifest;
using converter::MeshClass;
using converter::MeshOutcome;
using converter::Stage;
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
    if (!converter::load_manifest(opt.outdir, opt.sources, loaded, error)) return false;
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
    json objects = json::array();
    std::uint64_t total_file = 0, total_resident = 0, total_bvh = 0, total_bvh8 = 0;
    auto ratio = [](std::uint64_t bvh, std::uint64_t asset) {
        return double(bvh) / double(std::max<std::uint64_t>(1, asset));
    };
    for (const Object& o : l.objects) {
        auto src = make_source(o, opt.threads, error);
        if (!src) {
            error = o.name + ": " + error;
            return {};
        }
        const sampling::MeshView view{o.mesh.positions, o.mesh.indices, o.mesh.normals,
                                      o.mesh.triangle_materials};
        const auto bvh8 = sampling::measure_compressed_bvh(view, error);
        if (!bvh8) {
            error = o.name + ": " + error;
            return {};
        }
        // What the renderer holds on this CPU (the arithmetic opened with), and with the fp32
        // network, the same on every CPU and the least (what conversion counts).
        lsnif_info here{}, fp32{};
        lsnif_get_info(o.model, &here);
        const lsnif_arithmetic chosen = lsnif_get_arithmetic(o.model);
        lsnif_set_arithmetic(o.model, LSNIF_ARITHMETIC_FP32, nullptr);
        lsnif_get_info(o.model, &fp32);
        lsnif_set_arithmetic(o.model, chosen, nullptr);
        const std::uint64_t resident = fp32.decoded_bytes;
        total_file += o.lsnif_bytes;
        total_resident += resident;
        total_bvh += src->bvh_bytes();
        total_bvh8 += bvh8->bytes();
        objects.push_back({{"name", o.name},
                           {"triangles", o.mesh.triangle_count()},
                           {"instances", o.instances},
                           {"lsnif_file_bytes", o.lsnif_bytes},
                           {"lsnif_resident_bytes", resident},
                           {"lsnif_resident_bytes_here", here.decoded_bytes},
                           {"arithmetic_here", lsnif_arithmetic_string(chosen)},
                           {"embree_bvh_bytes", src->bvh_bytes()},
                           {"embree_device_bytes", src->device_bytes()},
                           {"bvh8_inner_nodes", bvh8->inner_nodes},
                           {"bvh8_leaves", bvh8->leaves},
                           {"bvh8_compressed_bytes_estimate", bvh8->bytes()},
                           {"ratio_embree_over_resident", ratio(src->bvh_bytes(), resident)},
                           {"ratio_bvh8_over_resident", ratio(bvh8->bytes(), resident)},
                           {"ratio_embree_over_file", ratio(src->bvh_bytes(), o.lsnif_bytes)}});
    }
    return {
        {"benchmark", "memory"},
        {"outdir", opt.outdir},
        {"yardstick", "resident: lsnif_info.decoded_bytes with the fp32 network (the most any CPU holds)"},
        {"objects", objects},
        {"total",
         {{"lsnif_file_bytes", total_file},
          {"lsnif_resident_bytes", total_resident},
          {"embree_bvh_bytes", total_bvh},
          {"bvh8_compressed_bytes_estimate", total_bvh8},
          {"ratio_embree_over_resident", ratio(total_bvh, total_resident)},
          {"ratio_bvh8_over_resident", ratio(total_bvh8, total_resident)}}}};
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
    const ConvertResult r = converter::convert(o);
    const double wall = seconds_since(t0);
    if (!r.ok()) {
        error = r.errors.empty() ? "conversion failed" : r.errors[0];
        return {};
    }
    json objects = json::array();
    std::map<std::string, double> totals;
    for (const MeshOutcome& m : r.meshes) {
        json t = json::object();
        for (std::size_t k = 0; k < converter::kStageCount; ++k) {
            const std::optional<double>& seconds = m.timings.seconds[k];
            if (!seconds) continue;
            const std::string stage(converter::stage_name(Stage(k)));
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
        s += "Assets as a renderer holds them once open (fp32 network: the most any CPU holds), against\n"
             "Embree's BVH as built and an 8-wide compressed BVH (80 bytes per inner node)\n";
        s += "object                      triangles  held in memory   file bytes  Embree BVH (ratio)        "
             "compressed BVH (ratio)\n";
        for (const json& o : r["objects"]) {
            std::snprintf(buf, sizeof buf, "%-26s %10llu %15llu %12llu %13llu (%6.2fx) %15llu (%6.2fx)\n",
                          o["name"].get<std::string>().c_str(), o["triangles"].get<unsigned long long>(),
                          o["lsnif_resident_bytes"].get<unsigned long long>(),
                          o["lsnif_file_bytes"].get<unsigned long long>(),
                          o["embree_bvh_bytes"].get<unsigned long long>(),
                          o["ratio_embree_over_resident"].get<double>(),
                          o["bvh8_compressed_bytes_estimate"].get<unsigned long long>(),
                          o["ratio_bvh8_over_resident"].get<double>());
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

}  // namespace lsnif::eval
