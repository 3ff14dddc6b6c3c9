// `lsnif convert`: scene import -> classification -> voxelization -> Embree ground truth ->
// training -> held-out evaluation and gate -> .lsnif assets + manifest (docs/architecture.md §1).
//
// Library code: never prints or exits. Progress goes through a callback; problems are
// collected per input and per mesh; the CLI decides what to print and the exit code.
#pragma once

#include <lsnif/format/container.hpp>
#include <lsnif/samples/held_out.hpp>
#include <lsnif/trainer/trainer.hpp>

#include <nlohmann/json.hpp>

#include <cstdint>
#include <functional>
#include <string>
#include <vector>

namespace lsnif::converter {

// Classification thresholds (documented in README "Classification").
//
// Model sizing ("never model more than a scene needs"): the preset's hash-table size
// 2^log2_table_size is the largest a mesh gets. It is halved while the .lsnif would not beat
// the BVH by min_memory_ratio, down to 2^min_log2_table_size; a mesh that still does not
// benefit stays BVH. `--complex NAME` skips this sizing and the memory rule: the mesh starts
// at the preset's model, and only the target (Sizing) makes it smaller.
struct ClassifyRule {
    std::uint64_t min_triangles = 2000;  // fewer: the BVH is tiny and exact; keep it
    // An approximation must at least halve the memory of what it replaces: a 10-30 % saving is
    // not worth ~3 % wrong visibility (2CylinderEngine has four 7-11k-triangle parts at 1.1-1.8x).
    double min_memory_ratio = 2.0;           // BVH bytes must be at least this x the .lsnif bytes
    std::uint32_t min_log2_table_size = 15;  // smallest table sizing may choose (2^15 rows)
};

// Held-out accuracy an asset must reach to ship (docs/architecture.md §3 "Gate").
struct Gate {
    double min_visibility = 0.95;          // pooled visibility accuracy
    double min_family_visibility = 0.90;   // every family
    double max_distance_median_pct = 2.0;  // pooled, % of the box diagonal
    double max_normal_median_deg = 30.0;   // pooled, against the shading normal
    // Every family must have at least this many held-out rays that reach the network: a
    // family the occupancy culls almost entirely (degenerate sampling, e.g. coordinates at
    // the edge of float range) is unmeasured, and an unmeasured asset is not shipped.
    std::uint64_t min_family_rays = 100;
};

// The accuracy a user asks of every shipped asset (`--target VIS,DIST,NORMAL`), on pooled
// held-out rays: visibility accuracy at least `visibility`, median distance error at most
// `distance_pct` % of the box diagonal, median shading-normal error at most `normal_deg`.
// Stricter than the gate, which is the floor below which nothing ships: an asset may pass
// the gate and miss the target, and the manifest says so (issue #12 sizes models to it).
// The default is issue #15's accuracy for the default preset on CGAL's dragon and
// armadillo (docs/model.md "A 64^3 grid"): sizing keeps the full model for them, and the
// early stop (TargetStop's margins beyond it) rarely cuts their training short.
struct Target {
    double visibility = 0.985;
    double distance_pct = 0.6;
    double normal_deg = 8.0;
};

// "VIS,DIST,NORMAL" (VIS in percent, e.g. "97,1.0,15") into `target`. False with a
// one-line `error` for anything else: not three finite numbers, VIS outside (0, 100],
// DIST outside (0, 100], NORMAL outside (0, 180].
bool parse_target(const std::string& text, Target& target, std::string& error);

// A byte count such as "1500000", "512K", "64MiB" or "1.5G" into `bytes` (K, M, G, T are
// powers of 1024; an optional "B" or "iB" after them; case-insensitive). False with a
// one-line `error` for anything else: empty, negative, zero, not a number, trailing text,
// or more than 2^63 bytes.
bool parse_byte_size(const std::string& text, std::uint64_t& bytes, std::string& error);

// Giving up early (docs/model.md "Deciding early"): at a validation check, once training
// has seen at least `min_samples` samples, an object is abandoned (it stays BVH) when even
// the largest improvement measured from such a point to the end of training could not
// bring its validation curve to the gate. The headrooms are the largest changes measured
// after ~2 M samples on CGAL's dragon and armadillo and the hard-geometry suite, with margin.
struct EarlyAbort {
    std::uint64_t min_samples = 1500000;  // before this the curve is too steep to judge
    double visibility_headroom = 0.05;    // measured at most 4.3 points (the hairball)
    double normal_headroom_deg = 20.0;    // measured at most 14.9 degrees (the cards)
    double distance_factor = 0.35;        // final / checked median: measured at least 0.46
};

// Stopping when the target is met (docs/model.md "Deciding early"): training ends at a
// validation check when this check and the `consecutive - 1` checks before it all meet the
// target with margins for the noise of the validation set (2^13 rays: about +-0.25 points of
// visibility between seeds), so that the held-out measure of the shipped model meets it too.
// Training an object further than its target only spends time: a user who wants more asks
// for more with --target.
struct TargetStop {
    std::uint32_t consecutive = 2;     // checks in a row: one good check may be noise; 0: never stop
    double visibility_margin = 0.003;  // validation visibility >= target + margin
    double distance_factor = 0.9;      // validation median distance <= factor x target
    double normal_margin_deg = 1.0;    // validation median normal <= target - margin
};

// Sizing to the target (docs/model.md "Sizing to the target"): the ladder is the preset's
// table size 2^log2_table_size halved down to 2^ClassifyRule::min_log2_table_size. A mesh's
// first rung is the largest that passes the memory rule; when it meets the target, the next
// smaller rung is trained from the steps left of the preset's budget, and so on while each
// smaller rung meets the target. The smallest asset that meets the target ships; so sizing
// never trains more steps than the fixed model did.
struct Sizing {
    bool explore_smaller = true;  // false: train the first rung only (the pre-#12 behaviour)
    // Also measure every rung with its hash-grid features quantized to 8 bits (FORMAT.md
    // §6.4.1): the grid's bytes halve, and the option ships when it still meets the target.
    bool quantize = true;
    // A smaller rung is given up at a validation check when its visibility, plus the most
    // the larger rung's curve gained after the same step, plus this slack, stays below the
    // visibility that TargetStop asks for: it would not catch up within its budget. A smaller
    // rung runs a shorter schedule and gains more late: the blob's 2^16 rung gained 2.25
    // points after step 288 where its 2^17 rung had gained 1.79 after step 240 (docs/model.md
    // "Sizing to the target"); the slack covers that difference twice.
    double curve_slack = 0.01;
};

// Box extents (largest axis of the padded box, in the mesh's units) that LSNIF models in
// single precision: squared distances and dot products of box-sized vectors stay inside
// float's normal range (~1e-38 .. 3e38) with margin. A mesh outside stays BVH, with the
// reason, even when forced with --complex.
inline constexpr double kMinModelExtent = 1e-15;
inline constexpr double kMaxModelExtent = 1e15;

struct Preset {
    std::string name;
    format::ModelDesc model;     // box is filled per mesh
    trainer::TrainConfig train;  // threads/seed are filled from the options
    // Training data is streamed in rounds: round r draws `train_chunk_rays` fresh rays, and
    // steps of that round sample the latest `train_window_chunks` chunks. Held-out accuracy
    // measured on the dragon rose from 96.3 % (2^21 rays reused for 10 epochs: 99.6 % on
    // the training rays themselves) to 97.7 % with 2^23 distinct rays at equal steps.
    std::uint64_t train_rays = 1u << 20;        // distinct training rays in all rounds
    std::uint64_t train_chunk_rays = 1u << 20;  // rays per round
    std::uint32_t train_window_chunks = 2;      // chunks a step samples from
    std::uint64_t eval_rays = 1u << 16;
    // Validation during training (docs/model.md "Validation curve"): `validation_rays` rays of
    // the three families, drawn apart from the training and held-out rays, are measured
    // through the reader's forward pass `validation_checks` times at evenly spaced steps.
    // The curve is recorded in the manifest; the held-out set stays untouched until the gate.
    std::uint64_t validation_rays = 1u << 13;
    std::uint32_t validation_checks = 10;
    // Inactive neurons (docs/model.md "Inactive neurons"): after training, every hidden
    // neuron whose ReLU output is zero on all `validation_rays` is removed with its weights,
    // so the shipped network is only as wide as the object uses (smaller and faster to run).
    bool prune_inactive = true;
    ClassifyRule classify;
    Gate gate;
    EarlyAbort early_abort;
    TargetStop target_stop;
    Sizing sizing;
};
// "default" (v1 model), "fast", "quality" (same model, more or fewer training steps) and
// "smoke" (a tiny model for pipeline checks).
bool find_preset(const std::string& name, Preset& out);
std::vector<std::string> preset_names();

// The arithmetic a conversion trains with (docs/pipeline.md "The same bytes everywhere").
//   canonical  fp32 in one fixed order: the same weights, metrics and decisions on every CPU
//              (AVX2, AVX-512, AMX machines, the portable build's scalar paths) and for any
//              thread count. The default.
//   machine    the MLP products of training in bf16 on Intel AMX or AVX-512 BF16 where the
//              CPU has them (fp32 elsewhere, which is the canonical arithmetic): faster on those
//              CPUs, but the weights depend on the CPU kind, so assets, cache keys and
//              manifests name the instructions (arithmetic_id).
enum class Arithmetic : std::uint8_t { canonical, machine };
// The version of the canonical arithmetic: bumped whenever an operation whose result
// reaches an asset or a decision (training, sampling, metrics, pruning, quantization) rounds
// differently. Recorded in assets and manifests; part of every cache key.
inline constexpr int kCanonicalArithmeticVersion = 1;
// What `a` runs as on this machine: "canonical-1", or "machine-bf16/amx" /
// "machine-bf16/avx512-bf16" (machine on a CPU without bf16 products is canonical).
std::string arithmetic_id(Arithmetic a);
// "canonical" or "machine" (the --arithmetic values); false for anything else.
bool parse_arithmetic(const std::string& text, Arithmetic& out);

// The reason recorded for a candidate that ConvertOptions::only_keys leaves to another job.
inline constexpr const char* kLeftToAnotherJob = "left to another job (lsnif batch --object)";

struct ConvertOptions {
    std::vector<std::string> inputs;
    std::string outdir;
    std::uint64_t seed = 1;
    // Threads and jobs decide how fast, never what: results are the same for any count.
    std::uint32_t threads = 0;  // 0 = hardware threads
    // --jobs: candidates converted at once, each with threads / jobs threads (at least 1).
    // Cannot be combined with memory_budget, which decides each conversion from the last.
    std::uint32_t jobs = 1;
    Arithmetic arithmetic = Arithmetic::canonical;  // --arithmetic
    std::string preset = "default";
    std::vector<std::string> force_complex;  // mesh names
    std::vector<std::string> force_simple;
    std::string command_line;         // recorded in metadata
    double gate_min_visibility = -1;  // >= 0 overrides the preset's pooled visibility gate
    std::uint32_t steps = 0;          // > 0 overrides the preset's training steps
    std::uint32_t batch_size = 0;     // > 0 overrides the preset's batch size
    // Import and classify only; report the plan (each candidate's cache key and estimated
    // conversion time with it: `cache_key`, `estimated_ms`), write nothing.
    bool dry_run = false;
    // --cache DIR: a content-addressed store (lsnif::cache) of every candidate's result,
    // shared between runs, processes and machines; empty = none (docs/pipeline.md).
    std::string cache_dir;
    // --shard I/N (`lsnif batch`): convert only the candidates this shard owns (the candidates
    // of all inputs, costliest first by an estimate of their conversion time, ties by cache
    // key, each dealt to the shard with the least estimated work); the others are recorded as
    // owned by their shard for `lsnif merge`. shard_count 0 = no sharding.
    std::uint32_t shard_index = 0, shard_count = 0;
    // --object KEY (`lsnif batch`; one edge of a Ninja file, docs/pipeline.md "Ninja"):
    // convert only the candidates with these cache keys, into the cache and OUTDIR's assets;
    // the others are left to other jobs and no manifest is written (the library's last step
    // writes it, from the cache). A key no candidate has is an error, and so is a result
    // that could not be stored (the Ninja edge's output is the cache entry).
    std::vector<std::string> only_keys;
    // Also write OUTDIR/scene.gltf (+ scene.bin): the scene with the LSNIF_neural_geometry
    // extension on every converted mesh (gltf_out.hpp). `lsnif batch` converts libraries,
    // not scenes, and leaves it out.
    bool write_gltf = true;
    // Leave run-dependent fields (timings, reused) out of the manifest, so that it is a
    // function of the inputs, the settings and the build alone (`lsnif batch`, `lsnif merge`).
    bool reproducible_manifest = false;
    // Train one model per mesh for the preset's whole budget, as before sizing existed: no
    // smaller rungs, no 8-bit option, no TargetStop (EarlyAbort and the gate still apply).
    bool fixed_model = false;
    // --no-give-up: train to the end of the budget even where the validation curve shows the
    // gate is out of reach (EarlyAbort off), to measure how far hard geometry gets. The gate
    // still decides what ships.
    bool no_give_up = false;
    // --keep-inactive: ship the trained network whole (Preset::prune_inactive off), to
    // measure what pruning changes.
    bool keep_inactive = false;
    Target target;  // --target: judged and reported per shipped asset
    // --memory-budget: the scene's memory in bytes (every mesh once: BVHs of the meshes that
    // stay BVH plus LSNIF assets) that conversion aims at; candidates are converted in order
    // of BVH bytes saved per asset byte until the scene fits, the rest stay BVH. 0 = none:
    // every candidate is converted. Missing it because candidates did not ship is a warning;
    // a budget below the meshes that stay BVH in any case is a usage error.
    std::uint64_t memory_budget = 0;
    // Model overrides (0 = the preset's value), for sweeps such as scripts/tradeoff. A
    // changed table size is the largest the per-mesh sizing may choose.
    std::uint32_t log2_table_size = 0;  // T = 2^n rows per hashed level
    std::uint32_t max_points = 0;       // H, voxel entry points per ray
    std::uint32_t grid_resolution = 0;  // V, occupancy grid cells per axis
    std::uint32_t hidden_width = 0;     // width of both hidden layers
    bool no_ray_inputs = false;         // the MLP sees the points' features only (1.0/1.1 files)
};

// Progress events: stage changes and training steps.
struct ProgressEvent {
    std::string mesh;
    std::string stage;  // import, classify, voxelize, sample, train, evaluate, write, done
    std::uint32_t step = 0, steps = 0;
    float loss = 0;
    double eta_seconds = 0;
    // Stage "done": the mesh's finished manifest entry (without "memory"), valid during the
    // call only. Sent once per mesh, as soon as it is decided or converted.
    const nlohmann::json* entry = nullptr;
};
using ConvertProgress = std::function<void(const ProgressEvent&)>;

struct ConvertResult {
    nlohmann::json manifest;          // what was written to OUTDIR/manifest.json (empty if nothing)
    nlohmann::json report;            // machine-readable report (--json)
    std::vector<std::string> errors;  // "FILE: problem", one per failed input
    std::vector<std::string> warnings;
    // The options cannot be met whatever conversion does (a --memory-budget below the bytes
    // of the meshes that stay BVH in any case): `errors` says why, nothing was written, and
    // the CLI exits 2 as for any other usage error.
    bool usage_error = false;
    bool ok() const { return errors.empty(); }
};

ConvertResult convert(const ConvertOptions& options, const ConvertProgress& progress = {});

// The threads each conversion of convert(options) uses: --threads (0 = the hardware's)
// shared by --jobs, at least 1.
std::uint32_t threads_per_job(const ConvertOptions& options);

// The accuracy gate's verdict on held-out metrics: one "held-out ..." reason per failed
// rule (the text the manifest's reasons carry after "gate: "); empty means the asset ships.
std::vector<std::string> gate_failures(const samples::Metrics& metrics, const Gate& gate);
// What pooled held-out metrics miss of `target`: one line per missed rule, empty when the
// target is met.
std::vector<std::string> target_misses(const samples::FamilyMetrics& pooled, const Target& target);

// One check of the validation curve (docs/model.md "Validation curve and deciding early"):
// pooled metrics of the validation rays after `step` steps. The manifest's candidates carry
// the curve as [{"step", "visibility", "distance_pct", "normal_deg"}] (validation_json).
struct ValidationPoint {
    std::uint32_t step = 0;
    double visibility = 0;    // fraction of rays whose hit or miss is right
    double distance_pct = 0;  // median distance error, % of the box diagonal
    double normal_deg = 0;    // median normal error, degrees
};
nlohmann::json validation_json(std::span<const ValidationPoint> curve);

// Why a validation point, after `samples` training samples, shows that training cannot
// reach `gate`; empty when it may (or when fewer than rule.min_samples samples were seen).
std::vector<std::string> early_abort_reasons(const ValidationPoint& point, std::uint64_t samples,
                                             const Gate& gate, const EarlyAbort& rule);

// The target training aims at: `target`, made at least as strict as `gate` on each pooled
// rule, since a model that meets a lenient target below the gate still may not ship.
Target effective_target(const Target& target, const Gate& gate);

// Whether a validation point meets `target` with the margins of `rule`.
bool meets_target_with_margin(const ValidationPoint& point, const Target& target, const TargetStop& rule);

// Why a smaller rung, at a validation point, cannot catch up with the target given the larger
// rung's validation curve `larger`; empty when it may. Only steps within the larger curve are
// judged.
std::string falls_behind(const ValidationPoint& point, std::span<const ValidationPoint> larger,
                         const Target& target, const TargetStop& stop, const Sizing& rule);

// What the results of a conversion depend on besides its inputs and settings
// (docs/pipeline.md "Cache keys" argues each part): the sources lsnif was built from, the
// compiler and the flags a user added, and the libraries whose code reaches an asset or a
// record. Not the thread count, the CPU, -march or the build type: the canonical arithmetic
// gives the same bits across those (tested), so the release, portable and packaged builds
// of one source share cache entries. Computed once per process. Part of every cache key.
struct ToolIdentity {
    std::string version;   // lsnif's version
    std::string sources;   // SHA-256 of format/, trainer/, converter/, schema/ and the build files
    std::string compiler;  // "GNU 12.2.0"
    std::string flags;     // CMAKE_CXX_FLAGS (a -ffast-math there would change results)
    std::string embree;    // the Embree library loaded (ground truth, BVH bytes), e.g. "31305"
    std::string zstd;      // the zstd library loaded (the assets' compressed sections)
    std::string json;      // nlohmann_json (numbers in metadata and records)
    std::string digest;    // SHA-256 over all of the above
};
const ToolIdentity& tool_identity();

// The absolute path of the running executable (/proc/self/exe); "" when it cannot be read.
std::string executable_path();

// Human-readable summary of a report (what `lsnif convert` prints).
std::string convert_text(const ConvertResult& result);

// Held-out metrics as the metadata schema stores them.
nlohmann::json metrics_json(const samples::Metrics& m);

}  // namespace lsnif::converter
