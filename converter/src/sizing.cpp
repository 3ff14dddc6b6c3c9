// Converting one candidate: its rays, training the rungs of the sizing ladder, the gate per
// option, the choice, the asset and its metadata (convert_stages.hpp has the contracts).
#include <lsnif/base/clock.hpp>
#include <lsnif/converter/file_tools.hpp>
#include <lsnif/converter/settings.hpp>
#include <lsnif/format/quantize.hpp>
#include "convert_stages.hpp"

#include <cinttypes>

namespace lsnif::converter {

using nlohmann::json;
namespace fs = std::filesystem;
using Clock = std::chrono::steady_clock;
using base::seconds_since;
using namespace stages;

namespace stages {

namespace {

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

// Everything else that changes the trained weights: the recipe (bump kRecipeVersion when
// sampling or training code changes its streams) and the arithmetic (arithmetic_id: the
// canonical arithmetic's version, or the instructions of the machine arithmetic). The thread
// count is not part of it: it never changes a result.
constexpr int kRecipeVersion = 5;

std::string recipe_key(const Preset& p, Arithmetic arithmetic) {
    const trainer::TrainConfig& c = p.train;
    char buf[512];
    std::snprintf(buf, sizeof buf, "r%d|%s|lw%g,%g,%g,%g|g%g,%g,%g,%g|m%g,%g,%g,%g,%g|d%g,%g,%g,%g|n%d,%g",
                  kRecipeVersion, arithmetic_id(arithmetic).c_str(), c.loss.visibility, c.loss.distance,
                  c.loss.normal, c.loss.material, c.grid_adam.lr, c.grid_adam.beta1, c.grid_adam.beta2,
                  c.grid_adam.eps, c.mlp_adam.lr, c.mlp_adam.beta1, c.mlp_adam.beta2, c.mlp_adam.eps,
                  c.mlp_adam.l2, c.decay_start, c.final_lr_fraction, c.huber_delta, c.grad_clip_norm,
                  int(c.normal_loss), c.normal_chord_epsilon);
    return buf;
}

// The rules that decide which weights ship: the target with its stop margins, the abort
// rule, the validation checks, the sizing ladder and pruning. Part of the asset key, since
// they decide how many steps the weights saw, which size and encoding was kept and which of
// its neurons.
std::string stop_key(const Target& t, const Preset& p) {
    const TargetStop& s = p.target_stop;
    const EarlyAbort& a = p.early_abort;
    const Sizing& z = p.sizing;
    char buf[320];
    std::snprintf(
        buf, sizeof buf,
        "target%g,%g,%g|stop%u,%g,%g,%g|abort%llu,%g,%g,%g|checks%u,%llu|sizing%d,%d,%g,%u,%g|prune%d",
        t.visibility, t.distance_pct, t.normal_deg, s.consecutive, s.visibility_margin, s.distance_factor,
        s.normal_margin_deg, (unsigned long long)a.min_samples, a.visibility_headroom, a.normal_headroom_deg,
        a.distance_factor, p.validation_checks, (unsigned long long)p.validation_rays, int(z.explore_smaller),
        int(z.quantize), z.curve_slack, p.classify.min_log2_table_size, p.classify.min_memory_ratio,
        int(p.prune_inactive));
    return buf;
}

}  // namespace

std::string asset_key(const Run& run, const scene::Mesh& mesh, const format::ModelDesc& desc) {
    const Preset& p = run.preset;
    return scene::geometry_hash(mesh) + "|" + p.name + "|" + std::to_string(run.opt.seed) + "|" +
           std::to_string(p.train.steps) + "|" + std::to_string(p.train.batch_size) + "|" +
           std::to_string(p.train_rays) + "/" + std::to_string(p.train_chunk_rays) + "/" +
           std::to_string(p.train_window_chunks) + "|" + model_json(desc).dump() + "|" +
           recipe_key(p, run.opt.arithmetic) + "|" + stop_key(run.opt.target, p) + "|" +
           mesh_settings_key(run.opt);
}

std::optional<Reused> reusable_metrics(const fs::path& asset, const std::string& key) {
    std::error_code ec;
    if (!fs::exists(asset, ec)) return std::nullopt;
    auto bytes = format::read_file_bytes(asset.string());
    if (!bytes) return std::nullopt;
    auto model = format::read_model(*bytes);
    if (!model) return std::nullopt;
    json meta = json::parse(model->metadata_json, nullptr, false);
    if (!meta.is_object() || !meta.contains("metrics") || !meta["metrics"].contains("gate") ||
        meta.value("extensions", json::object()).value("lsnif_convert_key", "") != key)
        return std::nullopt;
    const json& families = meta["metrics"].value("families", json());
    const auto pooled = family_from_json(families.is_object() ? families.value("pooled", json()) : json());
    if (!pooled) return std::nullopt;  // not metrics this version writes: convert again
    return Reused{meta["metrics"], *pooled};
}

ValidationPoint validation_point(std::uint32_t step, const format::ModelData& model,
                                 std::span<const samples::Sample> rays, std::uint32_t threads) {
    const samples::Metrics m = samples::held_out_metrics(format::make_runtime(model), rays, threads);
    return {step, m.pooled.visibility_accuracy, m.pooled.distance_median_pct, m.pooled.normal_median_deg};
}

MeasureRays draw_measure_rays(const Run& run, const scene::Mesh& mesh, Candidate& c, MeshRecord& rec) {
    const auto t0 = Clock::now();
    run.report({mesh.name, "sample"});
    MeasureRays rays;
    std::vector<sampling::SampleExtras> extras;
    c.source->generate(run.opt.seed * 2 + 1 + 0x5bd1e995ull, run.preset.eval_rays, rays.held_out, &extras);
    rays.held_out_geometric_normals.resize(extras.size());
    for (std::size_t i = 0; i < extras.size(); ++i)
        rays.held_out_geometric_normals[i] = extras[i].geometric_normal;
    c.source->generate(run.opt.seed * 2 + 1 + 0x27d4eb2full, run.preset.validation_rays, rays.validation);
    rec.add_seconds("sample", seconds_since(t0));
    return rays;
}

Trained train_rung(const Run& run, const scene::Mesh& mesh, Candidate& c, const format::ModelDesc& desc,
                   const voxelize::Occupancy& occ, const MeasureRays& rays, std::uint32_t steps,
                   std::span<const ValidationPoint> larger, MeshRecord& rec) {
    const auto t0 = Clock::now();
    Trained t;
    t.config = run.preset.train;
    t.config.steps = steps;
    t.config.threads = run.threads;
    t.config.seed = run.opt.seed;
    trainer::Trainer tr(desc, occ.bits, t.config);
    // Rays in proportion to the steps: a rung trained on part of the budget sees the same
    // rays per step as the full schedule.
    const Preset& p = run.preset;
    trainer::StreamPlan plan;
    plan.total_rays = std::max<std::uint64_t>(1, p.train_rays * steps / std::max(1u, p.train.steps));
    plan.rays_per_round = p.train_chunk_rays;
    plan.window_rounds = p.train_window_chunks;
    const std::uint64_t seed = run.opt.seed;
    plan.round_seed = [seed](std::uint64_t r) {
        return fnv1a64("train|" + std::to_string(seed) + "|" + std::to_string(r));
    };
    const std::uint32_t checks = p.validation_checks;
    std::uint32_t next_check = 1;  // check k runs once k * steps / checks steps are done
    std::uint32_t met_in_a_row = 0;
    double validation_seconds = 0;
    // At each validation check: give up when the gate is out of reach or a smaller rung
    // cannot catch up; stop when the target is met (TargetStop).
    const Target aim = effective_target(run.opt.target, p.gate);
    auto decide = [&](std::uint32_t step, std::uint32_t of) {
        const ValidationPoint& point = t.validation.back();
        t.abandoned =
            early_abort_reasons(point, std::uint64_t(step) * t.config.batch_size, p.gate, p.early_abort);
        if (!t.abandoned.empty()) {
            t.abandoned_at = step;
            return false;
        }
        t.fell_behind = falls_behind(point, larger, aim, p.target_stop, p.sizing);
        if (!t.fell_behind.empty()) return false;
        met_in_a_row = meets_target_with_margin(point, aim, p.target_stop) ? met_in_a_row + 1 : 0;
        if (p.target_stop.consecutive && met_in_a_row >= p.target_stop.consecutive && step < of) {
            t.target_met_at = step;
            return false;
        }
        return true;
    };
    t.stream = trainer::train_streamed(tr, *c.source, plan, [&](const trainer::Progress& pr) {
        if (!rays.validation.empty() && next_check <= checks &&
            std::uint64_t(pr.step) * checks >= std::uint64_t(next_check) * pr.steps) {
            ++next_check;
            const auto tv = Clock::now();
            t.validation.push_back(
                validation_point(pr.step, tr.export_model("{}"), rays.validation, run.threads));
            validation_seconds += seconds_since(tv);
            if (!decide(pr.step, pr.steps)) return false;
        }
        const double elapsed = seconds_since(t0);
        run.report({mesh.name, "train", pr.step, pr.steps, pr.loss,
                    pr.step ? elapsed / pr.step * (pr.steps - pr.step) : 0.0});
        return true;
    });
    const trainer::StreamedResult& st = t.stream;
    rec.stats["mean_occupied_per_ray"] = st.rays_reaching ? st.entry_points / double(st.rays_reaching) : 0.0;
    rec.stats["training_rays"] = rec.stats.value("training_rays", std::uint64_t(0)) + st.rays_drawn;
    rec.add_seconds("sample", st.generate_seconds);
    rec.add_seconds("prepare", st.prepare_seconds);
    rec.add_seconds("train", st.train.seconds - validation_seconds);
    rec.add_seconds("validate", validation_seconds);
    t.model = tr.export_model("{}");
    if (p.prune_inactive) {
        const auto tp = Clock::now();
        t.pruned = remove_inactive_neurons(t.model, active_neurons(t.model, rays.validation, run.threads));
        rec.add_seconds("prune", seconds_since(tp));
    }
    t.seconds = seconds_since(t0);
    return t;
}

json gate(const Run& run, const scene::Mesh& mesh, const format::ModelData& model, const Trained& t,
          const MeasureRays& rays, samples::Metrics& m, MeshRecord& rec) {
    const auto t0 = Clock::now();
    run.report({mesh.name, "evaluate"});
    const format::Runtime rt = format::make_runtime(model);
    m = samples::held_out_metrics(rt, rays.held_out, run.threads, rays.held_out_geometric_normals);
    json metrics = {{"held_out_rays", rays.held_out.size()}, {"families", metrics_json(m)}};
    std::vector<std::string> reasons = gate_failures(m, run.preset.gate);
    if (t.stream.train.diverged) reasons.push_back(t.stream.train.message);
    for (const std::string& why : t.abandoned)
        reasons.push_back("training given up at step " + std::to_string(t.abandoned_at) + " of " +
                          std::to_string(t.config.steps) + ": " + why);
    json verdict = {{"passed", reasons.empty()}};
    if (!reasons.empty()) verdict["reasons"] = reasons;
    metrics["gate"] = verdict;
    rec.add_seconds("evaluate", seconds_since(t0));
    return metrics;
}

json candidate_json(const Option& o, const Trained& t) {
    const format::ModelDesc& d = o.model.desc;
    const json& p = o.metrics["families"]["pooled"];
    json j = {{"log2_table_size", d.log2_table_size},
              {"hidden_width", d.hidden_width},
              {"grid", grid_encoding_name(std::uint32_t(d.grid_encoding))},
              {"bytes", o.bytes},
              {"steps", t.stream.train.steps},
              {"steps_planned", t.config.steps},
              {"seconds", o.seconds},
              {"held_out",
               {{"visibility", p["visibility_accuracy"]},
                {"distance_pct", p["distance_error_median_pct"]},
                {"normal_deg", p["normal_error_median_deg"]}}},
              {"gate_passed", o.metrics["gate"]["passed"]},
              {"target_met", o.target_met},
              {"memory_rule_passed", o.memory_ok},
              {"outcome", o.outcome}};
    // The curve is the training's: recorded once, with the rung's fp16 export.
    if (d.grid_encoding == format::GridEncoding::fp16) j["validation"] = validation_json(t.validation);
    if (t.target_met_at) j["stopped"] = "the validation curve met the target";
    if (!t.abandoned.empty()) j["stopped"] = "given up: " + t.abandoned.front();
    if (!t.fell_behind.empty()) j["stopped"] = "given up: " + t.fell_behind;
    if (!t.pruned.empty()) j["pruned_neurons"] = t.pruned;
    return j;
}

Option measure_option(const Run& run, const scene::Mesh& mesh, const Candidate& c, std::size_t rung,
                      format::ModelData model, const Trained& t, const MeasureRays& rays, MeshRecord& rec) {
    const auto t0 = Clock::now();
    Option o;
    o.rung = rung;
    o.model = std::move(model);
    o.metrics = gate(run, mesh, o.model, t, rays, o.held_out, rec);
    o.target_met =
        o.metrics["gate"]["passed"].get<bool>() && target_misses(o.held_out.pooled, run.opt.target).empty();
    auto bytes = format::serialize(o.model);
    o.bytes = bytes ? bytes->size() : 0;
    o.memory_ok = bytes && memory_rule_failure(run, c, o.bytes).empty();
    o.seconds = seconds_since(t0);
    return o;
}

Sized size_to_target(const Run& run, const scene::Mesh& mesh, Candidate& c, const voxelize::Occupancy& occ,
                     const MeasureRays& rays, MeshRecord& rec) {
    Sized sized;
    const Preset& p = run.preset;
    format::ModelDesc desc = c.desc;
    std::uint32_t budget = p.train.steps;  // steps left to all rungs
    for (;;) {
        const std::vector<ValidationPoint> larger =
            sized.rungs.empty() ? std::vector<ValidationPoint>{} : sized.rungs.back().validation;
        sized.rungs.push_back(train_rung(run, mesh, c, desc, occ, rays, budget, larger, rec));
        const std::size_t rung = sized.rungs.size() - 1;
        const Trained& t = sized.rungs[rung];
        const std::size_t first = sized.options.size();
        add_options(run, mesh, c, rung, rays, sized, rec);
        bool met = false, fits = false;  // some option meets the target / beats the BVH
        for (std::size_t i = first; i < sized.options.size(); ++i) {
            met = met || sized.options[i].target_met;
            fits = fits || sized.options[i].memory_ok;
        }
        const std::uint32_t used = t.stream.train.steps;
        budget -= std::min(budget, used);
        // A smaller rung is worth a try only after this one met the target (or could not
        // beat the BVH, the estimate having been too hopeful), and only with at least as many
        // steps as this one needed: a smaller model does not learn faster.
        if ((!met && fits) || !p.sizing.explore_smaller || budget < used ||
            desc.log2_table_size <= p.classify.min_log2_table_size)
            break;
        --desc.log2_table_size;
    }
    choose_option(sized);
    for (const Option& o : sized.options) sized.candidates.push_back(candidate_json(o, sized.rungs[o.rung]));
    return sized;
}

void add_options(const Run& run, const scene::Mesh& mesh, const Candidate& c, std::size_t rung,
                 const MeasureRays& rays, Sized& sized, MeshRecord& rec) {
    const Trained& t = sized.rungs[rung];
    for (const format::GridEncoding e : rung_encodings(run.preset)) {
        format::ModelData model = t.model;
        if (e == format::GridEncoding::u8_affine) {
            auto quantized = format::quantize_model(t.model);
            if (!quantized) continue;  // cannot happen for a valid fp16 export; then fp16 only
            model = std::move(*quantized);
        }
        Option o = measure_option(run, mesh, c, rung, std::move(model), t, rays, rec);
        if (e == format::GridEncoding::fp16) o.seconds += t.seconds;  // the training is the fp16 option's
        sized.options.push_back(std::move(o));
    }
}

std::vector<format::GridEncoding> rung_encodings(const Preset& p) {
    if (p.sizing.quantize) return {format::GridEncoding::fp16, format::GridEncoding::u8_affine};
    return {format::GridEncoding::fp16};
}

void choose_option(Sized& sized) {
    const std::size_t n = sized.options.size();
    auto smaller = [&](std::size_t i) {
        return !sized.chosen || sized.options[i].bytes < sized.options[*sized.chosen].bytes;
    };
    auto passes = [&](const Option& o) { return o.memory_ok && o.metrics["gate"]["passed"].get<bool>(); };
    for (std::size_t i = 0; i < n; ++i)
        if (passes(sized.options[i]) && sized.options[i].target_met && smaller(i)) sized.chosen = i;
    if (sized.chosen) {
        sized.why = "the smallest of " + std::to_string(n) + " candidates that meets the target";
    } else {
        // No option meets the target: the most accurate model, the first rung's, ships if
        // it passes the gate, in its smallest encoding that does.
        for (std::size_t i = 0; i < n; ++i)
            if (sized.options[i].rung == 0 && passes(sized.options[i]) && smaller(i)) sized.chosen = i;
        if (sized.chosen) sized.why = "no candidate meets the target; the largest passes the gate";
    }
    for (std::size_t i = 0; i < n; ++i) {
        Option& o = sized.options[i];
        if (sized.chosen == i)
            o.outcome = "chosen: " + sized.why;
        else if (!o.metrics["gate"]["passed"].get<bool>())
            o.outcome = "fails the gate";
        else if (!o.memory_ok)
            o.outcome = "fails the memory rule";
        else if (o.target_met)
            o.outcome = "meets the target, but a smaller candidate does too";
        else
            o.outcome = "misses the target";
    }
}

json asset_metadata(const Run& run, const std::string& source, const scene::Mesh& mesh, const Candidate& c,
                    const Option& o, const Trained& t, const std::string& key) {
    const trainer::TrainConfig& cfg = t.config;
    const trainer::TrainResult& tres = t.stream.train;
    return {
        {"format", "lsnif-metadata/1"},
        {"tool", {{"name", "lsnif"}, {"version", LSNIF_VERSION_STRING}, {"command", run.opt.command_line}}},
        {"object",
         {{"name", mesh.name},
          {"source", source},
          {"source_hash", scene::geometry_hash(mesh)},
          {"box_min", vec3(c.box.min)},
          {"box_max", vec3(c.box.max)},
          {"triangle_count", mesh.triangle_count()},
          {"vertex_count", mesh.vertex_count()},
          {"closed", c.source->is_closed()}}},
        {"model", model_json(o.model.desc)},
        {"training",
         {{"seed", run.opt.seed},
          {"arithmetic", arithmetic_id(run.opt.arithmetic)},
          {"steps", tres.steps},
          {"batch_size", cfg.batch_size},
          {"samples", tres.samples},
          {"rays", t.stream.rays_drawn},
          {"rays_per_round", t.stream.rays_per_round},
          {"window_rounds", std::max<std::uint32_t>(1, run.preset.train_window_chunks)},
          {"learning_rate_grid", cfg.grid_adam.lr},
          {"learning_rate_mlp", cfg.mlp_adam.lr},
          {"loss_weights",
           {{"visibility", cfg.loss.visibility},
            {"distance", cfg.loss.distance},
            {"normal", cfg.loss.normal},
            {"material", cfg.loss.material}}},
          {"final_loss", std::isfinite(tres.final_loss) ? tres.final_loss : 0.0f},
          {"preset", run.preset.name},
          {"divergence_rollbacks", tres.rollbacks}}},
        {"metrics", o.metrics},
        {"extensions", {{"lsnif_convert_key", key}}}};
}

format::Result<std::vector<std::uint8_t>> encode_asset(Option& o, const json& metadata) {
    o.model.metadata_json = metadata.dump(2);
    return format::serialize(o.model);
}

std::string option_summary(const Option& o) {
    const format::ModelDesc& d = o.model.desc;
    return "2^" + std::to_string(d.log2_table_size) + " rows, " +
           grid_encoding_name(std::uint32_t(d.grid_encoding)) + " grid, " + std::to_string(o.bytes) +
           " bytes";
}

std::string write_asset(const Run& run, const scene::Mesh& mesh, std::span<const std::uint8_t> bytes,
                        const fs::path& asset, MeshRecord& rec) {
    const auto t0 = Clock::now();
    run.report({mesh.name, "write"});
    std::error_code ec;
    fs::create_directories(run.outdir, ec);
    const format::Error e = format::write_bytes_atomically(asset.string(), bytes);
    rec.add_seconds("write", seconds_since(t0));
    return e ? e.message : std::string();
}

json convert_candidate(const Run& run, Planned& p, std::vector<std::string>& errors) {
    const scene::Mesh& mesh = *p.mesh;
    const std::string& source = p.source;
    MeshRecord& rec = p.rec;
    Candidate& c = *p.candidate;
    if (run.opt.dry_run) return rec.finish("complex");  // the plan only: no sampling, training or files

    const std::string key = asset_key(run, mesh, c.desc);
    const std::string file = hex16(fnv1a64(key)) + ".lsnif";
    const fs::path asset = run.outdir / file;
    if (auto previous = reusable_metrics(asset, key))
        return shipped(run, std::move(previous->metrics), previous->pooled, file, asset, true, rec);

    const MeasureRays rays = draw_measure_rays(run, mesh, c, rec);
    Sized sized = size_to_target(run, mesh, c, *p.occupancy, rays, rec);
    rec.entry["candidates"] = sized.candidates;
    // The chosen option, or the first rung's fp16 model when none may ship.
    Option& o = sized.options[sized.chosen.value_or(0)];
    const Trained& t = sized.rungs[o.rung];
    const json& metrics = o.metrics;
    rec.entry["validation"] = validation_json(t.validation);
    if (t.target_met_at)
        rec.entry["stopped_early"] = {{"step", t.target_met_at},
                                      {"steps", t.config.steps},
                                      {"reason", "validation curve met the target"}};
    if (!sized.chosen) return below_gate(metrics, !t.abandoned.empty(), rec);
    rec.reasons.push_back(option_summary(o) + ": " + sized.why);
    auto bytes = encode_asset(o, asset_metadata(run, source, mesh, c, o, t, key));
    if (!bytes) {
        errors.push_back(source + ": mesh '" + mesh.name + "': " + bytes.error().message);
        return rec.failed("the asset could not be encoded: " + bytes.error().message);
    }
    if (std::string why = memory_rule_failure(run, c, bytes->size()); !why.empty()) {
        rec.entry["metrics"] = metrics;
        return rec.simple(why);
    }
    if (std::string err = write_asset(run, mesh, *bytes, asset, rec); !err.empty()) {
        errors.push_back(source + ": mesh '" + mesh.name + "': " + err);
        return rec.failed("the asset could not be written: " + err);
    }
    return shipped(run, metrics, o.held_out.pooled, file, asset, false, rec);
}

json shipped(const Run& run, json metrics, const samples::FamilyMetrics& pooled, const std::string& file,
             const fs::path& asset, bool reused, MeshRecord& rec) {
    rec.entry["target"] = target_json(run.opt.target, target_misses(pooled, run.opt.target));
    rec.entry["metrics"] = std::move(metrics);
    std::error_code ec;
    rec.entry["lsnif"] = {{"file", file}, {"bytes", fs::file_size(asset, ec)}, {"reused", reused}};
    return rec.finish("complex");
}

json below_gate(const json& metrics, bool abandoned, MeshRecord& rec) {
    rec.entry["metrics"] = metrics;
    for (const auto& r : metrics["gate"].value("reasons", std::vector<std::string>{}))
        rec.reasons.push_back("gate: " + r);
    return rec.simple(abandoned ? "decided early from the validation curve: stays BVH"
                                : "held-out accuracy below the gate: stays BVH");
}

}  // namespace stages

}  // namespace lsnif::converter
