// The stages of `lsnif convert` (convert.cpp), one function each, in pipeline order:
//   resolve_preset; per mesh, triage_mesh: classify -> voxelize_mesh -> worth_an_lsnif and the
//   BVH's bytes; then convert_meshes, per candidate in conversion_order() until the memory
//   budget is met, convert_candidate: asset_key -> (reusable_metrics -> shipped |
//   draw_measure_rays -> size_to_target [train_rung (-> active_neurons -> remove_inactive_neurons)
//   -> gate per rung, choose_option] ->
//   asset_metadata -> encode_asset -> memory_rule_failure -> write_asset -> shipped);
//   finally scene_memory, manifest_json -> write_manifest (manifest.hpp).
// A stage that decides the mesh stays BVH returns nothing (or false) and settles the mesh's
// MeshOutcome (lsnif/converter/outcome.hpp) with the decision and its reason. Private to
// lsnif::convert: exposed to its own tests only, so that each stage is tested on its own
// (tests/convert/test_convert_stages.cpp); not installed, not an API.
#pragma once

#include <lsnif/converter/convert.hpp>
#include <lsnif/converter/outcome.hpp>
#include <lsnif/format/container.hpp>
#include <lsnif/mesh/mesh.hpp>
#include <lsnif/render/object_views.hpp>
#include <lsnif/samples/held_out.hpp>
#include <lsnif/samples/sample.hpp>
#include <lsnif/sampling/sampling.hpp>
#include <lsnif/scene/scene.hpp>
#include <lsnif/trainer/streamed.hpp>
#include <lsnif/voxelize/voxelize.hpp>

#include <nlohmann/json.hpp>

#include <algorithm>
#include <array>
#include <filesystem>
#include <memory>
#include <optional>
#include <span>
#include <string>
#include <vector>

namespace lsnif::cache {
class Cache;
}

namespace lsnif::converter::stages {

using nlohmann::json;
namespace fs = std::filesystem;

// The model's description as the asset's metadata and asset keys record it (records.cpp).
json model_json(const format::ModelDesc& d);

// What a run shares between its meshes.
struct Run {
    const ConvertOptions& opt;
    Preset preset;
    std::uint32_t threads;
    fs::path outdir;
    ConvertProgress progress;
    std::shared_ptr<const cache::Cache> cache;  // --cache; null without
    void report(const ProgressEvent& e) const {
        if (progress) progress(e);
    }
    bool forced(const std::vector<std::string>& names, const std::string& mesh) const {
        return std::find(names.begin(), names.end(), mesh) != names.end();
    }
};

// The view of a scene mesh that every stage takes (borrows `m`'s arrays).
inline mesh::MeshView view_of(const scene::Mesh& m) {
    return {m.positions, m.indices, m.normals, m.triangle_materials};
}

// A mesh that classification kept as a candidate for an LSNIF.
struct Candidate {
    mesh::MeshView view;  // of the scene mesh (view_of), the one every later stage reads
    mesh::Box box;
    format::ModelDesc desc;  // the preset's model, box set, tables sized to the mesh
    std::unique_ptr<sampling::EmbreeSource> source;
    BvhBytes bvh;  // the mesh's BVH on both yardsticks
    bool forced = false;
};

// What a mesh's models are measured on, made once and shared by every rung of the ladder,
// all apart from the training rays: validation rays (the curve that decides during
// training), decision rays (the gate, the target and the choice between options), held-out
// rays that no decision sees (what the manifest reports), and two sets of the object's views
// with their reference renders (Preset::visual_check; null when off): the decision views,
// which the gate, the target and the choice read, and the held-out views, drawn apart, on
// which the shipped asset's image error is reported.
struct MeasureRays {
    std::vector<samples::Sample> validation;
    std::vector<samples::Sample> decision;
    // The decision rays that leave the surface on its front side (family surface, side +1):
    // the rays a renderer's shadow, AO and reflection rays are like; choose_escape_points reads
    // them.
    std::vector<samples::Sample> decision_front;
    std::vector<samples::Sample> held_out;
    std::vector<std::array<float, 3>> held_out_geometric_normals;
    std::unique_ptr<render::ObjectViews> decision_views;
    std::unique_ptr<render::ObjectViews> held_out_views;
};

// One rung of the ladder, trained.
struct Trained {
    format::ModelData model;  // model.desc is the rung's
    trainer::TrainConfig config;
    trainer::StreamedResult stream;
    std::vector<ValidationPoint> validation;  // the curve, one point per check
    // Why training was given up at step `abandoned_at` (EarlyAbort); empty when it ran to the end.
    std::vector<RuleMiss> abandoned;
    std::uint32_t abandoned_at = 0;
    // The step at which training stopped because the validation curve met the target
    // (TargetStop); 0 when it did not.
    std::uint32_t target_met_at = 0;
    // Why a smaller rung was given up against the larger rung's curve (falls_behind).
    std::optional<RuleMiss> fell_behind;
    // Why the first rung stopped for a finer grid (finer_grid_reason); none otherwise.
    std::optional<RuleMiss> finer_grid;
    double seconds = 0;  // wall time of this rung: drawing, preparing, training, validating, pruning
    // Hidden neurons removed from `model` per layer (Preset::prune_inactive); empty when off.
    std::vector<std::uint32_t> pruned;
};

// A model that may ship: a trained rung's fp16 export, or its 8-bit quantization.
struct Option {
    std::size_t rung = 0;      // into Sized::rungs: the training it comes from
    format::ModelData model;   // metadata filled only for the chosen one (encode_asset)
    samples::Metrics decided;  // on the decision rays: what the gate, the target and the choice read
    HeldOut held_out;          // on the held-out rays, reported; its gate is the decided verdict
    std::optional<render::ObjectFlip> flip;  // the visual check on MeasureRays::decision_views, when on
    std::uint64_t bytes = 0;                 // serialized without metadata
    std::uint64_t resident = 0;              // held once opened (format::resident_bytes), without metadata
    bool target_met = false;                 // passes the gate and meets --target on held-out rays
    bool memory_ok = false;  // held in memory, beats the BVH by ClassifyRule::min_memory_ratio (or forced)
    double seconds = 0;      // measuring (and, for the fp16 option, training) it
    CandidateOutcome outcome = CandidateOutcome::misses_target;  // chosen and why, or why not (choose_option)
};

// Every rung tried for a mesh, in the order trained, and every option they gave.
struct Sized {
    std::vector<Trained> rungs;
    std::vector<Option> options;        // per rung: fp16, then u8_affine (Sizing::quantize)
    std::optional<std::size_t> chosen;  // into options; none when nothing may ship
};

// The object's views drawn from `seed` (Preset::views), with their reference renders; null
// when Embree cannot build them (classification built the same mesh: short of memory only).
std::unique_ptr<render::ObjectViews> object_views(const Run& run, const scene::Mesh& mesh,
                                                  std::uint64_t seed);

// The escape rule's limit for `model` (docs/model.md "The escape rule"): the largest N of
// 1..kMaxEscapePoints at which the rule raises the false-miss rate of `front` (rays leaving
// the surface on its front side, with their mesh answers) by at most kEscapeMissRise over the
// rule off, else 0. The rate only grows with N (each N forces a superset of rays to miss).
// At most 3: at 4 the renders' ambient occlusion lightens in creases that the rays' rates
// hardly show.
inline constexpr std::uint32_t kMaxEscapePoints = 3;
inline constexpr double kEscapeMissRise = 0.0025;
std::uint32_t choose_escape_points(const format::ModelData& model, std::span<const samples::Sample> front,
                                   std::uint32_t threads);

// The validation point of a model at `step`: pooled metrics of `rays` through the reader's
// forward pass (format::intersect on the fp16 export), as the manifest records it.
ValidationPoint validation_point(std::uint32_t step, const format::ModelData& model,
                                 std::span<const samples::Sample> rays, std::uint32_t threads);

// The preset with the command line's overrides applied; false (and `error`) for an
// unknown preset name.
bool resolve_preset(const ConvertOptions& opt, Preset& preset, std::string& error);

// Why a box cannot be modelled in single precision (kMinModelExtent..kMaxModelExtent), or
// an empty string.
std::string range_problem(const mesh::Box& box);

// Classify: bounds, float range, the BVH on both yardsticks, the table size whose asset,
// held in memory, beats the yardstick's BVH, and the geometry statistics. Returns nothing when the mesh stays
// simple (decision settled). `forced_complex` (--complex) skips the table sizing. Contract: `out.stats` is
// set whenever Embree built the mesh.
std::optional<Candidate> classify(const Run& run, const scene::Mesh& mesh, bool forced_complex,
                                  MeshOutcome& out);

// Voxelize: the conservative occupancy grid of the candidate's model.
std::optional<voxelize::Occupancy> voxelize_mesh(const Run& run, const scene::Mesh& mesh, const Candidate& c,
                                                 MeshOutcome& out);

// The memory rule: an LSNIF's resident bytes must beat the yardstick's BVH by
// min_memory_ratio (unless forced). Records the comparison; false when the mesh stays simple
// (decision settled).
bool worth_an_lsnif(const Run& run, const scene::Mesh& mesh, const Candidate& c, MeshOutcome& out);

// The asset's content key: geometry and every setting that changes the weights. The file
// is named by its hash, so an unchanged mesh finds its asset again.
std::string asset_key(const Run& run, const scene::Mesh& mesh, const format::ModelDesc& desc);

// Reuse: the held-out metrics of an existing asset written for exactly this key (as its
// metadata records them), or nothing (absent, unreadable, another key, or metrics this
// version does not write).
std::optional<HeldOut> reusable_metrics(const fs::path& asset, const std::string& key);

// Draws the held-out and validation rays (seeded by the run's seed, not by the rung) and, with
// Preset::visual_check, renders the object's reference views (none when Embree cannot build
// them: classification built the same mesh, so that does not happen short of memory).
MeasureRays draw_measure_rays(const Run& run, const scene::Mesh& mesh, Candidate& c, MeshOutcome& out);

// Where a rung stands in the search (Sizing): the first one trained, one below a rung that met
// the target, or one above a rung that narrowly missed it.
enum class RungRole : std::uint8_t { first, smaller, larger };

// Trains `desc` (a rung: the candidate's model with another table size) for at most `steps`
// steps on streamed rays, checking the validation curve `validation_checks` times: it gives
// up when the gate is out of reach (EarlyAbort) or when, as a smaller rung, it falls behind
// `above` (the curve of the rung above it), and stops once the target is met (TargetStop).
// Only the first rung may ask for a finer grid (Trained::finer_grid). Timings and training
// statistics accumulate in `out`.
Trained train_rung(const Run& run, const scene::Mesh& mesh, Candidate& c, const format::ModelDesc& desc,
                   const voxelize::Occupancy& occ, const MeasureRays& rays, std::uint32_t steps,
                   RungRole role, std::span<const ValidationPoint> above, MeshOutcome& out);

// Prune, part 1 (docs/model.md "Inactive neurons"): per hidden layer of `model`, whether
// each neuron's ReLU output is positive for at least one of `rays` that reaches the network,
// through the reader's walk, encoding and fp32 layers. The same for any `threads`.
std::vector<std::vector<std::uint8_t>> active_neurons(const format::ModelData& model,
                                                      std::span<const samples::Sample> rays,
                                                      std::uint32_t threads);

// Prune, part 2: removes from `model` every hidden neuron that `active` (active_neurons of
// this model) marks inactive: its row of the layer's weights, its bias and its column of the
// next layer's weights; a layer keeps at least one neuron. For a ray on which every removed
// neuron outputs zero, the fp32 forward pass gives the same outputs before and after (the
// dropped terms were zeros; the order of the others is unchanged). Returns the neurons
// removed per hidden layer.
std::vector<std::uint32_t> remove_inactive_neurons(format::ModelData& model,
                                                   const std::vector<std::vector<std::uint8_t>>& active);

// Evaluate: `model` (`t`'s fp16 export or its quantization) on the decision rays (into
// `decided`) and on the held-out rays, and the gate's verdict (gate_verdict: the decided
// metrics, `flip`, and `t`'s own verdicts: divergence, giving up) recorded with the
// held-out metrics.
HeldOut evaluate(const Run& run, const scene::Mesh& mesh, const format::ModelData& model, const Trained& t,
                 const MeasureRays& rays, std::optional<render::ObjectFlip> flip, samples::Metrics& decided,
                 MeshOutcome& out);

// The manifest's record of one option of `of`: size, encoding, bytes, steps, seconds,
// held-out metrics, verdicts, outcome, why training stopped and (fp16 option) the rung's curve.
CandidateRecord candidate_record(const Option& o, const Trained& t, std::size_t of);

// Measures `model` (from rung `rung`, trained as `t`) as an option: held-out metrics, the
// target, serialized bytes and the memory rule.
Option measure_option(const Run& run, const scene::Mesh& mesh, const Candidate& c, std::size_t rung,
                      format::ModelData model, const Trained& t, const MeasureRays& rays, MeshOutcome& out);

// Measures rung `rung` of `sized` in every encoding of rung_encodings() and appends the
// options to sized.options.
void add_options(const Run& run, const scene::Mesh& mesh, const Candidate& c, std::size_t rung,
                 const MeasureRays& rays, Sized& sized, MeshOutcome& out);

// The grid encodings each rung is measured in: fp16, and u8_affine when Sizing::quantize.
std::vector<format::GridEncoding> rung_encodings(const Preset& p);

// "2^17 rows, u8_affine grid, 855000 bytes": the option in the mesh's reasons.
std::string option_summary(const Option& o);

// The occupancy grid of `c` at twice desc's resolution for a finer-grid rung (desc updated),
// the reason (finer_grid_reason's `why`) appended to out's reasons; nothing when it cannot be
// built.
std::optional<voxelize::Occupancy> refine_grid(const Run& run, const Candidate& c, format::ModelDesc& desc,
                                               const std::string& why, MeshOutcome& out);

// The search of Sizing over table sizes up to c.desc's (triage's): the first rung, then down
// while rungs meet the target and steps are left, or up while a rung narrowly misses it
// (near_target), each larger rung with a whole budget.
Sized size_to_target(const Run& run, const scene::Mesh& mesh, Candidate& c, const voxelize::Occupancy& occ,
                     const MeasureRays& rays, MeshOutcome& out);

// The table size the search starts at: Sizing::first_log2_table_size, within
// [ClassifyRule::min_log2_table_size, largest] (0, or a preset that does not explore: largest).
std::uint32_t first_rung_log2(const Preset& p, std::uint32_t largest);

// Picks the smallest option (resident bytes) that passes the gate and the memory rule and meets the
// target; else the smallest option of the largest rung trained (the most accurate) that passes
// both; else none. Writes every option's outcome.
void choose_option(Sized& sized);

// The asset's metadata document (schema/lsnif-metadata.schema.json). No wall times: an
// asset must be reproducible byte for byte for the same input, seed and threads.
json asset_metadata(const Run& run, const std::string& source, const scene::Mesh& mesh, const Candidate& c,
                    const Option& o, const Trained& t, const std::string& key);

// The asset's bytes: `metadata` stored into the model, then serialized.
format::Result<std::vector<std::uint8_t>> encode_asset(Option& o, const json& metadata);

// Write: the bytes through a temporary file and a rename. Returns the error, if any.
std::string write_asset(const Run& run, const scene::Mesh& mesh, std::span<const std::uint8_t> bytes,
                        const fs::path& asset, MeshOutcome& out);

// The memory rule on the asset actually chosen: why its resident bytes do not beat the
// yardstick's BVH by ClassifyRule::min_memory_ratio, or an empty string (also for a forced mesh).
std::string memory_rule_failure(const Run& run, const Candidate& c, std::uint64_t resident_bytes);

// "Embree" or "compressed": the yardstick as the reasons name it.
const char* bvh_yardstick_label(BvhYardstick y);

// The manifest's record of the asset written at `asset` (named `file`): its file bytes and
// the bytes a renderer holds once it is open; 0 for what cannot be read.
AssetFile asset_file(const fs::path& asset, const std::string& file, std::optional<bool> reused);

// The image error of `asset` (its bytes) on the held-out views of `mesh` (`views`, or made
// here when null); none when the visual check is off or the views cannot be rendered.
std::optional<render::ObjectFlip> held_out_images(const Run& run, const scene::Mesh& mesh,
                                                  const render::ObjectViews* views,
                                                  std::span<const std::uint8_t> asset, MeshOutcome& out);

// Settles a mesh whose asset ships (just written, or reused): its metrics, its held-out image
// error, the target's verdict and the file.
void shipped(const Run& run, HeldOut metrics, std::optional<render::ObjectFlip> images,
             const std::string& file, const fs::path& asset, bool reused, MeshOutcome& out);

// Settles a mesh none of whose rungs passes the gate (`abandoned`: given up during training).
void below_gate(const HeldOut& metrics, bool abandoned, MeshOutcome& out);

// A mesh after classification (triage_mesh): decided (it stays BVH; `out` is settled) or a
// candidate that convert_candidate may still turn into an LSNIF. The scene's memory is
// counted from these before anything is trained.
struct Triaged {
    const scene::Mesh* mesh = nullptr;   // borrowed from the imported scene, alive for the run
    std::string source;                  // the input file, as given
    MeshOutcome out;                     // settled once decided
    std::optional<Candidate> candidate;  // a candidate's model and Embree scene
    std::optional<voxelize::Occupancy> occupancy;
    bool decided = false;         // stays BVH whatever happens next (`out` settled by triage)
    std::uint64_t bvh_bytes = 0;  // the mesh's own BVH on the run's yardstick: what it costs as BVH
    std::uint64_t estimate = 0;   // a candidate's estimated resident asset bytes
    std::string key;              // its cache key once cache_key computed it ("" until then)
    // A candidate whose asset another candidate of the run makes (mark_shared_assets): the
    // index of that leader in `triaged`. A follower is never converted; it takes the leader's
    // result (follow_leader).
    std::optional<std::size_t> leader;
    std::size_t triage_reasons = 0;  // out.reasons.size() before settling: triage's own
    bool forced() const { return candidate && candidate->forced; }
};

// Classification of one mesh (--simple, triangle count, classify, voxelize_mesh,
// worth_an_lsnif) and the bytes of its BVH. A mesh whose BVH cannot be measured counts 0
// bytes, with a warning appended to `warnings`.
Triaged triage_mesh(const Run& run, const std::string& source, const scene::Mesh& mesh, MeshOutcome out,
                    std::vector<std::string>& warnings);

// A candidate through the remaining stages (reuse, sizing, gate, encoding, memory rule,
// writing), which settle p.out. In a dry run, the plan (Decision::planned). Errors that
// concern the run (an asset that could not be written) are appended to `errors`.
void convert_candidate(const Run& run, Triaged& p, std::vector<std::string>& errors);

// The cache key of a candidate's result (docs/pipeline.md "Cache keys"): SHA-256 over the
// build identity, every setting that changes the result (asset_key's, the gate, whether the
// mesh was forced, the source and mesh name its asset's metadata records) and the mesh's
// geometry (positions, indices, shading normals, triangle materials). Computed once per
// candidate (it hashes every geometry array) and kept in p.key; the first call must come
// while p.candidate is set.
const std::string& cache_key(const Run& run, Triaged& p);

// convert_candidate through run.cache: a hit restores the stored outcome (and writes its
// asset into OUTDIR); a miss converts and stores the result; a corrupt entry is reported in
// `warnings`, converted again and replaced. Without a cache, convert_candidate.
void convert_cached(const Run& run, Triaged& p, std::vector<std::string>& errors,
                    std::vector<std::string>& warnings, CacheCounts& counts);

// A candidate's estimated conversion time in milliseconds on the reference machine
// (docs/pipeline.md "Shards"), from the preset's training samples and the mesh's triangles.
std::uint64_t estimated_cost_ms(const Run& run, const Triaged& p);

// The shard (1..shard_count) that converts each candidate of `triaged` (0 for the others
// and without sharding; a follower gets its leader's): candidates costliest first (estimated_cost_ms; ties by
// cache key), each to the shard with the least estimated work so far. Every shard computes the same
// assignment, whatever the order of `triaged`.
std::vector<std::uint32_t> shard_owners(const Run& run, std::vector<Triaged>& triaged);

// Candidates whose assets would be the same file (the same geometry and settings, so the
// same asset_key) share one conversion: the first in input order leads, the others follow
// it (Triaged::leader), whether or not either was forced. So the asset, which records its
// mesh's name and source, names the first user whatever the number of jobs or the order in
// which they finish.
void mark_shared_assets(const Run& run, std::vector<Triaged>& triaged);

// Puts into `result` (a stored or a leader's outcome) what belongs to this mesh of this run:
// where it is in the scene (id, name, input, source mesh, instances, the fields a cache
// record leaves out) and this run's timings, taken from `own`.
void keep_scene_place(MeshOutcome& result, const MeshOutcome& own);

// A follower's outcome from its settled leader's: the same decision, metrics, candidates and
// asset, with the follower's own place in the scene and triage reasons, and a reason naming
// the leader.
void follow_leader(Triaged& follower, const Triaged& leader);

// Order in which candidates (indices into `triaged`; not followers) are converted: the scene's order, or
// with a memory budget, forced meshes first, then by estimated BVH bytes saved per asset
// byte, highest first (ties in scene order).
std::vector<std::size_t> conversion_order(const std::vector<Triaged>& triaged, bool budgeted);

// The bytes a mesh costs once it is settled: its asset's resident bytes when it became an LSNIF (the
// estimate in a dry run), else its BVH's.
std::uint64_t bytes_after(const Triaged& p);

// Every mesh's outcome (indexed like `triaged`) with its memory {before, after}:
// candidates converted in conversion_order() until the scene's total (every mesh once,
// instances share it) fits run.opt.memory_budget; the ones left stay BVH with the reason.
// Without a budget every candidate is converted. Releases each candidate's Embree scene
// once it is done.
std::vector<MeshOutcome> convert_meshes(const Run& run, std::vector<Triaged>& triaged,
                                        std::vector<std::string>& errors, std::vector<std::string>& warnings,
                                        CacheCounts& counts);

// Why run.opt.memory_budget cannot be met whatever is converted: it is below the BVH bytes
// of the meshes that are not candidates. Empty when it can (or when there is no budget).
std::string unreachable_budget(const Run& run, const std::vector<Triaged>& triaged);

// The outcome of mesh k of input `in` before any stage ran: where it is, its counts.
MeshOutcome new_outcome(const scene::Scene& sc, std::size_t in, std::size_t k, std::size_t id);

// The manifest document (schema/manifest.schema.json); meshes written with `fields`
// (OutcomeFields::reproducible for ConvertOptions::reproducible_manifest).
json manifest_json(const Run& run, const std::vector<InputRecord>& inputs,
                   const std::vector<MeshOutcome>& meshes, const json& instances, const SceneMemory& memory,
                   OutcomeFields fields);

}  // namespace lsnif::converter::stages
