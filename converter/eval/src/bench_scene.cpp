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

// BVH bytes over an asset's; an asset of 0 bytes counts as 1.
double bytes_ratio(std::uint64_t bvh, std::uint64_t asset) {
    return double(bvh) / double(std::max<std::uint64_t>(1, asset));
}

std::unique_ptr<sampling::EmbreeSource> make_source(const Object& o, std::uint32_t threads,
                                                    std::string& error) {
    sampling::MeshView v{o.mesh.positions, o.mesh.indices, o.mesh.normals, o.mesh.triangle_materials};
    sampling::SamplingConfig cfg;
    cfg.threads = threads;
    return sampling::EmbreeSource::create(v, o.box, cfg, error);
}

}  // namespace

double MemoryBytes::ratio_embree_over_resident() const {
    return bytes_ratio(embree_bvh_bytes, lsnif_resident_bytes);
}
double MemoryBytes::ratio_bvh8_over_resident() const {
    return bytes_ratio(bvh8_compressed_bytes_estimate, lsnif_resident_bytes);
}
double MemoryBytes::ratio_embree_over_file() const {
    return bytes_ratio(embree_bvh_bytes, lsnif_file_bytes);
}

double RaysObject::ratio_lsnif_over_rtcintersect1() const {
    return lsnif_rays_per_second / rtcintersect1_rays_per_second;
}
double RaysObject::ratio_lsnif_over_rtcintersect16() const {
    return lsnif_rays_per_second / rtcintersect16_rays_per_second;
}
double RaysObject::time_ratio_lsnif_over_rtcintersect1() const {
    return rtcintersect1_rays_per_second / lsnif_rays_per_second;
}

base::Result<MemoryBench, std::string> bench_memory(const SceneBenchOptions& opt) {
    Loaded l;
    std::string error;
    if (!load_objects(opt, l, error)) return error;
    MemoryBench out;
    out.outdir = opt.outdir;
    for (const Object& o : l.objects) {
        auto src = make_source(o, opt.threads, error);
        if (!src) return o.name + ": " + error;
        const sampling::MeshView view{o.mesh.positions, o.mesh.indices, o.mesh.normals,
                                      o.mesh.triangle_materials};
        const auto bvh8 = sampling::measure_compressed_bvh(view, error);
        if (!bvh8) return o.name + ": " + error;
        // What the renderer holds on this CPU (the arithmetic opened with), and with the fp32
        // network, the same on every CPU and the least (what conversion counts).
        lsnif_info here{}, fp32{};
        lsnif_get_info(o.model, &here);
        const lsnif_arithmetic chosen = lsnif_get_arithmetic(o.model);
        lsnif_set_arithmetic(o.model, LSNIF_ARITHMETIC_FP32, nullptr);
        lsnif_get_info(o.model, &fp32);
        lsnif_set_arithmetic(o.model, chosen, nullptr);
        MemoryObject m;
        m.name = o.name;
        m.triangles = o.mesh.triangle_count();
        m.instances = o.instances;
        m.lsnif_file_bytes = o.lsnif_bytes;
        m.lsnif_resident_bytes = fp32.decoded_bytes;
        m.lsnif_resident_bytes_here = here.decoded_bytes;
        m.arithmetic_here = lsnif_arithmetic_string(chosen);
        m.embree_bvh_bytes = src->bvh_bytes();
        m.embree_device_bytes = src->device_bytes();
        m.bvh8_inner_nodes = bvh8->inner_nodes;
        m.bvh8_leaves = bvh8->leaves;
        m.bvh8_compressed_bytes_estimate = bvh8->bytes();
        out.total.lsnif_file_bytes += m.lsnif_file_bytes;
        out.total.lsnif_resident_bytes += m.lsnif_resident_bytes;
        out.total.embree_bvh_bytes += m.embree_bvh_bytes;
        out.total.bvh8_compressed_bytes_estimate += m.bvh8_compressed_bytes_estimate;
        out.objects.push_back(std::move(m));
    }
    return out;
}

base::Result<RaysBench, std::string> bench_rays(const SceneBenchOptions& opt) {
    Loaded l;
    std::string error;
    if (!load_objects(opt, l, error)) return error;
    RaysBench out;
    out.outdir = opt.outdir;
    for (const Object& o : l.objects) {
        auto src = make_source(o, opt.threads, error);
        if (!src) return o.name + ": " + error;
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
        RaysObject x;
        x.name = o.name;
        x.triangles = o.mesh.triangle_count();
        x.rays = rays.size();
        x.threads = opt.threads;
        x.lsnif_rays_per_second = lsnif_rps;
        x.rtcintersect1_rays_per_second = g.plain_rtcintersect_rays_per_second;
        x.rtcintersect16_rays_per_second = g.packet_rays_per_second;
        x.hit_agreement = double(agree) / double(rays.size());
        x.lsnif_arithmetic = lsnif_arithmetic_string(lsnif_get_arithmetic(o.model));
        out.objects.push_back(std::move(x));
    }
    return out;
}

base::Result<ConvertBench, std::string> bench_convert(const ConvertOptions& copt) {
    ConvertOptions o = copt;
    const auto t0 = Clock::now();
    const ConvertResult r = converter::convert(o);
    const double wall = seconds_since(t0);
    if (!r.ok()) return r.errors.empty() ? std::string("conversion failed") : r.errors[0];
    ConvertBench out;
    out.preset = o.preset;
    out.threads = o.threads;
    out.wall_seconds = wall;
    out.import_seconds = r.import_seconds;
    for (const MeshOutcome& m : r.meshes) {
        for (std::size_t k = 0; k < converter::kStageCount; ++k)
            if (const std::optional<double>& seconds = m.timings.seconds[k])
                out.stage_totals[std::string(converter::stage_name(Stage(k)))] += *seconds;
        out.objects.push_back({m.name, m.cls(), m.triangles, m.timings});
    }
    return out;
}

namespace {

json memory_bytes_json(const MemoryBytes& b) {
    return {{"lsnif_file_bytes", b.lsnif_file_bytes},
            {"lsnif_resident_bytes", b.lsnif_resident_bytes},
            {"embree_bvh_bytes", b.embree_bvh_bytes},
            {"bvh8_compressed_bytes_estimate", b.bvh8_compressed_bytes_estimate},
            {"ratio_embree_over_resident", b.ratio_embree_over_resident()},
            {"ratio_bvh8_over_resident", b.ratio_bvh8_over_resident()}};
}

json memory_object_json(const MemoryObject& m) {
    json j = memory_bytes_json(m);
    j.update({{"name", m.name},
              {"triangles", m.triangles},
              {"instances", m.instances},
              {"lsnif_resident_bytes_here", m.lsnif_resident_bytes_here},
              {"arithmetic_here", m.arithmetic_here},
              {"embree_device_bytes", m.embree_device_bytes},
              {"bvh8_inner_nodes", m.bvh8_inner_nodes},
              {"bvh8_leaves", m.bvh8_leaves},
              {"ratio_embree_over_file", m.ratio_embree_over_file()}});
    return j;
}

json rays_object_json(const RaysObject& x) {
    return {{"name", x.name},
            {"triangles", x.triangles},
            {"rays", x.rays},
            {"threads", x.threads},
            {"lsnif_rays_per_second", x.lsnif_rays_per_second},
            {"rtcintersect1_rays_per_second", x.rtcintersect1_rays_per_second},
            {"rtcintersect16_rays_per_second", x.rtcintersect16_rays_per_second},
            {"ratio_lsnif_over_rtcintersect1", x.ratio_lsnif_over_rtcintersect1()},
            {"ratio_lsnif_over_rtcintersect16", x.ratio_lsnif_over_rtcintersect16()},
            {"time_ratio_lsnif_over_rtcintersect1", x.time_ratio_lsnif_over_rtcintersect1()},
            {"hit_agreement", x.hit_agreement},
            {"lsnif_arithmetic", x.lsnif_arithmetic}};
}

// A stage that did not run is absent, as in the manifest's `timings`.
json timings_json(const converter::Timings& t) {
    json j = json::object();
    for (std::size_t k = 0; k < converter::kStageCount; ++k)
        if (t.seconds[k]) j[std::string(converter::stage_name(Stage(k)))] = *t.seconds[k];
    return j;
}

json convert_object_json(const ConvertObject& m) {
    return {{"name", m.name},
            {"class", converter::class_name(m.cls)},
            {"triangles", m.triangles},
            {"timings", timings_json(m.timings)}};
}

}  // namespace

json bench_json(const MemoryBench& b) {
    json objects = json::array();
    for (const MemoryObject& m : b.objects) objects.push_back(memory_object_json(m));
    return {
        {"benchmark", "memory"},
        {"outdir", b.outdir},
        {"yardstick", "resident: lsnif_info.decoded_bytes with the fp32 network (the most any CPU holds)"},
        {"objects", objects},
        {"total", memory_bytes_json(b.total)}};
}

json bench_json(const RaysBench& b) {
    json objects = json::array();
    for (const RaysObject& x : b.objects) objects.push_back(rays_object_json(x));
    return {{"benchmark", "rays"}, {"outdir", b.outdir}, {"objects", objects}};
}

json bench_json(const ConvertBench& b) {
    json objects = json::array();
    for (const ConvertObject& m : b.objects) objects.push_back(convert_object_json(m));
    return {{"benchmark", "convert"},
            {"preset", b.preset},
            {"threads", b.threads},
            {"wall_seconds", b.wall_seconds},
            {"objects", objects},
            {"stage_totals", b.stage_totals},
            {"run_timings", {{"import", b.import_seconds}}}};
}

std::string bench_text(const MemoryBench& r) {
    char buf[640];
    std::string s =
        "Assets as a renderer holds them once open (fp32 network: the most any CPU holds), against\n"
        "Embree's BVH as built and an 8-wide compressed BVH (80 bytes per inner node)\n";
    s += "object                      triangles  held in memory   file bytes  Embree BVH (ratio)        "
         "compressed BVH (ratio)\n";
    for (const MemoryObject& o : r.objects) {
        std::snprintf(buf, sizeof buf, "%-26s %10llu %15llu %12llu %13llu (%6.2fx) %15llu (%6.2fx)\n",
                      o.name.c_str(), (unsigned long long)o.triangles,
                      (unsigned long long)o.lsnif_resident_bytes, (unsigned long long)o.lsnif_file_bytes,
                      (unsigned long long)o.embree_bvh_bytes, o.ratio_embree_over_resident(),
                      (unsigned long long)o.bvh8_compressed_bytes_estimate, o.ratio_bvh8_over_resident());
        s += buf;
    }
    return s;
}

std::string bench_text(const RaysBench& r) {
    char buf[640];
    std::string s =
        "object                      rays     LSNIF rays/s  rtcIntersect1 rays/s (LSNIF ratio)  "
        "rtcIntersect16 (ratio)  hit agreement\n";
    for (const RaysObject& o : r.objects) {
        std::snprintf(buf, sizeof buf, "%-26s %8llu %12.0f %20.0f (%5.2fx) %16.0f (%5.2fx) %8.2f%%\n",
                      o.name.c_str(), (unsigned long long)o.rays, o.lsnif_rays_per_second,
                      o.rtcintersect1_rays_per_second, o.ratio_lsnif_over_rtcintersect1(),
                      o.rtcintersect16_rays_per_second, o.ratio_lsnif_over_rtcintersect16(),
                      100 * o.hit_agreement);
        s += buf;
    }
    return s;
}

std::string bench_text(const ConvertBench& r) {
    char buf[640];
    std::snprintf(buf, sizeof buf, "preset %s, wall %.2f s\n", r.preset.c_str(), r.wall_seconds);
    std::string s = buf;
    std::snprintf(buf, sizeof buf, "  %-10s %8.3f s\n", "import", r.import_seconds);
    s += buf;
    for (const auto& [k, v] : r.stage_totals) {
        std::snprintf(buf, sizeof buf, "  %-10s %8.3f s (all objects)\n", k.c_str(), v);
        s += buf;
    }
    return s;
}

}  // namespace lsnif::eval
