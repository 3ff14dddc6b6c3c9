// `lsnif convert`; see convert.hpp for the contracts.
#include <lsnif/converter/convert.hpp>
#include <lsnif/converter/manifest.hpp>
#include <lsnif/format/forward.hpp>
#include <lsnif/sampling/sampling.hpp>
#include <lsnif/scene/scene.hpp>
#include <lsnif/voxelize/voxelize.hpp>

#include <algorithm>
#include <chrono>
#include <cinttypes>
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <lsnif/base/parallel.hpp>
#include <numeric>

namespace lsnif::converter {

using nlohmann::json;
namespace fs = std::filesystem;
using Clock = std::chrono::steady_clock;

namespace {

double since(Clock::time_point t0) {
    return std::chrono::duration<double>(Clock::now() - t0).count();
}

std::uint64_t fnv1a64(const std::string& s, std::uint64_t h = 0xcbf29ce484222325ull) {
    for (unsigned char c : s) {
        h ^= c;
        h *= 0x100000001b3ull;
    }
    return h;
}

std::string hex16(std::uint64_t v) {
    char buf[17];
    std::snprintf(buf, sizeof buf, "%016" PRIx64, v);
    return buf;
}

json vec3(const std::array<float, 3>& v) {
    return json::array({v[0], v[1], v[2]});
}

// Index-connected components (vertices shared by index), union-find with path halving.
std::size_t count_components(const scene::Mesh& m) {
    std::vector<std::uint32_t> parent(m.vertex_count());
    std::iota(parent.begin(), parent.end(), 0u);
    auto find = [&](std::uint32_t x) {
        while (parent[x] != x) x = parent[x] = parent[parent[x]];
        return x;
    };
    std::vector<std::uint8_t> used(m.vertex_count(), 0);
    for (std::size_t t = 0; t < m.triangle_count(); ++t) {
        const std::uint32_t a = m.indices[3 * t], b = m.indices[3 * t + 1], c = m.indices[3 * t + 2];
        used[a] = used[b] = used[c] = 1;
        parent[find(a)] = find(b);
        parent[find(b)] = find(c);
    }
    std::size_t n = 0;
    for (std::uint32_t v = 0; v < parent.size(); ++v) n += used[v] && find(v) == v;
    return n;
}

double surface_area(const scene::Mesh& m) {
    double area = 0;
    for (std::size_t t = 0; t < m.triangle_count(); ++t) {
        const float* p0 = &m.positions[3 * std::size_t(m.indices[3 * t])];
        const float* p1 = &m.positions[3 * std::size_t(m.indices[3 * t + 1])];
        const float* p2 = &m.positions[3 * std::size_t(m.indices[3 * t + 2])];
        const double e1[3] = {double(p1[0]) - p0[0], double(p1[1]) - p0[1], double(p1[2]) - p0[2]};
        const double e2[3] = {double(p2[0]) - p0[0], double(p2[1]) - p0[1], double(p2[2]) - p0[2]};
        const double c[3] = {e1[1] * e2[2] - e1[2] * e2[1], e1[2] * e2[0] - e1[0] * e2[2],
                             e1[0] * e2[1] - e1[1] * e2[0]};
        area += 0.5 * std::sqrt(c[0] * c[0] + c[1] * c[1] + c[2] * c[2]);
    }
    return area;
}

// Raw bytes a model of these dimensions occupies in a .lsnif (before compression, which
// barely shrinks trained fp16 weights): header, table, occupancy, tables, MLP, metadata.
std::uint64_t lsnif_bytes_estimate(const format::ModelDesc& d) {
    return 64 + 64 * 5 + (d.voxel_count() + 7) / 8 + d.parameter_count() * 2 + 2048;
}

std::string gate_reason(const char* what, double value, const char* op, double limit, const char* unit) {
    char buf[160];
    std::snprintf(buf, sizeof buf, "held-out %s %.4g%s %s gate %.4g%s", what, value, unit, op, limit, unit);
    return buf;
}

json family_json(const trainer::FamilyMetrics& f) {
    return {{"rays", f.rays},
            {"visibility_accuracy", f.visibility_accuracy},
            {"false_hit_rate", f.false_hit_rate},
            {"false_miss_rate", f.false_miss_rate},
            {"distance_error_median_pct", f.distance_median_pct},
            {"distance_error_p95_pct", f.distance_p95_pct},
            {"normal_error_median_deg", f.normal_median_deg},
            {"normal_error_p95_deg", f.normal_p95_deg},
            {"geometric_normal_error_median_deg", f.geometric_normal_median_deg},
            {"culled_fraction", f.culled_fraction}};
}

const char* distance_encoding_name(std::uint32_t e) {
    return e == LSNIF_DISTANCE_SEGMENT ? "segment" : "first_entry_diagonal";
}

json model_json(const format::ModelDesc& d) {
    return {{"grid_resolution", d.grid_resolution},
            {"max_points", d.max_points},
            {"level_resolutions", d.level_resolution},
            {"features_per_level", d.features_per_level},
            {"log2_table_size", d.log2_table_size},
            {"hidden_widths", d.hidden_width},
            {"output_count", d.output_count()},
            {"material_count", d.material_count},
            {"activation", "relu"},
            {"distance_encoding", distance_encoding_name(d.distance_encoding)},
            {"normal", "shading"},
            {"parameter_count", d.parameter_count()}};
}

struct MeshJob {
    const scene::Mesh* mesh;
    const scene::Scene* scene;
    std::size_t input, source_mesh, id, instances;
    std::string input_path;
};

}  // namespace

std::vector<std::string> gate_failures(const trainer::Metrics& m, const Gate& g) {
    std::vector<std::string> fails;
    if (m.pooled.visibility_accuracy < g.min_visibility)
        fails.push_back(gate_reason("visibility accuracy", 100 * m.pooled.visibility_accuracy, "<",
                                    100 * g.min_visibility, "%"));
    for (int f = 0; f < trainer::kFamilyCount; ++f)
        if (m.family[f].rays < g.min_family_rays)
            fails.push_back(std::string("held-out ") + trainer::family_name(trainer::Family(f)) +
                            " rays reaching the network: " + std::to_string(m.family[f].rays) + " < " +
                            std::to_string(g.min_family_rays) + " (too few to measure)");
    for (int f = 0; f < trainer::kFamilyCount; ++f)
        if (m.family[f].rays && m.family[f].visibility_accuracy < g.min_family_visibility)
            fails.push_back(
                gate_reason((std::string(trainer::family_name(trainer::Family(f))) + " visibility").c_str(),
                            100 * m.family[f].visibility_accuracy, "<", 100 * g.min_family_visibility, "%"));
    if (m.pooled.distance_median_pct > g.max_distance_median_pct)
        fails.push_back(gate_reason("median distance error", m.pooled.distance_median_pct, ">",
                                    g.max_distance_median_pct, "% of diagonal"));
    if (m.pooled.normal_median_deg > g.max_normal_median_deg)
        fails.push_back(gate_reason("median normal error", m.pooled.normal_median_deg, ">",
                                    g.max_normal_median_deg, " deg"));
    return fails;
}

json metrics_json(const trainer::Metrics& m) {
    return {{"outside", family_json(m.family[0])},
            {"surface", family_json(m.family[1])},
            {"interior", family_json(m.family[2])},
            {"pooled", family_json(m.pooled)}};
}

// Everything else that changes the trained weights: the recipe (bump kRecipeVersion when
// sampling or training code changes its streams), the thread count (training is
// deterministic per thread count) and the MLP arithmetic this machine will use.
constexpr int kRecipeVersion = 2;
static std::string recipe_key(const Preset& p, std::uint32_t threads) {
    const trainer::TrainConfig& c = p.train;
    char buf[512];
    std::snprintf(
        buf, sizeof buf, "r%d|t%u|%s|lw%g,%g,%g,%g|g%g,%g,%g,%g|m%g,%g,%g,%g,%g|d%g,%g,%g,%g", kRecipeVersion,
        threads, trainer::precision_name(trainer::resolve_precision(c.mlp_precision)), c.loss.visibility,
        c.loss.distance, c.loss.normal, c.loss.material, c.grid_adam.lr, c.grid_adam.beta1, c.grid_adam.beta2,
        c.grid_adam.eps, c.mlp_adam.lr, c.mlp_adam.beta1, c.mlp_adam.beta2, c.mlp_adam.eps, c.mlp_adam.l2,
        c.decay_start, c.final_lr_fraction, c.huber_delta, c.grad_clip_norm);
    return buf;
}

std::vector<std::string> preset_names() {
    return {"default", "fast", "quality", "smoke"};
}

bool find_preset(const std::string& name, Preset& p) {
    p = Preset{};
    p.name = name;
    // v1 model of docs/architecture.md §3 in every preset; presets trade training time for accuracy.
    // Measured on the dragon (BENCHMARKS.md "Conversion", 2^23 streamed rays, bf16 MLP):
    // at equal samples, more and smaller steps win slightly (1200 x 16384: 97.21 %, 0.90 %,
    // 14.1 deg in 77 s of training; 2400 x 8192: 97.46 %, 0.85 %, 12.8 deg in 83 s), and
    // doubling the normal loss weight buys 2 deg of normal error for 0.06 % of visibility
    // (2400 x 8192 with weight 1: 97.52 %, 0.83 %, 14.7 deg).
    p.train.batch_size = 1u << 13;
    p.train.loss.normal = 2.0f;
    if (name == "default") {
        p.train.steps = 2400;
        p.train_rays = 1u << 23;
    } else if (name == "fast") {
        p.train.batch_size = 1u << 14;
        p.train.steps = 300;
        p.train_rays = 1u << 21;
    } else if (name == "quality") {
        p.train.batch_size = 1u << 12;
        p.train.steps = 4800;
        p.train_rays = 1u << 23;
    } else if (name == "smoke") {
        // Pipeline check in seconds (tests, CI): a small model and a lenient gate that only
        // rejects an untrained network. Not for shipping assets.
        p.model.grid_resolution = 16;
        p.model.max_points = 8;
        p.model.level_resolution = {32, 64};
        p.model.features_per_level = 2;
        p.model.log2_table_size = 12;
        p.model.hidden_width = {32, 32};
        p.train.batch_size = 2048;
        p.train.steps = 400;
        p.train_rays = 1u << 15;
        p.train_chunk_rays = 1u << 14;  // two rounds: exercises the streaming path
        p.eval_rays = 1u << 13;
        p.classify.min_triangles = 100;
        p.gate = {0.75, 0.6, 25.0, 90.0};
    } else {
        return false;
    }
    return true;
}

ConvertResult convert(const ConvertOptions& opt, const ConvertProgress& progress) {
    ConvertResult res;
    Preset preset;
    if (!find_preset(opt.preset, preset)) {
        std::string names;
        for (const auto& n : preset_names()) names += (names.empty() ? "" : ", ") + n;
        res.errors.push_back("unknown preset '" + opt.preset + "' (known: " + names + ")");
        return res;
    }
    if (opt.gate_min_visibility >= 0) preset.gate.min_visibility = opt.gate_min_visibility;
    if (opt.steps > 0) preset.train.steps = opt.steps;
    if (opt.batch_size > 0) preset.train.batch_size = opt.batch_size;
    if (opt.log2_table_size > 0) preset.model.log2_table_size = opt.log2_table_size;
    if (opt.max_points > 0) preset.model.max_points = opt.max_points;
    if (opt.grid_resolution > 0) preset.model.grid_resolution = opt.grid_resolution;
    if (opt.hidden_width > 0)
        for (auto& w : preset.model.hidden_width) w = opt.hidden_width;
    const std::uint32_t threads = base::resolve_threads(opt.threads);
    auto report = [&](const ProgressEvent& e) {
        if (progress) progress(e);
    };
    const fs::path outdir = opt.outdir;
    json inputs = json::array(), meshes = json::array(), instances = json::array();
    std::vector<scene::Scene> scenes;  // kept alive while meshes are processed
    scenes.reserve(opt.inputs.size());
    std::size_t ok_inputs = 0, next_id = 0;
    double total_train_seconds = 0, import_seconds = 0;

    for (std::size_t in = 0; in < opt.inputs.size(); ++in) {
        const std::string& path = opt.inputs[in];
        report({path, "import"});
        const auto import_t0 = Clock::now();
        auto imported = scene::import_scene(path);
        import_seconds += since(import_t0);
        if (!imported.ok()) {
            res.errors.push_back(imported.error);
            inputs.push_back({{"path", manifest_relative_path(path, outdir)},
                              {"given", path},
                              {"status", "error"},
                              {"error", imported.error}});
            scenes.emplace_back();
            continue;
        }
        ++ok_inputs;
        scenes.push_back(std::move(imported.scene));
        const scene::Scene& sc = scenes.back();
        json in_json = {{"path", manifest_relative_path(path, outdir)}, {"given", path}, {"status", "ok"}};
        if (!sc.warnings.empty()) {
            in_json["warnings"] = sc.warnings;
            for (const auto& w : sc.warnings) res.warnings.push_back(path + ": " + w);
        }
        inputs.push_back(in_json);
        const std::size_t first_id = next_id;

        for (std::size_t k = 0; k < sc.meshes.size(); ++k) {
            const scene::Mesh& mesh = sc.meshes[k];
            const std::size_t id = next_id++;
            std::size_t inst_count = 0;
            for (const auto& i : sc.instances) inst_count += i.mesh == k;
            json mj = {{"id", id},
                       {"name", mesh.name},
                       {"input", in},
                       {"source_mesh", k},
                       {"triangles", mesh.triangle_count()},
                       {"vertices", mesh.vertex_count()},
                       {"geometry_hash", scene::geometry_hash(mesh)},
                       {"instances", inst_count}};
            std::vector<std::string> reasons;
            json timings = json::object();
            const bool forced_complex = std::find(opt.force_complex.begin(), opt.force_complex.end(),
                                                  mesh.name) != opt.force_complex.end();
            const bool forced_simple = std::find(opt.force_simple.begin(), opt.force_simple.end(),
                                                 mesh.name) != opt.force_simple.end();
            auto finish_simple = [&](const std::string& why) {
                reasons.push_back(why);
                mj["class"] = "simple";
                mj["reasons"] = reasons;
                mj["timings"] = timings;
                meshes.push_back(mj);
            };
            if (forced_simple) {
                finish_simple("forced simple by --simple " + mesh.name);
                continue;
            }
            if (mesh.triangle_count() < preset.classify.min_triangles && !forced_complex) {
                finish_simple(std::to_string(mesh.triangle_count()) + " triangles < " +
                              std::to_string(preset.classify.min_triangles) + ": a BVH is small and exact");
                continue;
            }
            // ---- classify: geometry statistics and the memory benefit ----
            auto t0 = Clock::now();
            report({mesh.name, "classify"});
            voxelize::MeshView vview{mesh.positions, mesh.indices};
            auto box = voxelize::padded_box(vview);
            if (!box) {
                finish_simple("cannot bound the mesh: " + box.error().message);
                continue;
            }
            const double ext[3] = {double(box->max[0]) - box->min[0], double(box->max[1]) - box->min[1],
                                   double(box->max[2]) - box->min[2]};
            {
                const double extent = std::max({ext[0], ext[1], ext[2]});
                double coord = 0;
                for (int a = 0; a < 3; ++a)
                    coord = std::max({coord, std::fabs(double(box->min[a])), std::fabs(double(box->max[a]))});
                if (!(extent >= kMinModelExtent && extent <= kMaxModelExtent && coord <= kMaxModelExtent)) {
                    char why[200];
                    std::snprintf(
                        why, sizeof why,
                        "box extent %.3g (coordinates up to %.3g) is outside the range LSNIF models in "
                        "single precision [%g, %g]",
                        extent, coord, kMinModelExtent, kMaxModelExtent);
                    finish_simple(why);
                    continue;
                }
            }
            format::ModelDesc desc = preset.model;
            desc.box_min = box->min;
            desc.box_max = box->max;
            const double box_area = 2 * (ext[0] * ext[1] + ext[1] * ext[2] + ext[0] * ext[2]);
            sampling::MeshView sview{mesh.positions, mesh.indices, mesh.normals, mesh.triangle_materials};
            sampling::SamplingConfig scfg;
            scfg.threads = threads;
            std::string serr;
            auto source =
                sampling::EmbreeSource::create(sview, sampling::Box{box->min, box->max}, scfg, serr);
            if (!source) {
                finish_simple("Embree could not build the mesh: " + serr);
                continue;
            }
            const std::uint64_t bvh = source->bvh_bytes();
            // Size the tables to the mesh (ClassifyRule): halve T while the asset would not
            // beat the BVH. Levels dense at the preset size stay dense (fewer rows than T).
            if (!forced_complex)
                while (desc.log2_table_size > preset.classify.min_log2_table_size &&
                       double(bvh) < preset.classify.min_memory_ratio * double(lsnif_bytes_estimate(desc)))
                    --desc.log2_table_size;
            const std::uint64_t est = lsnif_bytes_estimate(desc);
            json stats = {{"box_min", vec3(box->min)},
                          {"box_max", vec3(box->max)},
                          {"area_ratio", surface_area(mesh) / box_area},
                          {"components", count_components(mesh)},
                          {"closed", source->is_closed()},
                          {"solid", source->rejects_interior()},
                          {"log2_table_size", desc.log2_table_size},
                          {"bvh_bytes", bvh},
                          {"lsnif_bytes_estimate", est}};
            timings["classify"] = since(t0);
            t0 = Clock::now();
            report({mesh.name, "voxelize"});
            voxelize::Options vopt;
            vopt.threads = threads;
            auto occ = voxelize::voxelize(vview, *box, desc.grid_resolution, vopt);
            if (!occ) {
                mj["stats"] = stats;
                finish_simple("voxelization failed: " + occ.error().message);
                continue;
            }
            stats["occupied_fraction"] = double(occ->count()) / double(desc.voxel_count());
            timings["voxelize"] = since(t0);
            const double ratio = double(bvh) / double(est);
            char why[200];
            std::snprintf(why, sizeof why, "Embree BVH %" PRIu64 " bytes vs LSNIF %" PRIu64 " bytes (%.2fx)",
                          bvh, est, ratio);
            reasons.push_back(why);
            if (!forced_complex && ratio < preset.classify.min_memory_ratio) {
                mj["stats"] = stats;
                char s2[160];
                std::snprintf(s2, sizeof s2, "memory benefit %.2fx below the %.2fx threshold", ratio,
                              preset.classify.min_memory_ratio);
                finish_simple(s2);
                continue;
            }
            if (forced_complex)
                reasons.push_back("forced complex by --complex " + mesh.name);
            else
                reasons.push_back(std::to_string(mesh.triangle_count()) + " triangles");
            if (desc.log2_table_size != preset.model.log2_table_size)
                reasons.push_back("hash tables sized to 2^" + std::to_string(desc.log2_table_size) +
                                  " rows (preset 2^" + std::to_string(preset.model.log2_table_size) +
                                  ") to beat the BVH's memory");

            if (opt.dry_run) {  // the plan only: no sampling, training or files
                mj["class"] = "complex";
                mj["reasons"] = reasons;
                mj["stats"] = stats;
                mj["timings"] = timings;
                meshes.push_back(mj);
                continue;
            }
            // ---- asset name: content hash of geometry and settings ----
            const std::string key =
                scene::geometry_hash(mesh) + "|" + preset.name + "|" + std::to_string(opt.seed) + "|" +
                std::to_string(preset.train.steps) + "|" + std::to_string(preset.train.batch_size) + "|" +
                std::to_string(preset.train_rays) + "/" + std::to_string(preset.train_chunk_rays) + "/" +
                std::to_string(preset.train_window_chunks) + "|" + model_json(desc).dump() + "|" +
                recipe_key(preset, threads);
            const std::string file = hex16(fnv1a64(key)) + ".lsnif";
            const fs::path asset = outdir / file;
            json metrics;
            bool passed = false;
            bool reused = false;
            {
                lsnif_model* existing = nullptr;
                if (fs::exists(asset) && lsnif_open_file(asset.c_str(), &existing, nullptr) == LSNIF_OK) {
                    std::size_t len = 0;
                    const char* text = lsnif_metadata(existing, &len);
                    json meta = json::parse(text, text + len, nullptr, false);
                    lsnif_close(existing);
                    if (meta.is_object() && meta.contains("metrics") && meta["metrics"].contains("gate") &&
                        meta.value("extensions", json::object()).value("lsnif_convert_key", "") == key) {
                        metrics = meta["metrics"];
                        passed = metrics["gate"]["passed"].get<bool>();
                        reused = true;
                    }
                }
            }
            if (!reused) {
                // ---- sample held-out rays, then train in rounds of fresh rays ----
                t0 = Clock::now();
                report({mesh.name, "sample"});
                std::vector<trainer::Sample> held_out;
                std::vector<sampling::SampleExtras> extras;
                source->generate(opt.seed * 2 + 1 + 0x5bd1e995ull, preset.eval_rays, held_out, &extras);
                double sample_seconds = since(t0), prepare_seconds = 0;
                trainer::TrainConfig tcfg = preset.train;
                tcfg.threads = threads;
                tcfg.seed = opt.seed;
                trainer::Trainer tr(desc, occ->bits, tcfg);
                const std::uint64_t chunk =
                    std::max<std::uint64_t>(1, std::min(preset.train_chunk_rays, preset.train_rays));
                const std::uint64_t rounds =
                    std::min<std::uint64_t>((preset.train_rays + chunk - 1) / chunk, tcfg.steps);
                trainer::PreparedSet pool;          // the latest train_window_chunks chunks
                trainer::PreparedSet fresh;         // this round's chunk (buffers reused)
                std::vector<trainer::Sample> rays;  // this round's rays (capacity reused)
                // Room for the whole window up front: a pool that regrows reallocates and
                // copies hundreds of MB, and every fresh page is a page fault.
                pool.reserve(std::size_t(chunk) * std::max<std::uint32_t>(1, preset.train_window_chunks),
                             desc.max_points);
                std::vector<std::size_t> in_pool;  // their sizes, oldest first
                trainer::TrainResult tres;
                double points = 0;
                std::uint64_t reached = 0, drawn = 0;
                const auto tr_t0 = Clock::now();
                for (std::uint64_t r = 0; r < rounds && !tres.diverged; ++r) {
                    auto tp = Clock::now();
                    const std::uint64_t n = std::min(chunk, preset.train_rays - r * chunk);
                    source->generate(fnv1a64("train|" + std::to_string(opt.seed) + "|" + std::to_string(r)),
                                     n, rays);
                    drawn += n;
                    sample_seconds += since(tp);
                    tp = Clock::now();
                    tr.prepare_into(rays, fresh);
                    for (auto c : fresh.count) points += c;
                    reached += fresh.size();
                    // Drop the oldest round before adding this one: the pool's buffers never
                    // hold more than the window, and they stop growing after a few rounds.
                    if (in_pool.size() >= std::max<std::uint32_t>(1, preset.train_window_chunks)) {
                        pool.drop_front(in_pool.front());
                        in_pool.erase(in_pool.begin());
                    }
                    in_pool.push_back(fresh.size());
                    pool.append(fresh);
                    prepare_seconds += since(tp);
                    const auto until =
                        std::uint32_t(r + 1 == rounds ? tcfg.steps : tcfg.steps * (r + 1) / rounds);
                    const trainer::TrainResult part = tr.train(
                        pool,
                        [&](const trainer::Progress& p) {
                            const double elapsed = since(tr_t0);
                            report({mesh.name, "train", p.step, p.steps, p.loss,
                                    p.step ? elapsed / p.step * (p.steps - p.step) : 0.0});
                            return true;
                        },
                        until);
                    tres.steps = part.steps;
                    tres.seconds += part.seconds;
                    tres.samples += part.samples;
                    tres.rollbacks = part.rollbacks;
                    tres.final_loss = part.final_loss;
                    tres.diverged = part.diverged;
                    if (!part.message.empty()) tres.message = part.message;
                }
                stats["mean_occupied_per_ray"] = reached ? points / double(reached) : 0.0;
                stats["training_rays"] = drawn;
                timings["sample"] = sample_seconds;
                timings["prepare"] = prepare_seconds;
                timings["train"] = tres.seconds;
                total_train_seconds += tres.seconds;
                // ---- evaluate on held-out rays ----
                t0 = Clock::now();
                report({mesh.name, "evaluate"});
                format::ModelData model = tr.export_model("{}");
                const format::Runtime rt = format::make_runtime(model);
                std::vector<std::array<float, 3>> geo_normals(extras.size());
                for (std::size_t i = 0; i < extras.size(); ++i) geo_normals[i] = extras[i].geometric_normal;
                const trainer::Metrics m = trainer::evaluate(rt, held_out, threads, geo_normals);
                metrics = {{"held_out_rays", held_out.size()}, {"families", metrics_json(m)}};
                const auto fails = gate_failures(m, preset.gate);
                passed = fails.empty() && !tres.diverged;
                json gate = {{"passed", passed}};
                std::vector<std::string> gate_reasons = fails;
                if (tres.diverged) gate_reasons.push_back(tres.message);
                if (!gate_reasons.empty()) gate["reasons"] = gate_reasons;
                metrics["gate"] = gate;
                timings["evaluate"] = since(t0);
                // ---- write ----
                if (passed) {
                    t0 = Clock::now();
                    report({mesh.name, "write"});
                    std::vector<std::string> materials;
                    for (const auto& name : sc.materials) materials.push_back(name);
                    json meta = {{"format", "lsnif-metadata/1"},
                                 {"tool",
                                  {{"name", "lsnif"},
                                   {"version", LSNIF_VERSION_STRING},
                                   {"command", opt.command_line}}},
                                 {"object",
                                  {{"name", mesh.name},
                                   {"source", path},
                                   {"source_hash", scene::geometry_hash(mesh)},
                                   {"box_min", vec3(box->min)},
                                   {"box_max", vec3(box->max)},
                                   {"triangle_count", mesh.triangle_count()},
                                   {"vertex_count", mesh.vertex_count()},
                                   {"closed", source->is_closed()}}},
                                 {"model", model_json(desc)},
                                 {"training",
                                  {{"seed", opt.seed},
                                   {"threads", threads},
                                   {"steps", tres.steps},
                                   {"batch_size", tcfg.batch_size},
                                   {"samples", tres.samples},
                                   {"rays", drawn},
                                   {"rays_per_round", chunk},
                                   {"window_rounds", std::max<std::uint32_t>(1, preset.train_window_chunks)},
                                   // No wall time here: an asset must be reproducible byte for byte
                                   // (same input, seed and threads); timings are in the report.
                                   {"learning_rate_grid", tcfg.grid_adam.lr},
                                   {"learning_rate_mlp", tcfg.mlp_adam.lr},
                                   {"loss_weights",
                                    {{"visibility", tcfg.loss.visibility},
                                     {"distance", tcfg.loss.distance},
                                     {"normal", tcfg.loss.normal},
                                     {"material", tcfg.loss.material}}},
                                   {"final_loss", std::isfinite(tres.final_loss) ? tres.final_loss : 0.0f},
                                   {"preset", preset.name},
                                   {"divergence_rollbacks", tres.rollbacks}}},
                                 {"metrics", metrics},
                                 {"extensions", {{"lsnif_convert_key", key}}}};
                    model.metadata_json = meta.dump(2);
                    std::error_code ec;
                    fs::create_directories(outdir, ec);
                    if (format::Error e = format::write_file(asset.string(), model)) {
                        res.errors.push_back(path + ": mesh '" + mesh.name + "': " + e.message);
                        passed = false;
                    }
                    timings["write"] = since(t0);
                }
            }
            mj["stats"] = stats;
            mj["metrics"] = metrics;
            mj["timings"] = timings;
            if (passed) {
                std::error_code ec;
                mj["class"] = "complex";
                mj["reasons"] = reasons;
                mj["lsnif"] = {{"file", file}, {"bytes", fs::file_size(asset, ec)}, {"reused", reused}};
                meshes.push_back(mj);
            } else {
                for (const auto& r : metrics["gate"].value("reasons", std::vector<std::string>{}))
                    reasons.push_back("gate: " + r);
                finish_simple("held-out accuracy below the gate: stays BVH");
            }
        }
        for (const auto& i : sc.instances)
            instances.push_back({{"mesh", first_id + i.mesh},
                                 {"name", i.node_name},
                                 {"transform", std::vector<float>(i.transform.begin(), i.transform.end())}});
    }

    res.report = {{"inputs", inputs},
                  {"meshes", meshes},
                  {"instances", instances.size()},
                  {"errors", res.errors},
                  {"warnings", res.warnings}};
    res.report["timings"] = {{"import", import_seconds}};  // per-mesh stages are in meshes[].timings
    if (opt.dry_run) res.report["dry_run"] = true;
    if (ok_inputs == 0 || opt.dry_run) return res;  // nothing converted, or a plan: leave OUTDIR untouched

    json forced_c = opt.force_complex, forced_s = opt.force_simple;
    res.manifest = {
        {"format", kManifestFormat},
        {"tool", {{"name", "lsnif"}, {"version", LSNIF_VERSION_STRING}}},
        {"settings",
         {{"preset", preset.name},
          {"seed", opt.seed},
          {"threads", threads},
          {"forced_complex", forced_c},
          {"forced_simple", forced_s}}},
        {"inputs", inputs},
        {"meshes", meshes},
        {"instances", instances},
        {"simple_geometry",
         {{"location", "inputs"},
          {"note", "simple meshes are read from their input file (meshes[].input, meshes[].source_mesh)"}}}};
    std::error_code ec;
    fs::create_directories(outdir, ec);
    if (ec) {
        res.errors.push_back(outdir.string() + ": cannot create the output directory: " + ec.message());
        return res;
    }
    const std::string text = res.manifest.dump(2) + "\n";
    if (format::Error e =
            format::write_bytes_atomically((outdir / "manifest.json").string(),
                                           {reinterpret_cast<const std::uint8_t*>(text.data()), text.size()}))
        res.errors.push_back(e.message);
    res.report["manifest"] = (outdir / "manifest.json").string();
    return res;
}

std::string convert_text(const ConvertResult& r) {
    std::string s;
    char buf[512];
    if (!r.report.contains("meshes")) return s;
    for (const json& m : r.report["meshes"]) {
        std::snprintf(buf, sizeof buf, "%-8s %-24s %9" PRIu64 " tris  x%-3" PRIu64,
                      m["class"].get<std::string>().c_str(),
                      m["name"].get<std::string>().substr(0, 24).c_str(), m["triangles"].get<std::uint64_t>(),
                      m.value("instances", std::uint64_t(0)));
        s += buf;
        if (m.contains("lsnif")) {
            const json& p = m["metrics"]["families"]["pooled"];
            std::snprintf(
                buf, sizeof buf, "  %s %6.1f KiB  vis %.2f%%  dist %.3f%%  normal %.1f deg%s",
                m["lsnif"]["file"].get<std::string>().c_str(), m["lsnif"]["bytes"].get<double>() / 1024,
                100 * p["visibility_accuracy"].get<double>(), p["distance_error_median_pct"].get<double>(),
                p["normal_error_median_deg"].get<double>(),
                m["lsnif"]["reused"].get<bool>() ? " (reused)" : "");
            s += buf;
            const json& fam = m["metrics"]["families"];
            for (const char* f : {"outside", "surface", "interior"}) {
                std::snprintf(buf, sizeof buf,
                              "\n           %-8s vis %.2f%%  dist %.3f%% (p95 %.2f%%)  normal %.1f deg (p95 "
                              "%.1f)  culled %.0f%%",
                              f, 100 * fam[f]["visibility_accuracy"].get<double>(),
                              fam[f]["distance_error_median_pct"].get<double>(),
                              fam[f]["distance_error_p95_pct"].get<double>(),
                              fam[f]["normal_error_median_deg"].get<double>(),
                              fam[f]["normal_error_p95_deg"].get<double>(),
                              100 * fam[f]["culled_fraction"].get<double>());
                s += buf;
            }
        } else if (!m["reasons"].empty()) {
            s += "  " + m["reasons"].back().get<std::string>();
        }
        s += "\n";
    }
    std::snprintf(buf, sizeof buf, "%zu meshes, %" PRIu64 " instances\n", r.report["meshes"].size(),
                  r.report["instances"].get<std::uint64_t>());
    s += buf;
    if (r.report.contains("manifest")) s += "manifest: " + r.report["manifest"].get<std::string>() + "\n";
    if (r.report.value("dry_run", false)) s += "dry run: nothing written\n";
    return s;
}

}  // namespace lsnif::converter
