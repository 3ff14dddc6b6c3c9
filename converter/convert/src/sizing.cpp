// Converting one candidate: its rays, training the rungs of the sizing ladder, the gate per
// option, the choice, the asset and its metadata (convert_stages.hpp has the contracts).
#include <lsnif/base/clock.hpp>
#include <lsnif/base/random.hpp>
#include <lsnif/converter/metadata_names.hpp>
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

// The image error the gate and the target read: the combined image over the object's pixels.
std::optional<double> image_error(const std::optional<render::ObjectFlip>& f) {
    return f ? std::optional<double>(f->combined_object) : std::nullopt;
}

// How far above the image gate a model may be at a validation check and still be trained on
// when its rays say the gate is out of reach (EarlyAbort), as a factor of the gate: the
// largest fall of an image error measured from such a check to the end of training, with
// margin (docs/investigations/judged-by-how-it-looks.md "The visual check's figures").
constexpr double kImageHeadroom = 1.5;

// Whether the image gate may still be reached (Gate::accept takes images and the views
// exist): the current model rendered in the views is within kImageHeadroom of the gate.
bool image_gate_in_reach(const Run& run, const trainer::Trainer& tr, const MeasureRays& rays,
                         MeshOutcome& out) {
    if (run.preset.gate.accept == Acceptance::rays || !rays.decision_views) return false;
    const auto t0 = Clock::now();
    auto bytes = format::serialize(tr.export_model("{}"));
    auto flip = bytes ? rays.decision_views->compare(*bytes)
                      : base::Result<render::ObjectFlip, std::string>(std::string());
    out.timings.add(Stage::visual, seconds_since(t0));
    return flip && flip->combined_object <= run.preset.gate.max_flip * kImageHeadroom;
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
    const render::ObjectViewOptions& v = p.views;
    const Gate& g = p.gate;
    char buf[640];
    std::snprintf(
        buf, sizeof buf,
        "target%g,%g,%g,%g|stop%u,%g,%g,%g|abort%llu,%g,%g,%g,%g|checks%u,%llu|decision%llu|sizing%d,%d,%g,"
        "%u,%g,%u,%g,%u,%g,%g,%g,%g|prune%d|views%d,%u,%u,%u,%u,%llu|accept%s,%g",
        t.visibility, t.distance_pct, t.normal_deg, t.flip, s.consecutive, s.visibility_margin,
        s.distance_factor, s.normal_margin_deg, (unsigned long long)a.min_samples, a.visibility_headroom,
        a.normal_headroom_deg, a.distance_factor, kImageHeadroom, p.validation_checks,
        (unsigned long long)p.validation_rays, (unsigned long long)p.eval_rays, int(z.explore_smaller),
        int(z.quantize), z.curve_slack, p.classify.min_log2_table_size, p.classify.min_memory_ratio,
        z.max_grid_resolution, z.finer_grid_headroom, z.first_log2_table_size, z.climb_visibility,
        z.climb_normal_deg, z.climb_distance_factor, z.descend_budget_fraction, int(p.prune_inactive),
        int(p.visual_check), v.width, v.height, v.views, v.ao_samples, (unsigned long long)v.seed,
        acceptance_name(g.accept), g.max_flip);
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

std::optional<HeldOut> reusable_metrics(const fs::path& asset, const std::string& key) {
    std::error_code ec;
    if (!fs::exists(asset, ec)) return std::nullopt;
    auto bytes = format::read_file_bytes(asset.string());
    if (!bytes) return std::nullopt;
    auto model = format::read_model(*bytes);
    if (!model) return std::nullopt;
    const json meta = json::parse(model->metadata_json, nullptr, false);
    if (!meta.is_object() || !meta.contains("extensions") || !meta["extensions"].is_object() ||
        meta["extensions"].value("lsnif_convert_key", json()) != key || !meta.contains("metrics"))
        return std::nullopt;
    auto metrics = held_out_from_json(meta["metrics"]);
    if (!metrics) return std::nullopt;  // not metrics this version writes: convert again
    return std::move(*metrics);
}

std::unique_ptr<render::ObjectViews> object_views(const Run& run, const scene::Mesh& mesh,
                                                  std::uint64_t seed) {
    render::ObjectViewOptions views = run.preset.views;
    views.threads = run.threads;
    views.seed = seed;
    std::string error;
    return render::ObjectViews::create(mesh.positions, mesh.indices, mesh.normals, views, error);
}

ValidationPoint validation_point(std::uint32_t step, const format::ModelData& model,
                                 std::span<const samples::Sample> rays, std::uint32_t threads) {
    const samples::Metrics m = samples::held_out_metrics(format::make_runtime(model), rays, threads);
    return {step, m.pooled.visibility_accuracy, m.pooled.distance_median_pct, m.pooled.normal_median_deg};
}

std::uint32_t choose_escape_points(const format::ModelData& model, std::span<const samples::Sample> front,
                                   std::uint32_t threads) {
    if (front.empty()) return 0;
    format::Runtime rt = format::make_runtime(model);
    const auto false_misses = [&](std::uint32_t n) {
        rt.escape_points = n;
        return samples::held_out_metrics(rt, front, threads)
            .family[int(samples::Family::surface)]
            .false_miss_rate;
    };
    const double off = false_misses(0);
    std::uint32_t chosen = 0;
    for (std::uint32_t n = 1; n <= std::min(kMaxEscapePoints, model.desc.max_points); ++n) {
        if (false_misses(n) > off + kEscapeMissRise) break;
        chosen = n;
    }
    return chosen;
}

MeasureRays draw_measure_rays(const Run& run, const scene::Mesh& mesh, Candidate& c, MeshOutcome& out) {
    const auto t0 = Clock::now();
    run.report({mesh.name, "sample"});
    MeasureRays rays;
    std::vector<sampling::SampleExtras> extras;
    c.source->generate(run.opt.seed * 2 + 1 + 0x5bd1e995ull, run.preset.eval_rays, rays.held_out, &extras);
    rays.held_out_geometric_normals.resize(extras.size());
    for (std::size_t i = 0; i < extras.size(); ++i)
        rays.held_out_geometric_normals[i] = extras[i].geometric_normal;
    c.source->generate(run.opt.seed * 2 + 1 + 0x27d4eb2full, run.preset.validation_rays, rays.validation);
    c.source->generate(run.opt.seed * 2 + 1 + 0x165667b1ull, run.preset.eval_rays, rays.decision, &extras);
    for (std::size_t i = 0; i < rays.decision.size(); ++i)
        if (rays.decision[i].family == samples::Family::surface && extras[i].side == 1)
            rays.decision_front.push_back(rays.decision[i]);
    out.timings.add(Stage::sample, seconds_since(t0));
    if (run.preset.visual_check) {
        const auto tv = Clock::now();
        rays.decision_views = object_views(run, mesh, decision_view_seed(run.opt.seed));
        rays.held_out_views =
            object_views(run, mesh, held_out_view_seed(run.opt.view_seed.value_or(run.opt.seed)));
        out.timings.add(Stage::visual, seconds_since(tv));
    }
    return rays;
}

Trained train_rung(const Run& run, const scene::Mesh& mesh, Candidate& c, const format::ModelDesc& desc,
                   const voxelize::Occupancy& occ, const MeasureRays& rays, std::uint32_t steps,
                   RungRole role, std::span<const ValidationPoint> above, MeshOutcome& out) {
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
    bool images_in_reach = false;
    const bool may_refine = role == RungRole::first && p.sizing.explore_smaller &&
                            desc.grid_resolution * 2 <= p.sizing.max_grid_resolution;
    auto decide = [&](std::uint32_t step, std::uint32_t of) {
        const ValidationPoint& point = t.validation.back();
        if (may_refine) {
            t.finer_grid = finer_grid_reason(point, std::uint64_t(step) * t.config.batch_size, aim,
                                             p.early_abort, p.sizing);
            if (t.finer_grid) return false;
        }
        // Once the images were within reach of the gate, they decide at the end: the curve's
        // rays are not asked again (each asking renders the views).
        if (!images_in_reach)
            t.abandoned =
                early_abort_reasons(point, std::uint64_t(step) * t.config.batch_size, p.gate, p.early_abort);
        if (!t.abandoned.empty() && image_gate_in_reach(run, tr, rays, out)) {
            t.abandoned.clear();
            images_in_reach = true;
        }
        if (!t.abandoned.empty()) {
            t.abandoned_at = step;
            return false;
        }
        if (role == RungRole::smaller) {
            t.fell_behind = falls_behind(point, above, aim, p.target_stop, p.sizing);
            if (t.fell_behind) return false;
        }
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
    out.stats->mean_occupied_per_ray = st.rays_reaching ? st.entry_points / double(st.rays_reaching) : 0.0;
    out.stats->training_rays = out.stats->training_rays.value_or(0) + st.rays_drawn;
    out.timings.add(Stage::sample, st.generate_seconds);
    out.timings.add(Stage::prepare, st.prepare_seconds);
    out.timings.add(Stage::train, st.train.seconds - validation_seconds);
    out.timings.add(Stage::validate, validation_seconds);
    t.model = tr.export_model("{}");
    if (p.prune_inactive) {
        const auto tp = Clock::now();
        t.pruned = remove_inactive_neurons(t.model, active_neurons(t.model, rays.validation, run.threads));
        out.timings.add(Stage::prune, seconds_since(tp));
    }
    t.seconds = seconds_since(t0);
    return t;
}

HeldOut evaluate(const Run& run, const scene::Mesh& mesh, const format::ModelData& model, const Trained& t,
                 const MeasureRays& rays, std::optional<render::ObjectFlip> flip, samples::Metrics& decided,
                 MeshOutcome& out) {
    const auto t0 = Clock::now();
    run.report({mesh.name, "evaluate"});
    const format::Runtime rt = format::make_runtime(model);
    decided = samples::held_out_metrics(rt, rays.decision, run.threads);
    HeldOut h;
    h.rays = rays.held_out.size();
    h.metrics = samples::held_out_metrics(rt, rays.held_out, run.threads, rays.held_out_geometric_normals);
    std::vector<std::string> training;
    if (t.stream.train.diverged) training.push_back(t.stream.train.message);
    for (const RuleMiss& why : t.abandoned)
        training.push_back("training given up at step " + std::to_string(t.abandoned_at) + " of " +
                           std::to_string(t.config.steps) + ": " + describe(why));
    h.gate = gate_verdict(decided, image_error(flip), std::move(training), run.preset.gate);
    h.flip = flip;
    out.timings.add(Stage::evaluate, seconds_since(t0));
    return h;
}

CandidateRecord candidate_record(const Option& o, const Trained& t, std::size_t of) {
    const format::ModelDesc& d = o.model.desc;
    const samples::FamilyMetrics& p = o.held_out.metrics.pooled;
    CandidateRecord c;
    c.log2_table_size = d.log2_table_size;
    c.grid_resolution = d.grid_resolution;
    c.hidden_width = d.hidden_width;
    c.grid = d.grid_encoding;
    c.bytes = o.bytes;
    c.resident_bytes = o.resident;
    c.steps = t.stream.train.steps;
    c.steps_planned = t.config.steps;
    c.seconds = o.seconds;
    c.visibility = p.visibility_accuracy;
    c.distance_pct = p.distance_median_pct;
    c.normal_deg = p.normal_median_deg;
    c.decided_visibility = o.decided.pooled.visibility_accuracy;
    c.decided_distance_pct = o.decided.pooled.distance_median_pct;
    c.decided_normal_deg = o.decided.pooled.normal_median_deg;
    c.gate_passed = o.held_out.gate.passed;
    c.target_met = o.target_met;
    c.memory_rule_passed = o.memory_ok;
    c.outcome = o.outcome;
    c.of = of;
    // The curve is the training's: recorded once, with the rung's fp16 export.
    if (d.grid_encoding == format::GridEncoding::fp16) c.validation = t.validation;
    if (t.target_met_at) c.stop = StopKind::target_met;
    if (!t.abandoned.empty()) c.stop = StopKind::given_up, c.stop_why = describe(t.abandoned.front());
    if (t.fell_behind) c.stop = StopKind::given_up, c.stop_why = describe(*t.fell_behind);
    c.pruned_neurons = t.pruned;
    c.flip = o.flip;
    return c;
}

Option measure_option(const Run& run, const scene::Mesh& mesh, const Candidate& c, std::size_t rung,
                      format::ModelData model, const Trained& t, const MeasureRays& rays, MeshOutcome& out) {
    const auto t0 = Clock::now();
    Option o;
    o.rung = rung;
    o.model = std::move(model);
    auto bytes = format::serialize(o.model);
    o.bytes = bytes ? bytes->size() : 0;
    o.resident = format::resident_bytes(o.model);
    if (bytes && rays.decision_views) {
        const auto tv = Clock::now();
        if (auto f = rays.decision_views->compare(*bytes)) o.flip = *f;
        out.timings.add(Stage::visual, seconds_since(tv));
    }
    o.held_out = evaluate(run, mesh, o.model, t, rays, o.flip, o.decided, out);
    o.target_met =
        o.held_out.gate.passed &&
        target_misses(o.decided.pooled, image_error(o.flip), run.opt.target, run.preset.gate.accept).empty();
    o.memory_ok = bytes && memory_rule_failure(run, c, o.resident).empty();
    o.seconds = seconds_since(t0);
    return o;
}

// The occupancy grid at twice desc's resolution (desc updated), recording why in `out`'s
// reasons; nothing when it cannot be built.
std::optional<voxelize::Occupancy> refine_grid(const Run& run, const Candidate& c, format::ModelDesc& desc,
                                               const std::string& why, MeshOutcome& out) {
    const auto t0 = Clock::now();
    voxelize::Options vopt;
    vopt.threads = run.threads;
    auto occ = voxelize::voxelize(c.view, c.box, desc.grid_resolution * 2, vopt);
    out.timings.add(Stage::voxelize, seconds_since(t0));
    if (!occ) return std::nullopt;
    const std::string from = std::to_string(desc.grid_resolution);
    desc.grid_resolution *= 2;
    const std::string to = std::to_string(desc.grid_resolution);
    out.reasons.push_back("grid " + from + "^3: " + why + "; trained again at " + to + "^3");
    return std::move(*occ);
}

std::uint32_t first_rung_log2(const Preset& p, std::uint32_t largest) {
    const std::uint32_t first = p.sizing.first_log2_table_size;
    if (!p.sizing.explore_smaller || first == 0) return largest;
    return std::min(largest, std::max(first, p.classify.min_log2_table_size));
}

namespace {

std::string climb_reason(const Option& o, const Target& aim) {
    const samples::FamilyMetrics& m = o.decided.pooled;
    char buf[240];
    std::snprintf(buf, sizeof buf,
                  "2^%u rows ended near the target (decision rays: %.2f %% visibility, %.2f %% distance, "
                  "%.1f deg normal; target %.2f %%, %.2f %%, %.1f deg); trained again at 2^%u",
                  o.model.desc.log2_table_size, 100 * m.visibility_accuracy, m.distance_median_pct,
                  m.normal_median_deg, 100 * aim.visibility, aim.distance_pct, aim.normal_deg,
                  o.model.desc.log2_table_size + 1);
    return buf;
}

}  // namespace

Sized size_to_target(const Run& run, const scene::Mesh& mesh, Candidate& c, const voxelize::Occupancy& occ,
                     const MeasureRays& rays, MeshOutcome& out) {
    Sized sized;
    const Preset& p = run.preset;
    const Target aim = effective_target(run.opt.target, p.gate);
    const std::uint32_t largest = c.desc.log2_table_size;  // triage's: the memory rule's cap
    format::ModelDesc desc = c.desc;
    desc.log2_table_size = first_rung_log2(p, largest);
    std::uint32_t budget = p.train.steps;      // steps left to the rungs of this budget
    std::optional<voxelize::Occupancy> finer;  // the grid of a finer-grid rung
    RungRole role = RungRole::first;
    for (;;) {
        // The curve of the rung above, read by train_rung only (before rungs grows).
        const std::span<const ValidationPoint> above =
            role == RungRole::smaller ? std::span<const ValidationPoint>(sized.rungs.back().validation)
                                      : std::span<const ValidationPoint>();
        Trained trained =
            train_rung(run, mesh, c, desc, finer ? *finer : occ, rays, budget, role, above, out);
        if (trained.finer_grid) {
            // The first size at this grid cannot reach the target: start again, twice as fine.
            if (auto g = refine_grid(run, c, desc, describe(*trained.finer_grid), out)) {
                finer = std::move(*g);
                continue;
            }
            trained.finer_grid.reset();  // voxelization failed: this training is what there is
        }
        sized.rungs.push_back(std::move(trained));
        const std::size_t rung = sized.rungs.size() - 1;
        const Trained& t = sized.rungs[rung];
        const std::size_t first = sized.options.size();
        add_options(run, mesh, c, rung, rays, sized, out);
        bool met = false, fits = false;  // some option meets the target / beats the BVH
        for (std::size_t i = first; i < sized.options.size(); ++i) {
            met = met || sized.options[i].target_met;
            fits = fits || sized.options[i].memory_ok;
        }
        const std::uint32_t used = t.stream.train.steps;
        budget -= std::min(budget, used);
        if (!p.sizing.explore_smaller) break;
        // Up: a rung that ended near the target, trained to its end (not given up), and
        // never after a smaller rung (going down means the rung above met it).
        // The rung's fp16 option, its training's own export, is its first (rung_encodings).
        const Option& trained_option = sized.options[first];
        if (!met && role != RungRole::smaller && desc.log2_table_size < largest && t.abandoned.empty() &&
            near_target(trained_option.decided.pooled, aim, p.sizing)) {
            out.reasons.push_back(climb_reason(trained_option, aim));
            ++desc.log2_table_size;
            budget = p.train.steps;
            role = RungRole::larger;
            continue;
        }
        // Down: only after this rung met the target (or could not beat the BVH, the estimate
        // having been too hopeful), never after climbing, and only with enough steps left.
        if (role == RungRole::larger || (!met && fits) ||
            double(budget) < p.sizing.descend_budget_fraction * double(used) ||
            desc.log2_table_size <= p.classify.min_log2_table_size)
            break;
        --desc.log2_table_size;
        role = RungRole::smaller;
    }
    choose_option(sized);
    return sized;
}

void add_options(const Run& run, const scene::Mesh& mesh, const Candidate& c, std::size_t rung,
                 const MeasureRays& rays, Sized& sized, MeshOutcome& out) {
    const Trained& t = sized.rungs[rung];
    for (const format::GridEncoding e : rung_encodings(run.preset)) {
        format::ModelData model = t.model;
        if (e == format::GridEncoding::u8_affine) {
            auto quantized = format::quantize_model(t.model);
            if (!quantized) continue;  // cannot happen for a valid fp16 export; then fp16 only
            model = std::move(*quantized);
        }
        Option o = measure_option(run, mesh, c, rung, std::move(model), t, rays, out);
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
        return !sized.chosen || sized.options[i].resident < sized.options[*sized.chosen].resident;
    };
    auto passes = [&](const Option& o) { return o.memory_ok && o.held_out.gate.passed; };
    CandidateOutcome why = CandidateOutcome::chosen_meets_target;
    for (std::size_t i = 0; i < n; ++i)
        if (passes(sized.options[i]) && sized.options[i].target_met && smaller(i)) sized.chosen = i;
    if (!sized.chosen) {
        // No option meets the target: the most accurate model, the largest table trained
        // (the first such rung), ships if it passes the gate, in its smallest encoding that does.
        why = CandidateOutcome::chosen_passes_gate;
        std::size_t best = 0;
        for (std::size_t r = 1; r < sized.rungs.size(); ++r)
            if (sized.rungs[r].model.desc.log2_table_size > sized.rungs[best].model.desc.log2_table_size)
                best = r;
        for (std::size_t i = 0; i < n; ++i)
            if (sized.options[i].rung == best && passes(sized.options[i]) && smaller(i)) sized.chosen = i;
    }
    for (std::size_t i = 0; i < n; ++i) {
        Option& o = sized.options[i];
        if (sized.chosen == i)
            o.outcome = why;
        else if (!o.held_out.gate.passed)
            o.outcome = CandidateOutcome::fails_gate;
        else if (!o.memory_ok)
            o.outcome = CandidateOutcome::fails_memory_rule;
        else if (o.target_met)
            o.outcome = CandidateOutcome::smaller_meets_target;
        else
            o.outcome = CandidateOutcome::misses_target;
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
          {"box_min", c.box.min},
          {"box_max", c.box.max},
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
        {"metrics", held_out_json(o.held_out)},
        {"extensions", {{"lsnif_convert_key", key}}}};
}

format::Result<std::vector<std::uint8_t>> encode_asset(Option& o, const json& metadata) {
    o.model.metadata_json = metadata.dump(2);
    return format::serialize(o.model);
}

std::string option_summary(const Option& o) {
    const format::ModelDesc& d = o.model.desc;
    return "2^" + std::to_string(d.log2_table_size) + " rows, " +
           grid_encoding_name(std::uint32_t(d.grid_encoding)) + " grid, " + std::to_string(o.resident) +
           " bytes held in memory (" + std::to_string(o.bytes) + " in the file)";
}

std::string write_asset(const Run& run, const scene::Mesh& mesh, std::span<const std::uint8_t> bytes,
                        const fs::path& asset, MeshOutcome& out) {
    const auto t0 = Clock::now();
    run.report({mesh.name, "write"});
    std::error_code ec;
    fs::create_directories(run.outdir, ec);
    const format::Error e = format::write_bytes_atomically(asset.string(), bytes);
    out.timings.add(Stage::write, seconds_since(t0));
    return e ? e.message : std::string();
}

void convert_candidate(const Run& run, Triaged& p, std::vector<std::string>& errors) {
    const scene::Mesh& mesh = *p.mesh;
    const std::string& source = p.source;
    MeshOutcome& out = p.out;
    Candidate& c = *p.candidate;
    if (run.opt.dry_run) {
        out.settle(Decision::planned);  // the plan only: no sampling, training or files
        return;
    }
    const std::string key = asset_key(run, mesh, c.desc);
    const std::string file = hex16(fnv1a64(key)) + ".lsnif";
    const fs::path asset = run.outdir / file;
    if (auto previous = reusable_metrics(asset, key)) {
        const auto bytes = format::read_file_bytes(asset.string());
        auto images = bytes ? held_out_images(run, mesh, nullptr, *bytes, out) : std::nullopt;
        return shipped(run, std::move(*previous), std::move(images), file, asset, true, out);
    }

    const MeasureRays rays = draw_measure_rays(run, mesh, c, out);
    Sized sized = size_to_target(run, mesh, c, *p.occupancy, rays, out);
    for (const Option& o : sized.options)
        out.candidates.push_back(candidate_record(o, sized.rungs[o.rung], sized.options.size()));
    // The chosen option, or the first rung's fp16 model when none may ship.
    Option& o = sized.options[sized.chosen.value_or(0)];
    const Trained& t = sized.rungs[o.rung];
    out.validation = t.validation;
    if (t.target_met_at) out.stopped_early = StoppedEarly{t.target_met_at, t.config.steps};
    if (!sized.chosen) return below_gate(o.held_out, !t.abandoned.empty(), out);
    out.reasons.push_back(option_summary(o) + ": " + choice_text(o.outcome, sized.options.size()));
    o.held_out.escape_points = choose_escape_points(o.model, rays.decision_front, run.threads);
    auto bytes = encode_asset(o, asset_metadata(run, source, mesh, c, o, t, key));
    if (!bytes) {
        errors.push_back(source + ": mesh '" + mesh.name + "': " + bytes.error().message);
        out.settle(Decision::encode_failed, "the asset could not be encoded: " + bytes.error().message);
        return;
    }
    if (std::string why = memory_rule_failure(run, c, format::resident_bytes(o.model)); !why.empty()) {
        out.held_out = o.held_out;
        out.settle(Decision::asset_not_smaller, why);
        return;
    }
    auto images = held_out_images(run, mesh, rays.held_out_views.get(), *bytes, out);
    if (std::string err = write_asset(run, mesh, *bytes, asset, out); !err.empty()) {
        errors.push_back(source + ": mesh '" + mesh.name + "': " + err);
        out.settle(Decision::write_failed, "the asset could not be written: " + err);
        return;
    }
    shipped(run, o.held_out, std::move(images), file, asset, false, out);
}

AssetFile asset_file(const fs::path& asset, const std::string& file, std::optional<bool> reused) {
    AssetFile f{file, 0, 0, reused};
    const auto bytes = format::read_file_bytes(asset.string());
    if (!bytes) return f;
    f.bytes = bytes->size();
    if (auto model = format::read_model(*bytes)) f.resident_bytes = format::resident_bytes(*model);
    return f;
}

std::optional<render::ObjectFlip> held_out_images(const Run& run, const scene::Mesh& mesh,
                                                  const render::ObjectViews* views,
                                                  std::span<const std::uint8_t> asset, MeshOutcome& out) {
    if (!run.preset.visual_check) return std::nullopt;
    const auto t0 = Clock::now();
    std::unique_ptr<render::ObjectViews> made;
    if (!views)
        views = (made = object_views(run, mesh, held_out_view_seed(run.opt.view_seed.value_or(run.opt.seed))))
                    .get();
    std::optional<render::ObjectFlip> flip;
    if (views)
        if (auto f = views->compare(asset)) flip = *f;
    out.timings.add(Stage::visual, seconds_since(t0));
    return flip;
}

void shipped(const Run& run, HeldOut metrics, std::optional<render::ObjectFlip> images,
             const std::string& file, const fs::path& asset, bool reused, MeshOutcome& out) {
    // The target's verdict on what is reported: the held-out rays and the held-out views.
    out.target =
        TargetVerdict{run.opt.target, describe(target_misses(metrics.metrics.pooled, image_error(images),
                                                             run.opt.target, run.preset.gate.accept))};
    out.held_out_images = std::move(images);
    out.held_out = std::move(metrics);
    out.asset = asset_file(asset, file, reused);
    out.settle(Decision::shipped);
}

void below_gate(const HeldOut& metrics, bool abandoned, MeshOutcome& out) {
    out.held_out = metrics;
    for (const std::string& r : metrics.gate.reasons) out.reasons.push_back("gate: " + r);
    if (abandoned)
        out.settle(Decision::decided_early, "decided early from the validation curve: stays BVH");
    else
        out.settle(Decision::below_gate, "held-out accuracy below the gate: stays BVH");
}

}  // namespace stages

std::uint64_t decision_view_seed(std::uint64_t seed) {
    return base::mix64(seed ^ 0x6465636973696f6eull);  // "decision"
}

std::uint64_t held_out_view_seed(std::uint64_t view_seed) {
    return base::mix64(view_seed ^ 0x68656c642d6f7574ull);  // "held-out"
}

}  // namespace lsnif::converter
