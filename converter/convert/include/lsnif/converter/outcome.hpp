// What a conversion decided and measured for one mesh (`MeshOutcome`), as typed values: the
// value every stage of `lsnif convert` fills in, the memory budget, shards and the cache
// record pass on, and the manifest, the text report, `lsnif batch`, `lsnif merge`, `lsnif eval`
// and `lsnif bench` read. JSON exists only at the edges: `outcome_json` writes the manifest's
// mesh entry (schema/manifest.schema.json) and a cache record, `outcome_from_json` reads
// either back and refuses anything it did not write, naming the field (no field defaults: a
// decision never reads a value nobody measured). One key vocabulary, the manifest's.
//
// Text (reasons, misses, a candidate's outcome) is for people: it is rendered from the typed
// values and no code reads it back to decide anything.
#pragma once

#include <lsnif/base/result.hpp>
#include <lsnif/converter/rules.hpp>
#include <lsnif/format/container.hpp>
#include <lsnif/render/object_views.hpp>
#include <lsnif/samples/held_out.hpp>

#include <nlohmann/json.hpp>

#include <array>
#include <cstdint>
#include <optional>
#include <string>
#include <string_view>
#include <vector>

namespace lsnif::converter {

// Where a mesh ends up: what a renderer does with it.
enum class MeshClass : std::uint8_t {
    simple,    // stays in the BVH by decision
    complex,   // an LSNIF asset (or, in a dry run, planned to become one)
    failed,    // this run could not encode or write its asset: drawn from its BVH, converted again next run
    deferred,  // left to another job (`lsnif batch --object`): neither converted nor decided here
};

// Why: the one decision that settled the mesh (the manifest's `decision`). Each implies its
// class (mesh_class). The reasons beside it say the same in words, with the numbers.
enum class Decision : std::uint8_t {
    forced_simple,        // --simple NAME
    few_triangles,        // below ClassifyRule::min_triangles: a BVH is small and exact
    not_modelable,        // no box, outside single precision's range, or Embree could not build it
    voxelization_failed,  // the occupancy grid could not be built
    no_memory_benefit,  // an LSNIF, held in memory, would not beat the BVH by ClassifyRule::min_memory_ratio
    decided_early,      // the validation curve showed the gate is out of reach (EarlyAbort)
    below_gate,         // trained to the end, held-out accuracy below the gate
    asset_not_smaller,  // the chosen asset, held in memory, does not beat the BVH by the memory rule
    budget_met,         // --memory-budget: the scene fits without converting it
    other_shard,        // --shard: another shard converts it
    left_to_another_job,  // --object: another job converts it
    planned,              // --dry-run: would be converted
    shipped,              // converted (or reused) and written
    encode_failed,        // the asset could not be serialized
    write_failed,         // the asset could not be written (or restored from the cache)
};
inline constexpr std::size_t kDecisionCount = 15;

MeshClass mesh_class(Decision d);
// Whether classification alone decided (the mesh never was a candidate): forced_simple,
// few_triangles, not_modelable, voxelization_failed, no_memory_benefit.
bool decided_in_triage(Decision d);
std::string_view class_name(MeshClass c);
std::string_view decision_name(Decision d);

// The stages whose wall time a mesh records (the manifest's `timings`, in seconds).
enum class Stage : std::uint8_t {
    classify,
    voxelize,
    sample,
    prepare,
    train,
    validate,
    prune,
    evaluate,
    visual,
    write
};
inline constexpr std::size_t kStageCount = 10;
std::string_view stage_name(Stage s);

// Wall seconds per stage; a stage that did not run is absent (not 0).
struct Timings {
    std::array<std::optional<double>, kStageCount> seconds{};
    void add(Stage s, double t) { seconds[std::size_t(s)] = seconds[std::size_t(s)].value_or(0) + t; }
    bool empty() const;
    double total() const;
};

// A mesh's BVH on both yardsticks (BvhYardstick): Embree's as built and the compressed
// estimate (the manifest's `stats.bvh`).
struct BvhBytes {
    std::uint64_t embree = 0;
    std::uint64_t compressed = 0;
    std::uint64_t of(BvhYardstick y) const { return y == BvhYardstick::compressed ? compressed : embree; }
};

// What classification measured of a mesh (the manifest's `stats`).
struct MeshStats {
    std::array<float, 3> box_min{}, box_max{};    // the padded box (voxelize::padded_box)
    double area_ratio = 0;                        // surface area / box surface area
    std::uint64_t components = 0;                 // index-connected components
    bool closed = false, solid = false;           // sampling::EmbreeSource::is_closed, rejects_interior
    std::uint32_t log2_table_size = 0;            // the table size classification chose
    BvhBytes bvh;                                 // the mesh's BVH on both yardsticks
    std::uint64_t resident_estimate = 0;          // the planned asset's resident bytes, estimated
    std::optional<double> occupied_fraction;      // once voxelized
    std::optional<double> mean_occupied_per_ray;  // once trained: occupied voxels a ray crosses
    std::optional<std::uint64_t> training_rays;   // once trained: distinct rays over every rung
};

// The gate's verdict on held-out metrics: passed, or why not (gate_failures' lines and the
// training's own verdicts: divergence, giving up).
// A model's measurement as the manifest's and the asset's `metrics` hold it: the held-out
// rays (that no decision saw), the gate's verdict (decided on the decision rays and the
// images), and the visual check.
struct HeldOut {
    std::uint64_t rays = 0;    // held-out rays drawn (before culling)
    samples::Metrics metrics;  // per family and pooled
    GateVerdict gate;
    std::optional<render::ObjectFlip> flip;  // absent when the visual check was off
    // The escape rule's limit chosen for the asset on the decision rays (choose_escape_points;
    // docs/model.md "The escape rule"); 0 = off. Absent from older records: 0.
    std::uint32_t escape_points = 0;
};

// One option of the sizing ladder (the manifest's `candidates[]`).
enum class CandidateOutcome : std::uint8_t {
    chosen_meets_target,  // the smallest that meets the target
    chosen_passes_gate,   // none meets the target; the largest rung's smallest that passes the gate
    fails_gate,
    fails_memory_rule,
    smaller_meets_target,  // meets the target, but a smaller candidate does too
    misses_target,
};
enum class StopKind : std::uint8_t { ran_to_end, target_met, given_up };
struct CandidateRecord {
    std::uint32_t log2_table_size = 0;
    std::uint32_t grid_resolution = 0;        // V of the occupancy grid
    std::vector<std::uint32_t> hidden_width;  // per hidden layer, after pruning
    format::GridEncoding grid = format::GridEncoding::fp16;
    std::uint64_t bytes = 0;           // serialized without metadata
    std::uint64_t resident_bytes = 0;  // held once opened (format::resident_bytes), without metadata
    std::uint32_t steps = 0, steps_planned = 0;
    std::optional<double> seconds;                            // wall time (absent in reproducible records)
    double visibility = 0, distance_pct = 0, normal_deg = 0;  // pooled held-out
    double decided_visibility = 0, decided_distance_pct = 0, decided_normal_deg = 0;  // pooled, decision rays
    bool gate_passed = false, target_met = false, memory_rule_passed = false;
    CandidateOutcome outcome = CandidateOutcome::misses_target;
    std::size_t of = 0;  // candidates of the mesh (rendered in a chosen outcome)
    std::optional<std::vector<ValidationPoint>> validation;  // the rung's curve, with its fp16 option
    StopKind stop = StopKind::ran_to_end;
    std::string stop_why;                       // given_up: why (EarlyAbort or falls_behind)
    std::vector<std::uint32_t> pruned_neurons;  // per hidden layer; empty when pruning was off
    std::optional<render::ObjectFlip> flip;     // the visual check (ObjectViews); absent when off
};

// The --target verdict of a shipped asset.
struct TargetVerdict {
    Target target;
    std::vector<std::string> misses;  // target_misses; empty = met
};

struct AssetFile {
    std::string file;                  // relative to the manifest: a bare file name
    std::uint64_t bytes = 0;           // the file
    std::uint64_t resident_bytes = 0;  // what a renderer holds once it is open (format::resident_bytes)
    std::optional<bool> reused;        // absent in reproducible records
};

// The mesh's bytes in the scene, once whatever its instances, on the run's yardstick
// (ClassifyRule::yardstick): before = its BVH; after = its asset's resident bytes when
// complex, else its BVH.
struct MeshMemory {
    std::uint64_t before = 0, after = 0;
    bool estimated = false;  // a dry run: the asset's estimate
};

struct StoppedEarly {
    std::uint32_t step = 0, steps = 0;  // stopped at `step` of `steps` planned: the curve met the target
};

struct MeshOutcome {
    // Where the mesh is in the scene.
    std::uint64_t id = 0;  // index among the run's meshes
    std::string name;
    std::uint64_t input = 0;        // index into the run's inputs
    std::uint64_t source_mesh = 0;  // index within that input
    std::uint64_t triangles = 0, vertices = 0, instances = 0;
    std::string geometry_hash;
    // What was decided and why.
    Decision decision = Decision::planned;
    std::vector<std::string> reasons;
    std::optional<MeshStats> stats;
    Timings timings;
    std::optional<HeldOut> held_out;          // the shipped (or best) option's; the manifest's `metrics`
    std::vector<CandidateRecord> candidates;  // every option tried, largest rung first
    std::optional<std::vector<ValidationPoint>> validation;  // the chosen rung's curve
    std::optional<StoppedEarly> stopped_early;
    std::optional<TargetVerdict> target;
    // The shipped asset's image error on its held-out views (ObjectViews drawn apart from the
    // decision views; the manifest's `held_out_images`): what is reported. Not in the asset.
    std::optional<render::ObjectFlip> held_out_images;
    std::optional<AssetFile> asset;  // the manifest's `lsnif`
    std::optional<MeshMemory> memory;
    std::optional<std::uint32_t> shard;         // --shard: the shard that converts it
    std::optional<std::string> cache_key;       // --dry-run: the planned key
    std::optional<std::uint64_t> estimated_ms;  // --dry-run: estimated_cost_ms

    MeshClass cls() const { return mesh_class(decision); }
    // Settles the mesh: `decision`, with `why` as the last reason (when not empty).
    MeshOutcome& settle(Decision d, std::string why = {});
};

// Which fields outcome_json writes.
enum class OutcomeFields : std::uint8_t {
    all,           // the run's report and a non-reproducible manifest
    reproducible,  // without what differs between runs of one conversion: timings, reused, seconds
    result,        // a cache record: reproducible, and without where the mesh is in a scene
                   // (id, name, input, source_mesh, instances), which the restoring run fills in
};

nlohmann::json outcome_json(const MeshOutcome& o, OutcomeFields fields = OutcomeFields::all);
// The inverse, strict: every field outcome_json writes for this kind of record is present and
// of its type, enumerations name one of their values. An error names the field ("meshes[3]."
// is the caller's prefix). `fields` says what the record may lack.
base::Result<MeshOutcome, std::string> outcome_from_json(const nlohmann::json& j,
                                                         OutcomeFields fields = OutcomeFields::all);

// An ObjectFlip as the manifest, the asset's metadata and `lsnif eval --objects` write it.
nlohmann::json object_flip_json(const render::ObjectFlip& f);

// Held-out metrics as the asset's metadata and the manifest store them
// ({"held_out_rays", "families", "gate"}), and back (strict, as outcome_from_json).
nlohmann::json held_out_json(const HeldOut& h);
base::Result<HeldOut, std::string> held_out_from_json(const nlohmann::json& j);

// One input of a run (the manifest's `inputs[]`).
struct InputRecord {
    std::string path;                   // relative to the manifest's directory (manifest_relative_path)
    std::string given;                  // as given on the command line, for people
    std::optional<std::string> error;   // why it could not be imported; none = imported
    std::vector<std::string> warnings;  // the importer's
    bool ok() const { return !error; }
};
nlohmann::json input_json(const InputRecord& in);
base::Result<InputRecord, std::string> input_from_json(const nlohmann::json& j);

// The scene's memory, every mesh once (the manifest's `scene_memory`), on `yardstick`: before
// = every mesh's BVH, after = the converted meshes' assets as held in memory plus the BVHs of
// the others.
struct SceneMemory {
    BvhYardstick yardstick = BvhYardstick::embree;
    std::uint64_t before = 0, after = 0;
    std::optional<std::uint64_t> budget;  // --memory-budget
    bool estimated = false;               // a dry run
    bool fits() const { return !budget || after <= *budget; }
};
// The sums over `meshes`' memory (each must have it, on `yardstick`); `budget` 0 = none.
SceneMemory scene_memory(const std::vector<MeshOutcome>& meshes, BvhYardstick yardstick, std::uint64_t budget,
                         bool estimated);
nlohmann::json scene_memory_json(const SceneMemory& m);
base::Result<SceneMemory, std::string> scene_memory_from_json(const nlohmann::json& j);

// A candidate's outcome as the manifest says it ("chosen: the smallest of 4 candidates that
// meets the target", "fails the gate", ...).
std::string candidate_outcome_text(CandidateOutcome o, std::size_t of);
// Why a chosen candidate won ("the smallest of 4 candidates that meets the target"); empty for
// an outcome that is not a choice.
std::string choice_text(CandidateOutcome o, std::size_t of);

}  // namespace lsnif::converter
