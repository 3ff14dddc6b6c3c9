// The stages of `lsnif convert` (convert.cpp), one function each, in pipeline order:
//   resolve_preset; per mesh, plan_mesh: classify -> voxelize_mesh -> worth_an_lsnif and the
//   BVH's bytes; then convert_meshes, per candidate in conversion_order() until the memory
//   budget is met, convert_candidate: asset_key -> (reusable_metrics -> shipped |
//   draw_measure_rays -> size_to_target [train_rung (-> active_neurons -> remove_inactive_neurons)
//   -> gate per rung, choose_option] ->
//   asset_metadata -> encode_asset -> memory_rule_failure -> write_asset -> shipped);
//   finally scene_memory, manifest_json -> write_manifest (manifest.hpp).
// A stage that decides "simple" returns nothing (or false) and records its reason in the
// mesh's MeshRecord. Internal to the converter: exposed so that each stage is tested on its
// own (tests/converter/test_convert_stages.cpp); not installed, not an API.
#pragma once

#include <lsnif/converter/convert.hpp>
#include <lsnif/format/container.hpp>
#include <lsnif/mesh/mesh.hpp>
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
#include <string>
#include <vector>

namespace lsnif::cache {
class Store;
}

namespace lsnif::converter::stages {

using nlohmann::json;
namespace fs = std::filesystem;

// JSON of the records (records.cpp): a 3-vector, one family's held-out metrics (and read
// back strictly: every field present and of its type, or nothing), the model's description.
json vec3(const std::array<float, 3>& v);
json family_json(const samples::FamilyMetrics& f);
std::optional<samples::FamilyMetrics> family_from_json(const json& j);
json model_json(const format::ModelDesc& d);

// What a run shares between its meshes.
struct Run {
    const ConvertOptions& opt;
    Preset preset;
    std::uint32_t threads;
    fs::path outdir;
    ConvertProgress progress;
    std::shared_ptr<const cache::Store> cache;  // --cache; null without
    void report(const ProgressEvent& e) const {
        if (progress) progress(e);
    }
    bool forced(const std::vector<std::string>& names, const std::string& mesh) const {
        return std::find(names.begin(), names.end(), mesh) != names.end();
    }
};

// A mesh's manifest entry while it moves through the stages.
struct MeshRecord {
    json entry;  // id, name, input, counts, geometry hash, instance count
    std::vector<std::string> reasons;
    json stats;  // null until classification measured the mesh
    json timings = json::object();

    void add_seconds(const char* stage, double seconds) {
        timings[stage] = timings.value(stage, 0.0) + seconds;
    }
    json simple(const std::string& why) {
        reasons.push_back(why);
        return finish("simple");
    }
    // This run could not produce the mesh's result (its asset could not be encoded or
    // written): not a decision, and not cached. A renderer draws the mesh from its BVH.
    json failed(const std::string& why) {
        reasons.push_back(why);
        return finish("failed");
    }
    // Left to another job (lsnif batch --object): neither converted nor decided here.
    json deferred(const std::string& why) {
        reasons.push_back(why);
        return finish("deferred");
    }
    json finish(const char* cls) {
        entry["class"] = cls;
        entry["reasons"] = reasons;
        if (!stats.is_null()) entry["stats"] = stats;
        entry["timings"] = timings;
        return entry;
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
    bool forced = false;
};

// The rays a mesh's models are measured on, drawn once and shared by every rung of the
// ladder: held-out rays (the gate and the target) and validation rays (the curve that
// decides during training). Both apart from the training rays.
struct MeasureRays {
    std::vector<samples::Sample> held_out;
    std::vector<std::array<float, 3>> held_out_geometric_normals;
    std::vector<samples::Sample> validation;
};

// One rung of the ladder, trained.
struct Trained {
    format::ModelData model;  // model.desc is the rung's
    trainer::TrainConfig config;
    trainer::StreamedResult stream;
    std::vector<ValidationPoint> validation;  // the curve, one point per check
    // Why training was given up at step `abandoned_at` (EarlyAbort); empty when it ran to the end.
    std::vector<std::string> abandoned;
    std::uint32_t abandoned_at = 0;
    // The step at which training stopped because the validation curve met the target
    // (TargetStop); 0 when it did not.
    std::uint32_t target_met_at = 0;
    // Why a smaller rung was given up against the larger rung's curve (falls_behind).
    std::string fell_behind;
    double seconds = 0;  // wall time of this rung: drawing, preparing, training, validating, pruning
    // Hidden neurons removed from `model` per layer (Preset::prune_inactive); empty when off.
    std::vector<std::uint32_t> pruned;
};

// A model that may ship: a trained rung's fp16 export, or its 8-bit quantization.
struct Option {
    std::size_t rung = 0;       // into Sized::rungs: the training it comes from
    format::ModelData model;    // metadata filled only for the chosen one (encode_asset)
    json metrics;               // gate() on the held-out rays, as the manifest records them
    samples::Metrics held_out;  // the same, typed: what decisions read
    std::uint64_t bytes = 0;    // serialized without metadata
    bool target_met = false;    // passes the gate and meets --target on held-out rays
    bool memory_ok = false;     // beats the BVH by ClassifyRule::min_memory_ratio (or forced)
    double seconds = 0;         // measuring (and, for the fp16 option, training) it
    std::string outcome;        // chosen and why, or why not (choose_option)
};

// Every rung tried for a mesh, largest first, and every option they gave.
struct Sized {
    std::vector<Trained> rungs;
    std::vector<Option> options;        // per rung: fp16, then u8_affine (Sizing::quantize)
    json candidates = json::array();    // the manifest's "candidates", one per option
    std::optional<std::size_t> chosen;  // into options; none when nothing may ship
    std::string why;                    // why `chosen` won
};

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

// Classify: bounds, float range, Embree's BVH size, the table size that beats it and the
// geometry statistics. Returns nothing when the mesh stays simple (reason recorded).
// `forced_complex` (--complex) skips the table sizing. Contract: `rec.stats` is set whenever
// Embree built the mesh.
std::optional<Candidate> classify(const Run& run, const scene::Mesh& mesh, bool forced_complex,
                                  MeshRecord& rec);

// Voxelize: the conservative occupancy grid of the candidate's model.
std::optional<voxelize::Occupancy> voxelize_mesh(const Run& run, const scene::Mesh& mesh, const Candidate& c,
                                                 MeshRecord& rec);

// The memory rule: an LSNIF must beat the BVH by min_memory_ratio (unless forced). Records
// the comparison; false when the mesh stays simple (reason recorded).
bool worth_an_lsnif(const Run& run, const scene::Mesh& mesh, const Candidate& c, MeshRecord& rec);

// The asset's content key: geometry and every setting that changes the weights. The file
// is named by its hash, so an unchanged mesh finds its asset again.
std::string asset_key(const Run& run, const scene::Mesh& mesh, const format::ModelDesc& desc);

// Reuse: the held-out metrics of an existing asset written for exactly this key (as its
// metadata records them, and the pooled ones read back), or nothing (absent, unreadable,
// another key, or metrics this version does not write).
struct Reused {
    json metrics;
    samples::FamilyMetrics pooled;
};
std::optional<Reused> reusable_metrics(const fs::path& asset, const std::string& key);

// Draws the held-out and validation rays (seeded by the run's seed, not by the rung).
MeasureRays draw_measure_rays(const Run& run, const scene::Mesh& mesh, Candidate& c, MeshRecord& rec);

// Trains `desc` (a rung: the candidate's model with another table size) for at most `steps`
// steps on streamed rays, checking the validation curve `validation_checks` times: it gives
// up when the gate is out of reach (EarlyAbort) or when, as a smaller rung, it falls behind
// `larger` (the previous rung's curve; empty for the first), and stops once the target is
// met (TargetStop). Timings accumulate in `rec`.
Trained train_rung(const Run& run, const scene::Mesh& mesh, Candidate& c, const format::ModelDesc& desc,
                   const voxelize::Occupancy& occ, const MeasureRays& rays, std::uint32_t steps,
                   std::span<const ValidationPoint> larger, MeshRecord& rec);

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

// Gate: held-out metrics of the trained model and the verdict, as the manifest records
// them ({"held_out_rays", "families", "gate": {"passed", "reasons"?}}).
// `model` is `t`'s fp16 export or its quantization; `t` supplies the training verdicts. The
// metrics also go to `held_out`, typed, for the decisions that read them.
json gate(const Run& run, const scene::Mesh& mesh, const format::ModelData& model, const Trained& t,
          const MeasureRays& rays, samples::Metrics& held_out, MeshRecord& rec);

// The manifest's record of one option: size, encoding, bytes, steps, seconds, held-out
// metrics, verdicts, outcome, why training stopped and (fp16 option) the rung's curve.
json candidate_json(const Option& o, const Trained& t);

// Measures `model` (from rung `rung`, trained as `t`) as an option: held-out metrics, the
// target, serialized bytes and the memory rule.
Option measure_option(const Run& run, const scene::Mesh& mesh, const Candidate& c, std::size_t rung,
                      format::ModelData model, const Trained& t, const MeasureRays& rays, MeshRecord& rec);

// Measures rung `rung` of `sized` in every encoding of rung_encodings() and appends the
// options to sized.options.
void add_options(const Run& run, const scene::Mesh& mesh, const Candidate& c, std::size_t rung,
                 const MeasureRays& rays, Sized& sized, MeshRecord& rec);

// The grid encodings each rung is measured in: fp16, and u8_affine when Sizing::quantize.
std::vector<format::GridEncoding> rung_encodings(const Preset& p);

// "2^17 rows, u8_affine grid, 855000 bytes": the option in the mesh's reasons.
std::string option_summary(const Option& o);

// The ladder (Sizing): trains c.desc, then each smaller table size while the previous one
// met the target and the preset's step budget has at least as many steps left as it used.
Sized size_to_target(const Run& run, const scene::Mesh& mesh, Candidate& c, const voxelize::Occupancy& occ,
                     const MeasureRays& rays, MeshRecord& rec);

// Picks the smallest option (bytes) that passes the gate and the memory rule and meets the
// target; else the first rung's smallest option that passes both; else none. Writes every
// option's outcome.
void choose_option(Sized& sized);

// The asset's metadata document (schema/lsnif-metadata.schema.json). No wall times: an
// asset must be reproducible byte for byte for the same input, seed and threads.
json asset_metadata(const Run& run, const std::string& source, const scene::Mesh& mesh, const Candidate& c,
                    const Option& o, const Trained& t, const std::string& key);

// The asset's bytes: `metadata` stored into the model, then serialized.
format::Result<std::vector<std::uint8_t>> encode_asset(Option& o, const json& metadata);

// Write: the bytes through a temporary file and a rename. Returns the error, if any.
std::string write_asset(const Run& run, const scene::Mesh& mesh, std::span<const std::uint8_t> bytes,
                        const fs::path& asset, MeshRecord& rec);

// The memory rule on the asset actually chosen: why it does not beat the BVH by
// ClassifyRule::min_memory_ratio, or an empty string (also for a forced mesh).
std::string memory_rule_failure(const Run& run, const Candidate& c, std::uint64_t asset_bytes);

// The entry of a mesh whose asset ships (just written, or reused).
json shipped(const Run& run, json metrics, const samples::FamilyMetrics& pooled, const std::string& file,
             const fs::path& asset, bool reused, MeshRecord& rec);

// The entry of a mesh none of whose rungs passes the gate.
json below_gate(const json& metrics, bool abandoned, MeshRecord& rec);

// The manifest's verdict on the target for one shipped asset: the target and whether it
// was met ({"visibility", "distance_pct", "normal_deg", "met", "misses"?}).
json target_json(const Target& target, const std::vector<std::string>& misses);

// A mesh after classification (plan_mesh): decided (it stays BVH; `decided` is its final
// manifest entry) or a candidate that convert_candidate may still turn into an LSNIF. The
// scene's memory is counted from these before anything is trained (scene_memory).
struct Planned {
    const scene::Mesh* mesh = nullptr;  // borrowed from the imported scene, alive for the run
    std::string source;                 // the input file, as given
    MeshRecord rec;
    std::optional<Candidate> candidate;  // a candidate's model and Embree scene
    std::optional<voxelize::Occupancy> occupancy;
    json decided;                 // the entry of a mesh that stays BVH; null for a candidate
    std::uint64_t bvh_bytes = 0;  // the mesh's own BVH: what it costs while it stays BVH
    std::uint64_t estimate = 0;   // a candidate's estimated asset bytes (lsnif_bytes_estimate)
    std::string key;              // its cache key once cache_key computed it ("" until then)
    bool forced() const { return candidate && candidate->forced; }
};

// Classification of one mesh (--simple, triangle count, classify, voxelize_mesh,
// worth_an_lsnif) and the bytes of its BVH. A mesh whose BVH cannot be measured counts 0
// bytes, with a warning appended to `warnings`.
Planned plan_mesh(const Run& run, const std::string& source, const scene::Mesh& mesh, MeshRecord rec,
                  std::vector<std::string>& warnings);

// A candidate through the remaining stages (reuse, sizing, gate, encoding, memory rule,
// writing): its manifest entry. In a dry run, the entry of the plan ("complex"). Errors that
// concern the run (an asset that could not be written) are appended to `errors`.
json convert_candidate(const Run& run, Planned& p, std::vector<std::string>& errors);

// What the cache did in a run (the report's "cache").
struct CacheCounts {
    std::size_t hits = 0, stored = 0, corrupt = 0;
};

// The cache key of a candidate's result (docs/pipeline.md "Cache keys"): SHA-256 over the
// build identity, every setting that changes the result (asset_key's, the gate, whether the
// mesh was forced, the source and mesh name its asset's metadata records) and the mesh's
// geometry (positions, indices, shading normals, triangle materials). Computed once per
// candidate (it hashes every geometry array) and kept in p.key; the first call must come
// while p.candidate is set.
const std::string& cache_key(const Run& run, Planned& p);

// convert_candidate through run.cache: a hit restores the stored entry (and writes its
// asset into OUTDIR); a miss converts and stores the result; a corrupt entry is reported in
// `warnings`, converted again and replaced. Without a cache, convert_candidate.
json convert_cached(const Run& run, Planned& p, std::vector<std::string>& errors,
                    std::vector<std::string>& warnings, CacheCounts& counts);

// A candidate's estimated conversion time in milliseconds on the reference machine
// (docs/pipeline.md "Shards"), from the preset's training samples and the mesh's triangles.
std::uint64_t estimated_cost_ms(const Run& run, const Planned& p);

// The shard (1..shard_count) that converts each candidate of `planned` (0 for the others
// and without sharding): candidates costliest first (estimated_cost_ms; ties by cache key),
// each to the shard with the least estimated work so far. Every shard computes the same
// assignment, whatever the order of `planned`.
std::vector<std::uint32_t> shard_owners(const Run& run, std::vector<Planned>& planned);

// Drops from a manifest entry what differs between runs of the same conversion: timings,
// whether the asset was reused, the candidates' seconds (ConvertOptions::reproducible_manifest).
void strip_run_dependent(json& entry);

// Order in which candidates (indices into `planned`) are converted: the scene's order, or
// with a memory budget, forced meshes first, then by estimated BVH bytes saved per asset
// byte, highest first (ties in scene order).
std::vector<std::size_t> conversion_order(const std::vector<Planned>& planned, bool budgeted);

// The bytes a mesh costs once its entry is decided: its asset's when it became an LSNIF
// (the estimate in a dry run), else its BVH's.
std::uint64_t bytes_after(const Planned& p, const json& entry);

// Every mesh's manifest entry (indexed like `planned`) with its "memory" {before, after}:
// candidates converted in conversion_order() until the scene's total (every mesh once,
// instances share it) fits run.opt.memory_budget; the ones left stay BVH with the reason.
// Without a budget every candidate is converted. Releases each candidate's Embree scene
// once it is done.
std::vector<json> convert_meshes(const Run& run, std::vector<Planned>& planned,
                                 std::vector<std::string>& errors, std::vector<std::string>& warnings,
                                 CacheCounts& counts);

// Why run.opt.memory_budget cannot be met whatever is converted: it is below the BVH bytes
// of the meshes that are not candidates. Empty when it can (or when there is no budget).
std::string unreachable_budget(const Run& run, const std::vector<Planned>& planned);

// The scene's memory from the entries' "memory": {"before", "after"} in bytes, and with a
// budget {"budget", "fits"}; "estimated" in a dry run.
json scene_memory(const Run& run, const std::vector<json>& entries);

// The manifest entry of mesh k of input `in` before any stage ran.
MeshRecord new_record(const scene::Scene& sc, std::size_t in, std::size_t k, std::size_t id);

// The manifest document (schema/manifest.schema.json).
json manifest_json(const Run& run, const json& inputs, const json& meshes, const json& instances,
                   const json& memory);

}  // namespace lsnif::converter::stages
