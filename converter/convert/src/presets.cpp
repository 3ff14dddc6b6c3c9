// The presets and the options applied to them (convert.hpp, convert_stages.hpp).
#include <lsnif/converter/convert.hpp>
#include "convert_stages.hpp"

namespace lsnif::converter {

using nlohmann::json;
using namespace stages;

std::vector<std::string> preset_names() {
    return {"default", "fast", "quality", "smoke"};
}

namespace {

// The model and training an asset is converted with unless a preset or an option says
// otherwise, every value written out. docs/architecture.md §3 describes the model;
// docs/model.md gives the reason for each choice, in the sections named here, and points to
// the measurements behind it.
Preset shipped_default() {
    Preset p;
    p.name = "default";
    format::ModelDesc& m = p.model;      // its box and material count are the mesh's
    m.grid_resolution = 64;              // "A 64³ grid"
    m.max_points = 14;                   // "Coarse levels": fewer slots, as accurate
    m.level_resolution = {16, 32, 128};  // "Coarse levels": two dense coarse levels and one hashed
    m.features_per_level = 3;
    m.log2_table_size = 17;  // the largest rung; sizing tries smaller tables ("Sizing to the target")
    m.hash_primes = {1u, 2654435761u, 805459861u};  // the spatial hash of instant-ngp (Müller et al. 2022)
    m.hidden_width = {128, 128};
    m.activation = 0;  // ReLU
    m.distance_encoding = LSNIF_DISTANCE_FIRST_ENTRY_DIAGONAL;
    m.grid_encoding = format::GridEncoding::fp16;  // each rung is also measured in 8 bits
    m.ray_inputs = format::kRayInputDirection | format::kRayInputEntryOffsets;  // "Ray inputs"
    trainer::TrainConfig& t = p.train;  // its threads, seed and arithmetic are the options'
    t.steps = 1200;  // at most: training stops at the target ("Validation curve and deciding early")
    t.batch_size = 1u << 13;
    t.grid_adam = {2e-2f, 0.9f, 0.99f, 1e-10f, 0.0f};  // "Optimizer"
    t.mlp_adam = {1e-2f, 0.9f, 0.99f, 1e-10f, 1e-6f};
    t.decay_start = 0.6f;  // "Coarse levels": the schedule
    t.final_lr_fraction = 0.1f;
    t.huber_delta = 0.01f;
    t.normal_loss = trainer::NormalLoss::chord;  // "The normal loss"
    t.normal_chord_epsilon = 0.01f;
    t.grad_clip_norm = 10.0f;
    t.loss = {2.0f, 4.0f, 0.7f,
              0.1f};  // visibility ("A 64³ grid"), distance, normal ("The normal loss"), material
    t.divergence_factor = 8.0f;
    t.snapshot_interval = 50;
    t.max_rollbacks = 8;
    p.train_rays = 1u << 23;  // distinct rays, streamed in rounds ("Training data in rounds")
    p.train_chunk_rays = 1u << 20;
    p.train_window_chunks = 2;
    p.eval_rays = 1u << 16;
    p.validation_rays = 1u << 13;
    p.validation_checks = 10;
    p.prune_inactive = true;  // "Inactive neurons"
    p.classify = {2000, 2.0, BvhYardstick::embree, 15};
    p.gate = {0.95, 0.90, 2.0, 30.0, 100};
    p.early_abort = {1500000, 0.05, 20.0, 0.35};
    p.target_stop = {2, 0.003, 0.9, 1.0};
    p.sizing = {true, true, 0.01};
    return p;
}

}  // namespace

bool find_preset(const std::string& name, Preset& p) {
    p = shipped_default();
    p.name = name;
    if (name == "default") return true;
    // The same model, trained for more or fewer rays per step and steps.
    if (name == "fast") {
        p.train.batch_size = 1u << 14;
        p.train.steps = 300;
        p.train_rays = 1u << 21;
        return true;
    }
    if (name == "quality") {
        p.train.batch_size = 1u << 12;
        p.train.steps = 4800;
        return true;
    }
    if (name == "smoke") {
        // A pipeline check in seconds (tests, CI): a small model and a lenient gate that only
        // rejects an untrained network. Not for shipping assets.
        p.model.grid_resolution = 16;
        p.model.max_points = 8;
        p.model.level_resolution = {32, 64};
        p.model.features_per_level = 2;
        p.model.log2_table_size = 12;
        p.model.hidden_width = {32, 32};
        p.train.batch_size = 2048;
        p.train.steps = 250;
        p.train_rays = 1u << 15;
        p.train_chunk_rays = 1u << 14;  // two rounds: exercises the streaming path
        p.eval_rays = 1u << 13;
        p.classify.min_triangles = 100;
        p.gate = {0.75, 0.6, 25.0, 90.0, 100};
        // Smaller views with fewer AO rays: the visual check's stages run, at a fifth of the
        // default's pixels and rays.
        p.views.width = 96;
        p.views.height = 72;
        p.views.ao_samples = 4;
        return true;
    }
    return false;
}

namespace stages {

bool resolve_preset(const ConvertOptions& opt, Preset& preset, std::string& error) {
    if (!find_preset(opt.preset, preset)) {
        std::string names;
        for (const auto& n : preset_names()) names += (names.empty() ? "" : ", ") + n;
        error = "unknown preset '" + opt.preset + "' (known: " + names + ")";
        return false;
    }
    if (opt.gate_min_visibility >= 0) preset.gate.min_visibility = opt.gate_min_visibility;
    if (opt.gate_max_flip >= 0) preset.gate.max_flip = opt.gate_max_flip;
    if (opt.accept) preset.gate.accept = *opt.accept;
    if (opt.bvh_yardstick) preset.classify.yardstick = *opt.bvh_yardstick;
    if (opt.min_memory_ratio > 0) preset.classify.min_memory_ratio = opt.min_memory_ratio;
    if (preset.gate.accept == Acceptance::images && !preset.visual_check) {
        error = "--accept images: the preset '" + preset.name + "' renders no views to judge images by";
        return false;
    }
    if (opt.steps > 0) preset.train.steps = opt.steps;
    if (opt.batch_size > 0) preset.train.batch_size = opt.batch_size;
    if (opt.log2_table_size > 0) preset.model.log2_table_size = opt.log2_table_size;
    if (opt.first_log2_table_size > 0) preset.sizing.first_log2_table_size = opt.first_log2_table_size;
    if (opt.max_points > 0) preset.model.max_points = opt.max_points;
    if (opt.grid_resolution > 0) preset.model.grid_resolution = opt.grid_resolution;
    if (opt.max_grid_resolution > 0) preset.sizing.max_grid_resolution = opt.max_grid_resolution;
    if (opt.hidden_width > 0)
        for (auto& w : preset.model.hidden_width) w = opt.hidden_width;
    if (opt.no_ray_inputs) preset.model.ray_inputs = 0;
    if (opt.fixed_model) {
        preset.sizing.explore_smaller = false;
        preset.sizing.quantize = false;
        preset.target_stop.consecutive = 0;
    }
    if (opt.no_give_up) preset.early_abort.min_samples = std::numeric_limits<std::uint64_t>::max();
    if (opt.keep_inactive) preset.prune_inactive = false;
    preset.train.mlp_precision = opt.arithmetic == Arithmetic::machine ? trainer::MlpPrecision::automatic
                                                                       : trainer::MlpPrecision::fp32;
    return true;
}

}  // namespace stages

}  // namespace lsnif::converter
